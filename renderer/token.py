"""Where the bearer token of a verdict server comes from: one rule for the server
(`service.auth`) and its client (`renderer.client`).

An explicit token or token file first, else NOISESTOP_TOKEN or the file NOISESTOP_TOKEN_FILE
names (a Docker or Kubernetes secret). Both set is a mistake, refused on both sides (before,
the client let the variable win while the server refused), and an empty token is never
taken for "no token": a variable that is set but empty (`NOISESTOP_TOKEN=`, or
`NOISESTOP_TOKEN_FILE=`), a token of spaces and an empty token file are all refused. Only
variables that are not set at all mean "no token" (which `noisestop serve` then accepts
only with `--no-auth`, on loopback).
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from noisefeat.safeio import InputFileError, read_text

ENV_TOKEN = "NOISESTOP_TOKEN"
ENV_TOKEN_FILE = "NOISESTOP_TOKEN_FILE"


def resolve_token(token: str | None = None, token_file: str | os.PathLike | None = None,
                  environ: Mapping[str, str] = os.environ) -> str | None:
    """The token to require: explicit arguments first, then the environment; None if none."""
    if token is None and token_file is None:
        token, token_file = environ.get(ENV_TOKEN), environ.get(ENV_TOKEN_FILE)
    if token is not None and token_file is not None:
        raise ValueError(f"set either {ENV_TOKEN} or {ENV_TOKEN_FILE}, not both")
    if token_file is not None and not str(token_file).strip():
        raise ValueError(f"{ENV_TOKEN_FILE} (or --token-file) is set but empty: name the token file, "
                         "or unset it")
    if token_file is not None:
        path = Path(token_file)
        try:
            token = read_text(path, "token file").strip()
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: token file ({ENV_TOKEN_FILE}) does not exist") from None
        except InputFileError as exc:
            raise ValueError(f"{exc} ({ENV_TOKEN_FILE})") from None
        except OSError as exc:
            raise ValueError(f"{path}: token file is unreadable ({exc})") from None
        if not token:
            raise ValueError(f"{path}: token file is empty")
    elif token is not None:
        token = token.strip()
        if not token:
            raise ValueError(f"{ENV_TOKEN} is set but empty (a token of spaces is no token): set it, "
                             "or unset it")
    return token
