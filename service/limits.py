"""Request size limits, enforced before a body is decoded.

`BodyLimitMiddleware` is plain ASGI so that it guards every route, including those whose
body FastAPI would read itself: a declared Content-Length over the limit is answered 413
at once, and the bytes actually received are counted too (chunked uploads declare no
length, and a client may lie about it). The batch limit (items per request) is checked
on the declared tensor shapes, before any tensor data is converted (oip.decode_tensors).
"""
from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from .oip import ApiError

ENV_MAX_BODY = "NOISESTOP_MAX_BODY_BYTES"
ENV_MAX_BATCH = "NOISESTOP_MAX_BATCH"
DEFAULT_MAX_BODY = 64 * 1024 * 1024   # 16 blocks of 128x128 + quick as JSON take ~30 MB
DEFAULT_MAX_BATCH = 1024


@dataclass(frozen=True)
class Limits:
    max_body_bytes: int = DEFAULT_MAX_BODY
    max_batch: int = DEFAULT_MAX_BATCH

    def __post_init__(self) -> None:
        for name in ("max_body_bytes", "max_batch"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")

    @classmethod
    def from_env(cls, max_body_bytes: int | None = None, max_batch: int | None = None,
                 environ: Mapping[str, str] = os.environ) -> "Limits":
        """Explicit values win over the environment, which wins over the defaults."""
        return cls(max_body_bytes=max_body_bytes or _env_int(environ, ENV_MAX_BODY, DEFAULT_MAX_BODY),
                   max_batch=max_batch or _env_int(environ, ENV_MAX_BATCH, DEFAULT_MAX_BATCH))


def _env_int(environ: Mapping[str, str], key: str, default: int) -> int:
    text = environ.get(key, "").strip()
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{key}={text!r}: expected a whole number") from None
    if value < 1:
        raise ValueError(f"{key}={value}: expected a number >= 1")
    return value


def too_large(limit: int) -> ApiError:
    return ApiError(413, f"request body exceeds the limit of {limit} bytes",
                    headers={"Connection": "close"})


class BodyLimitMiddleware:
    """413 for bodies over `max_bytes`, by declared length first, then by bytes received."""

    def __init__(self, app: Any, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:
            try:
                length = int(declared)
            except ValueError:
                length = -1
            if length < 0:
                await _send_error(send, ApiError(400, "invalid Content-Length header"))
                return
            if length > self.max_bytes:
                await _send_error(send, too_large(self.max_bytes))
                return
        received = 0

        async def counting_receive() -> dict:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise too_large(self.max_bytes)  # rendered by the app's ApiError handler
            return message

        await self.app(scope, counting_receive, send)


async def _send_error(send: Any, err: ApiError) -> None:
    body = json.dumps({"error": err.message}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in (err.headers or {}).items()]
    await send({"type": "http.response.start", "status": err.status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
