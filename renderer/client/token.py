"""Where a verdict server's bearer token comes from: one rule for the server (`service.auth`)
and its client.

An explicit token or token file first, else NOISESTOP_TOKEN or the file NOISESTOP_TOKEN_FILE
names (a Docker or Kubernetes secret); both set is refused. Only unset variables mean "no
token": an empty one, a token of spaces, an empty file and a token that is not one line of
visible ASCII (a file may end with one newline) are refused, naming where it came from, never
showing it.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from noisefeat.safeio import InputFileError, read_input

ENV_TOKEN = "NOISESTOP_TOKEN"
ENV_TOKEN_FILE = "NOISESTOP_TOKEN_FILE"


def resolve_token(token: str | None = None, token_file: str | os.PathLike | None = None,
                  environ: Mapping[str, str] = os.environ) -> str | None:
    """The token to require: explicit arguments first, then the environment; None if none."""
    from_env = token is None and token_file is None
    if from_env:
        token, token_file = environ.get(ENV_TOKEN), environ.get(ENV_TOKEN_FILE)
    token_where, file_where = (ENV_TOKEN, ENV_TOKEN_FILE) if from_env else ("the token argument", "--token-file")
    if token is not None and token_file is not None:
        raise ValueError(f"set either {token_where} or {file_where}, not both")
    if token_file is not None and not str(token_file).strip():
        raise ValueError(f"{file_where} is set but empty: name the token file, or unset it")
    if token_file is not None:
        path = Path(token_file)
        try:
            raw = read_input(path, "token file")
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: token file ({file_where}) does not exist") from None
        except InputFileError as exc:
            raise ValueError(f"{exc} ({file_where})") from None
        except OSError as exc:
            raise ValueError(f"{path}: token file ({file_where}) is unreadable ({exc})") from None
        if not raw.strip():
            raise ValueError(f"{path}: token file ({file_where}) is empty")
        line = raw[:-2] if raw.endswith(b"\r\n") else raw[:-1] if raw.endswith(b"\n") else raw
        check_token(line, f"{path}: token file ({file_where})")
        token = line.decode("ascii")
    elif token is not None:
        if not token.strip():
            raise ValueError(f"{token_where} is set but empty (a token of spaces is no token): set it, "
                             "or unset it")
        check_token(token, f"the token ({token_where})")
    return token


def check_token(token: str | bytes, where: str) -> None:
    """One-line ValueError, naming `where` and never showing the token, unless `token` is
    one line of visible ASCII characters (what an HTTP ``Authorization`` header carries)."""
    data = token.encode("utf-8", "replace") if isinstance(token, str) else token
    if not data or all(0x21 <= b <= 0x7E for b in data):
        return
    lines = data.count(b"\n") + 1
    what = f"it has {lines} lines" if lines > 1 else "it holds a space, a control or a non-ASCII character"
    raise ValueError(f"{where} must be one line of visible ASCII characters (a trailing newline "
                     f"allowed); {what} (the token is not shown)")
