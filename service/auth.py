"""Bearer-token authentication, and the rule that a server runs without a token only when
asked to (`serve --no-auth`), and then on loopback only.

The token comes from NOISESTOP_TOKEN or from the file NOISESTOP_TOKEN_FILE names (a Docker
or Kubernetes secret; the rule is `renderer.client.token`, shared with the client). A wrong or missing token gets the same fixed 401 (no hint of which),
and tokens are compared in constant time (hmac.compare_digest) so response timing does not
leak how much of a guess was right.
"""
from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from renderer.client.token import ENV_TOKEN, ENV_TOKEN_FILE, resolve_token

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


def check_bind(host: str, token: str | None, no_auth: bool = False) -> None:
    """Refuse to serve without a token unless `no_auth` says so, and never without one on
    anything but a loopback address; refuse a token together with `no_auth` (which of the
    two was meant is not for the server to guess)."""
    if no_auth and token is not None:
        raise ValueError(f"--no-auth given but a token is set ({ENV_TOKEN} / {ENV_TOKEN_FILE} / "
                         "--token-file): drop one of them")
    if token is None and not is_loopback(host):
        raise ValueError(f"refusing to listen on {host!r} without a token: set {ENV_TOKEN} or "
                         f"{ENV_TOKEN_FILE} (--no-auth is for loopback only)")
    if token is None and not no_auth:
        raise ValueError(f"no token: set {ENV_TOKEN} (or {ENV_TOKEN_FILE}, --token-file), or pass "
                         "--no-auth to serve without one on loopback")


async def require_token(request: Request,
                        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    """FastAPI dependency: the app's token (app.state.token), if it has one, must be presented."""
    expected: str | None = request.app.state.token
    if expected is None:
        return
    given = credentials.credentials if credentials is not None else ""
    if not hmac.compare_digest(given.encode(), expected.encode()):
        raise ApiError(401, UNAUTHORIZED, headers={"WWW-Authenticate": "Bearer"})
