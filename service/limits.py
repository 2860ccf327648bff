"""Request size limits, enforced before a body is decoded.

`BodyLimitMiddleware` is plain ASGI so that it guards every route, including those whose
body FastAPI would read itself: a declared Content-Length over the limit is answered 413
at once, and the bytes actually received are counted too (chunked uploads declare no
length, and a client may lie about it). The batch limit (items per request), the largest
block side and the pixel budget of a request (noisefeat.bounds: a 3.8 MB request of
[1, 8, 40000, 3] once took the server to 23.7 GB) are checked on the declared tensor
shapes, before any tensor data is converted (`Limits.check_shapes`, oip.decode_tensors).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import json
import os
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import anyio

from noisefeat.bounds import DEFAULT_MAX_BLOCK_SIDE, DEFAULT_MAX_PIXELS, ENV as BOUNDS_ENV, MIN_SIDE, env_int

from .oip import ApiError, RequestInput

ENV_MAX_BODY = "NOISESTOP_MAX_BODY_BYTES"
ENV_MAX_BATCH = "NOISESTOP_MAX_BATCH"
ENV_MAX_BLOCK_SIDE = BOUNDS_ENV["max_block_side"]
ENV_MAX_PIXELS = BOUNDS_ENV["max_pixels"]
ENV_MEMORY_BUDGET = "NOISESTOP_MEMORY_BUDGET"
DEFAULT_MAX_BODY = 64 * 1024 * 1024   # 16 blocks of 128x128 + quick as JSON take ~30 MB
DEFAULT_MAX_BATCH = 1024
#: working memory a request takes per byte of its body, at its peak (measured, BENCHMARKS.md
#: "Reliability under attack": binary tensors ~10x, JSON ~15x: parsed numbers are Python
#: objects), plus a fixed part
MEMORY_PER_BODY_BYTE = 16
MEMORY_PER_REQUEST = 1 << 20
#: by default one request of the largest body at a time, or many smaller ones at once
DEFAULT_MEMORY_BUDGET = MEMORY_PER_BODY_BYTE * DEFAULT_MAX_BODY + MEMORY_PER_REQUEST


@dataclass(frozen=True)
class Limits:
    max_body_bytes: int = DEFAULT_MAX_BODY
    max_batch: int = DEFAULT_MAX_BATCH
    max_block_side: int = DEFAULT_MAX_BLOCK_SIDE
    max_pixels: int = DEFAULT_MAX_PIXELS
    #: working memory all requests in flight may claim together (None: the cost of one
    #: request of the largest body); see `MemoryBudget`
    memory_budget: int | None = None

    def __post_init__(self) -> None:
        for name in ("max_body_bytes", "max_batch", "max_block_side", "max_pixels"):
            value = getattr(self, name)
            least = MIN_SIDE if name in ("max_block_side", "max_pixels") else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"{name} must be a whole number >= {least}, got {value!r}")
        if self.memory_budget is None:
            object.__setattr__(self, "memory_budget", request_cost(self.max_body_bytes))
        elif isinstance(self.memory_budget, bool) or not isinstance(self.memory_budget, int) \
                or self.memory_budget < request_cost(self.max_body_bytes):
            raise ValueError(f"memory_budget must be a whole number of bytes >= {request_cost(self.max_body_bytes)} "
                             f"(what one request of max_body_bytes = {self.max_body_bytes} may take), "
                             f"got {self.memory_budget!r}")

    @classmethod
    def from_env(cls, max_body_bytes: int | None = None, max_batch: int | None = None,
                 environ: Mapping[str, str] = os.environ, *, max_block_side: int | None = None,
                 max_pixels: int | None = None, memory_budget: int | None = None) -> "Limits":
        """Explicit values win over the environment, which wins over the defaults."""
        def env(key: str, default: int) -> int:
            return env_int(environ, key, default, minimum=1)
        budget = memory_budget or (env(ENV_MEMORY_BUDGET, 0) or None)
        return cls(max_body_bytes=max_body_bytes or env(ENV_MAX_BODY, DEFAULT_MAX_BODY),
                   max_batch=max_batch or env(ENV_MAX_BATCH, DEFAULT_MAX_BATCH),
                   max_block_side=max_block_side or env(ENV_MAX_BLOCK_SIDE, DEFAULT_MAX_BLOCK_SIDE),
                   max_pixels=max_pixels or env(ENV_MAX_PIXELS, DEFAULT_MAX_PIXELS),
                   memory_budget=budget)

    def check_shapes(self, inputs: list[RequestInput]) -> None:
        """413 for an image tensor [N, H, W, C] whose block side or pixel count (N x H x W)
        is over the limit, judged on its declared shape alone."""
        for t in inputs:
            if len(t.shape) != 4:
                continue
            n, h, w = t.shape[:3]
            if max(h, w) > self.max_block_side:
                raise ApiError(413, f"input {t.name!r}: blocks of {h}x{w} pixels exceed the largest block "
                                    f"side of this server, max_block_side = {self.max_block_side} "
                                    f"(serve --max-block-side, {ENV_MAX_BLOCK_SIDE})")
            if n * h * w > self.max_pixels:
                raise ApiError(413, f"input {t.name!r}: {n} blocks of {h}x{w} are {n * h * w} pixels, over "
                                    f"the pixel budget of a request, max_pixels = {self.max_pixels} "
                                    f"(serve --max-pixels, {ENV_MAX_PIXELS}); send fewer blocks per request")


def request_cost(body_bytes: int) -> int:
    """Working memory a request of `body_bytes` is counted for (`MEMORY_PER_BODY_BYTE`)."""
    return MEMORY_PER_BODY_BYTE * body_bytes + MEMORY_PER_REQUEST


class MemoryBudget:
    """Admission by memory: requests in flight claim `request_cost(body)` bytes of `total`
    before their body is read, first come first served, and give them back when answered.

    Why: limits per request bound one request; without this, 64 requests in flight of the
    largest body would still take 64 times that. A request waits (its upload held back by
    TCP flow control) while the budget is taken, and is answered 503 after `timeout`
    seconds. One event loop: no lock is needed."""

    def __init__(self, total: int, timeout: float = 30.0) -> None:
        self.total = total
        self.timeout = timeout
        self.used = 0
        self._waiters: deque[tuple[int, anyio.Event]] = deque()

    async def acquire(self, n: int) -> bool:
        """Claim n bytes (n <= total); False if not granted within the timeout."""
        if not self._waiters and self.used + n <= self.total:
            self.used += n
            return True
        entry = (n, anyio.Event())
        self._waiters.append(entry)
        with anyio.move_on_after(self.timeout):
            await entry[1].wait()
        if entry[1].is_set():            # granted (possibly just as the time ran out)
            return True
        self._waiters.remove(entry)
        self._grant()
        return False

    def release(self, n: int) -> None:
        self.used -= n
        self._grant()

    def _grant(self) -> None:
        while self._waiters and self.used + self._waiters[0][0] <= self.total:
            n, event = self._waiters.popleft()
            self.used += n
            event.set()


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


@functools.cache
def _libc() -> tuple[Callable[[int], int] | None, Callable[[], _MallInfo2] | None]:
    """glibc's malloc_trim and mallinfo2 (None where missing: not glibc, or glibc < 2.33)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None, None
    trim = getattr(libc, "malloc_trim", None)
    info = getattr(libc, "mallinfo2", None)
    if info is not None:
        info.restype = _MallInfo2
    return trim, info


