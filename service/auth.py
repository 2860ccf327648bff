"""Bearer-token authentication, and the rule that a server without a token stays on loopback.

The token comes from NOISESTOP_TOKEN or from the file NOISESTOP_TOKEN_FILE names (a Docker
or Kubernetes secret). A wrong or missing token gets the same fixed 401 (no hint of which),
and tokens are compared in constant time (hmac.compare_digest) so response timing does not
leak how much of a guess was right.
"""
from __future__ import annotations

import hmac
import ipaddress
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .oip import ApiError

ENV_TOKEN = "NOISESTOP_TOKEN"
ENV_TOKEN_FILE = "NOISESTOP_TOKEN_FILE"
UNAUTHORIZED = "unauthorized"

bearer = HTTPBearer(auto_error=False, description=f"the server's token ({ENV_TOKEN} or {ENV_TOKEN_FILE})")


def resolve_token(token: str | None = None, token_file: str | os.PathLike | None = None,
                  environ: Mapping[str, str] = os.environ) -> str | None:
    """The token to require: explicit arguments first, then the environment; None if none."""
    if token is None and token_file is None:
        token, token_file = environ.get(ENV_TOKEN) or None, environ.get(ENV_TOKEN_FILE) or None
    if token is not None and token_file is not None:
        raise ValueError(f"set either {ENV_TOKEN} or {ENV_TOKEN_FILE}, not both")
    if token_file is not None:
        path = Path(token_file)
        try:
            token = path.read_text(encoding="utf-8").strip()
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: token file ({ENV_TOKEN_FILE}) does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{path}: token file is unreadable ({exc})") from None
        if not token:
            raise ValueError(f"{path}: token file is empty")
    elif token is not None:
        token = token.strip()
        if not token:
            raise ValueError(f"{ENV_TOKEN} is set but empty")
    return token


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None) -> None:
    """Refuse to serve without a token on anything but a loopback address."""
    if token is None and not is_loopback(host):
        raise ValueError(f"refusing to listen on {host!r} without a token: set {ENV_TOKEN} or "
                         f"{ENV_TOKEN_FILE}, or listen on 127.0.0.1")


async def require_token(request: Request,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    """FastAPI dependency: the app's token (app.state.token), if it has one, must be presented."""
    expected: str | None = request.app.state.token
    if expected is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not hmac.compare_digest(given.encode(), expected.encode()):
        raise ApiError(401, UNAUTHORIZED, headers={"WWW-Authenticate": "Bearer"})
