"""Bearer-token authentication, and the rule that a server without a token stays on loopback.

The token comes from NOISESTOP_TOKEN or from the file NOISESTOP_TOKEN_FILE names (a Docker
or Kubernetes secret; the rule is `renderer.token`, shared with the client). A wrong or missing token gets the same fixed 401 (no hint of which),
and tokens are compared in constant time (hmac.compare_digest) so response timing does not
leak how much of a guess was right.
"""
from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from renderer.token import ENV_TOKEN, ENV_TOKEN_FILE, resolve_token

from .oip import ApiError

__all__ = ["ENV_TOKEN", "ENV_TOKEN_FILE", "resolve_token", "check_bind", "is_loopback", "bearer"]

UNAUTHORIZED = "unauthorized"

bearer = HTTPBearer(auto_error=False, description=f"the server's token ({ENV_TOKEN} or {ENV_TOKEN_FILE})")


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