#: free heap bytes above which `release_memory` trims the heap
RELEASE_ABOVE = 64 * 1024 * 1024


def release_memory(above: int = RELEASE_ABOVE) -> bool:
    """Give the heap's free pages back to the system after a request when more than `above`
    bytes of it are free (glibc keeps them, so the resident size would stay at its
    high-water mark and the next large request would start from there). True if trimmed.

    Why not after every request (as issue 14 first did): trimming the few tens of MB an
    ordinary request frees makes the next one fault them all back in; for 16 blocks of
    128x128 that was 7.6 ms of CPU a request (issue 16, measured). Large requests, the
    ones issue 14 was about, still leave a trimmed heap. Without mallinfo2: always trims."""
    trim, info = _libc()
    if trim is None:
        return False
    if info is not None and info().fordblks <= above:
        return False
    trim(0)
    return True


def too_large(limit: int) -> ApiError:
    return ApiError(413, f"request body exceeds the limit of {limit} bytes",
                    headers={"Connection": "close"})


class BodyLimitMiddleware:
    """413 for bodies over `max_bytes`, by declared length first, then by bytes received;
    408 when a body stops arriving for `body_timeout` seconds (a slow upload otherwise
    holds a request slot for as long as the client likes)."""

    def __init__(self, app: Any, max_bytes: int, body_timeout: float | None = None,
                 budget: MemoryBudget | None = None) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.body_timeout = body_timeout
        self.budget = budget

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
        cost = 0
        if self.budget is not None and scope.get("method") in ("POST", "PUT", "PATCH"):
            cost = request_cost(self.max_bytes if declared is None else length)
            if not await self.budget.acquire(cost):
                await _send_error(send, ApiError(503, "server busy: the memory for requests in flight is taken "
                                                      f"(serve --memory-budget, {ENV_MEMORY_BUDGET}); retry",
                                                 headers={"Retry-After": "1"}))
                return
        try:
            await self._guarded(scope, receive, send)
        finally:
            if cost:
                self.budget.release(cost)

    async def _guarded(self, scope: dict, receive: Any, send: Any) -> None:
        received = 0
        body_done = False

        async def counting_receive() -> dict:
            nonlocal received, body_done
            if body_done or self.body_timeout is None:
                message = await receive()
            else:
                try:
                    with anyio.fail_after(self.body_timeout):
                        message = await receive()
                except TimeoutError:
                    raise ApiError(408, f"no request body bytes for {self.body_timeout:g} s "
                                        "(serve --body-timeout)", headers={"Connection": "close"}) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
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
