"""Request size limits, enforced before a body is decoded.

`BodyLimitMiddleware` is plain ASGI so that it guards every route, including those whose
body FastAPI would read itself: a declared Content-Length over the limit is answered 413
at once, and the bytes actually received are counted too (chunked uploads declare no
length, and a client may lie about it). The batch limit (items per request), the largest
block side and the pixel budget of a request (noisefeat.bounds: a 3.8 MB request of
[1, 8, 40000, 3] once took the server to 23.7 GB) are checked on the declared tensor
shapes, before any tensor data is converted (`Limits.check_shapes`, oip.decode_tensors).

Memory is claimed in two steps, from two `MemoryBudget`s, so that no request holds what it
does not use: while a body arrives, the bytes received so far (in steps of `RESERVE_STEP`)
from the upload budget (`UPLOAD_BODIES` bodies of the largest size); once it is complete,
its bytes plus what decoding and classifying it will take from the memory budget (its
upload claim is then given back), estimated from the body itself before any parsing (`decode_cost`: binary tensors at `MEMORY_PER_BODY_BYTE` a byte, JSON
from a count of its brackets, commas and colons, the costs measured for the worst shapes).
A request whose estimate is over the whole budget gets 413 at once, unparsed. A body must
also arrive within `UploadPolicy.deadline` seconds, at `UploadPolicy.min_rate` bytes a
second at least after a grace period, and never stall for `UploadPolicy.stall` seconds:
a slow uploader is answered 408 instead of holding a request slot and memory.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import anyio

from noisefeat.bounds import DEFAULT_MAX_BLOCK_SIDE, DEFAULT_MAX_PIXELS, ENV as BOUNDS_ENV, MIN_SIDE, env_int, env_seconds

from .oip import ApiError, RequestInput

ENV_MAX_BODY = "NOISESTOP_MAX_BODY_BYTES"
ENV_MAX_BATCH = "NOISESTOP_MAX_BATCH"
ENV_MAX_BLOCK_SIDE = BOUNDS_ENV["max_block_side"]
ENV_MAX_PIXELS = BOUNDS_ENV["max_pixels"]
ENV_MEMORY_BUDGET = "NOISESTOP_MEMORY_BUDGET"
ENV_BODY_DEADLINE = "NOISESTOP_BODY_DEADLINE"
ENV_MIN_BODY_RATE = "NOISESTOP_MIN_BODY_RATE"
ENV_BODY_GRACE = "NOISESTOP_BODY_GRACE"
DEFAULT_MAX_BODY = 64 * 1024 * 1024   # 16 blocks of 128x128 + quick as JSON take ~30 MB
DEFAULT_MAX_BATCH = 1024
#: working memory a request of binary tensors takes per byte of its body, at its peak, the
#: body included (measured ~10x, BENCHMARKS.md "Reliability under attack"), plus a fixed part
MEMORY_PER_BODY_BYTE = 16
MEMORY_PER_REQUEST = 1 << 20
#: what parsing and decoding JSON costs, in bytes, per opening bracket or brace (a list or
#: dict object, its slot in its parent, numpy's walk of it), per comma or colon (a number
#: object and its slot, or a dict entry) and per byte of text (strings). Measured peak
#: working memory over the body, full decode (BENCHMARKS.md "Hardening, second
#: round"): 20 nested lists around each number 52x (this estimate: 60x), [1] 31x (48x),
#: {} 28x (64x), {"a":1} 26x (32x), flat 3-digit integers 13x (16x), floats of 9 digits
#: 4.3x (5.3x), whitespace and long number strings ~0x (1x).
JSON_COST_PER_CONTAINER = 128
JSON_COST_PER_ITEM = 64
JSON_COST_PER_BYTE = 1
#: the memory of a body in flight is claimed in steps of this many bytes as it arrives
RESERVE_STEP = 1 << 20
#: bodies being received may hold this many times --max-body-bytes together (a pool of
#: its own: bodies waiting for the memory budget must not starve the one being decoded)
UPLOAD_BODIES = 4
#: an upload that has sent nothing for this many seconds while other requests wait for the
#: upload budget is ended (408) and its claim given back (burst-then-stall clients held the
#: whole budget for the 30 s stall limit, and every normal request got 503 or 408)
STALL_EVICT = 1.0
#: how often a claim waiting for the budget looks for stalled holders to end (seconds)
RECLAIM_POLL = 0.25
#: where BodyLimitMiddleware puts a request's upload claim for the route to hand it over
UPLOAD_CLAIM = "noisestop.upload_claim"
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
    """Working memory a binary request of `body_bytes` is counted for, body included
    (`MEMORY_PER_BODY_BYTE`): the least budget that admits one request of the largest body."""
    return MEMORY_PER_BODY_BYTE * body_bytes + MEMORY_PER_REQUEST


def json_cost(text: bytes | bytearray) -> int:
    """Working memory parsing and decoding this JSON text may take, from a byte count
    alone (no parsing; ~10 ms for 30 MB). Brackets, commas and colons inside strings are
    counted too: the estimate errs on the high side, never the low."""
    from .jsonguard import CHUNK, SCAN_BYTES_PER_BYTE

    containers = text.count(b"[") + text.count(b"{")
    items = text.count(b",") + text.count(b":")
    # plus the depth scan's working arrays (`jsonguard`), which run before the parser
    return JSON_COST_PER_CONTAINER * containers + JSON_COST_PER_ITEM * items + JSON_COST_PER_BYTE * len(text) \
        + SCAN_BYTES_PER_BYTE * min(len(text), CHUNK)


def decode_cost(body: bytes | bytearray | memoryview, header_length: int | None) -> int:
    """Working memory a complete request body will take beyond the body itself, estimated
    before any parsing: its JSON by `json_cost`, its binary tensors at
    `MEMORY_PER_BODY_BYTE` - 1 a byte (the body is already counted as it arrived)."""
    if header_length is None:
        head, tail = bytes(body) if isinstance(body, memoryview) else body, 0
    else:
        head = bytes(memoryview(body)[:max(0, min(header_length, len(body)))])
        tail = len(body) - len(head)
    return MEMORY_PER_REQUEST + json_cost(head) + (MEMORY_PER_BODY_BYTE - 1) * tail


@dataclass(frozen=True)
class UploadPolicy:
    """How fast a request body must arrive (seconds; bytes a second). None: no such limit.

    `stall`: longest wait for the next bytes; `deadline`: the whole body, from its
    headers; `min_rate`: after `grace` seconds, the body must have averaged this rate
    since then (bytes received >= min_rate x (elapsed - grace))."""
    stall: float | None = 30.0
    deadline: float | None = 120.0
    min_rate: int | None = 64 * 1024
    grace: float = 10.0

    def __post_init__(self) -> None:
        for name in ("stall", "deadline"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not 0 < value <= 86400):
                raise ValueError(f"{name} must be a number of seconds in (0, 86400], got {value!r}")
        if isinstance(self.grace, bool) or not isinstance(self.grace, (int, float)) or not 0 <= self.grace <= 86400:
            raise ValueError(f"grace must be a number of seconds in [0, 86400], got {self.grace!r}")
        if self.min_rate is not None and (isinstance(self.min_rate, bool) or not isinstance(self.min_rate, int)
                                          or self.min_rate < 1):
            raise ValueError(f"min_rate must be a whole number of bytes a second >= 1, got {self.min_rate!r}")

    @classmethod
    def from_env(cls, stall: float | None = 30.0, deadline: float | None = None, min_rate: int | None = None,
                 grace: float | None = None, environ: Mapping[str, str] = os.environ) -> "UploadPolicy":
        """Explicit values win over NOISESTOP_BODY_DEADLINE / NOISESTOP_MIN_BODY_RATE /
        NOISESTOP_BODY_GRACE, which win over the defaults (120 s, 64 KiB/s, 10 s)."""
        return cls(stall=stall,
                   deadline=deadline if deadline is not None else env_seconds(environ, ENV_BODY_DEADLINE, 120.0,
                                                                              86400),
                   min_rate=min_rate if min_rate is not None else env_int(environ, ENV_MIN_BODY_RATE, 64 * 1024,
                                                                          minimum=1),
                   grace=grace if grace is not None else env_seconds(environ, ENV_BODY_GRACE, 10.0, 86400,
                                                                     zero=True))


class MemoryBudget:
    """Admission by memory: requests in flight claim `request_cost(body)` bytes of `total`
    before their body is read, first come first served, and give them back when answered.

    Why: limits per request bound one request; without this, 64 requests in flight of the
    largest body would still take 64 times that. A request waits (its upload held back by
    TCP flow control) while the budget is taken, and is answered 503 after `timeout`
    seconds. One event loop: no lock is needed."""

    def __init__(self, total: int, timeout: float = 30.0,
                 reclaim: Callable[[int], None] | None = None) -> None:
        self.total = total
        self.timeout = timeout
        self.used = 0
        self.reclaim = reclaim      # (rank) called while a claim of that rank waits: ends holders to free memory
        self._waiters: list[tuple[int, anyio.Event, int, int]] = []
        self._seq = 0

    async def acquire(self, n: int, rank: int = 0) -> bool:
        """Claim n bytes (n <= total); False if not granted within the timeout. Waiting
        claims are granted smallest `rank` first, then first come first served (the
        upload budget ranks by declared body size: a stream of large bodies that stall
        must not keep small ones waiting behind them)."""
        if self.used + n <= self.total and all(rank < w[2] for w in self._waiters):
            self.used += n
            return True
        self._seq += 1
        entry = (n, anyio.Event(), rank, self._seq)
        self._waiters.append(entry)
        deadline = time.monotonic() + self.timeout
        try:
            while not entry[1].is_set() and time.monotonic() < deadline:
                if self.reclaim is not None:
                    self.reclaim(rank)
                with anyio.move_on_after(min(RECLAIM_POLL, max(0.0, deadline - time.monotonic()))):
                    await entry[1].wait()
        except BaseException:            # cancelled (preempted, or the request ended)
            if entry[1].is_set():
                self.release(n)
            else:
                self._waiters.remove(entry)
                self._grant()
            raise
        if entry[1].is_set():            # granted (possibly just as the time ran out)
            return True
        self._waiters.remove(entry)
        self._grant()
        return False

    def release(self, n: int) -> None:
        self.used -= n
        self._grant()

    def _grant(self) -> None:
        while self._waiters:
            first = min(self._waiters, key=lambda w: (w[2], w[3]))
            if self.used + first[0] > self.total:
                return
            self._waiters.remove(first)
            self.used += first[0]
            first[1].set()


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

    Why not after every request: trimming the few tens of MB an
    ordinary request frees makes the next one fault them all back in; for 16 blocks of
    128x128 that was 7.6 ms of CPU a request (measured). Large requests, the ones that
    matter for memory, still leave a trimmed heap. Without mallinfo2: always trims."""
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


def busy(what: str) -> ApiError:
    return ApiError(503, f"server busy: the memory for requests in flight is taken ({what}; serve "
                         f"--memory-budget, {ENV_MEMORY_BUDGET}); retry",
                    headers={"Retry-After": "1", "Connection": "close"})


class BodyLimitMiddleware:
    """413 for bodies over `max_bytes`, by declared length first, then by bytes received;
    408 for a body that arrives too slowly (`UploadPolicy`: a stall, the whole-body
    deadline, the minimum rate after the grace period), so that a slow upload cannot hold
    a request slot for as long as the client likes. With a `budget`, the bytes received
    are claimed from it as they arrive (`RESERVE_STEP` at a time) and given back when the
    request is answered: a slow uploader holds what it has sent, not what it declared."""

    def __init__(self, app: Any, max_bytes: int, body_timeout: float | None = None,
                 budget: MemoryBudget | None = None, upload: UploadPolicy | None = None) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.upload = upload or UploadPolicy(stall=body_timeout, deadline=None, min_rate=None)
        self.budget = budget
        self._receiving: dict[int, _Upload] = {}     # uploads now waiting for their next bytes
        if budget is not None and budget.reclaim is None:
            budget.reclaim = self.evict_stalled

    def evict_stalled(self, rank: int | None = None) -> int:
        """Free upload memory for a claim of `rank` that waits: end every upload that holds
        budget and has sent nothing for `STALL_EVICT` s (answered 408), and every upload of
        a larger rank that holds budget while it waits for more (answered 503: holding
        while waiting is how a few large bodies deadlock the budget). The number ended."""
        now = time.monotonic()
        ended = 0
        for up in list(self._receiving.values()):
            stalled = now - up.last >= STALL_EVICT
            blocking = up.waiting and rank is not None and up.rank > rank
            if up.held[0] > 0 and (stalled or blocking) and not up.evicted:
                up.evicted = True
                up.scope.cancel()
                ended += 1
        return ended

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
        held = [0]
        rank = length if declared is not None else self.max_bytes     # smaller bodies first
        scope[UPLOAD_CLAIM] = held      # the infer route gives it back once the body is decoded
        try:
            await self._guarded(scope, receive, send, held, rank)
        finally:
            if held[0] and self.budget is not None:
                self.budget.release(held[0])

    async def _guarded(self, scope: dict, receive: Any, send: Any, held: list[int], rank: int) -> None:
        received = 0
        body_done = False
        policy = self.upload
        start = time.monotonic()
        last = start

        def wait_limit() -> tuple[float | None, str]:
            """Seconds the next bytes may take, and the rule that would be broken."""
            now = time.monotonic()
            limits = []
            if policy.stall is not None:
                limits.append((policy.stall, f"no request body bytes for {policy.stall:g} s (serve --body-timeout)"))
            if policy.deadline is not None:
                limits.append((start + policy.deadline - now,
                               f"request body not complete after {policy.deadline:g} s (serve --body-deadline, "
                               f"{ENV_BODY_DEADLINE})"))
            if policy.min_rate is not None:
                limits.append((start + policy.grace + (received + 1) / policy.min_rate - now,
                               f"request body slower than {policy.min_rate} bytes/s after {policy.grace:g} s "
                               f"(serve --min-body-rate, {ENV_MIN_BODY_RATE})"))
            if not limits:
                return None, ""
            return min(limits, key=lambda x: x[0])

        async def counting_receive() -> dict:
            nonlocal received, body_done, start, last
            if body_done:
                return await receive()
            seconds, rule = wait_limit()
            up = _Upload(held, last, anyio.CancelScope(), rank)
            self._receiving[id(up)] = up
            try:
                with up.scope:
                    if seconds is None:
                        message = await receive()
                    else:
                        if seconds <= 0:
                            raise TimeoutError
                        with anyio.fail_after(seconds):
                            message = await receive()
            except TimeoutError:
                raise ApiError(408, rule, headers={"Connection": "close"}) from None
            finally:
                del self._receiving[id(up)]
            if up.evicted and up.scope.cancelled_caught:
                raise ApiError(408, f"request body stalled for over {STALL_EVICT:g} s while other requests "
                                    "waited for upload memory", headers={"Connection": "close"})
            last = time.monotonic()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if received > self.max_bytes:
                    raise too_large(self.max_bytes)  # rendered by the app's ApiError handler
                if self.budget is not None and held[0] < received:
                    step = min(max(RESERVE_STEP, received - held[0]), self.budget.total)
                    t0 = time.monotonic()
                    up = _Upload(held, last, anyio.CancelScope(), rank, waiting=True)
                    self._receiving[id(up)] = up
                    granted = False
                    try:
                        with up.scope:
                            granted = await self.budget.acquire(step, rank)
                    finally:
                        del self._receiving[id(up)]
                    if not granted:
                        raise busy(f"{received} body bytes received" + (
                            "; smaller requests were waiting" if up.evicted else ""))
                    held[0] += step
                    waited = time.monotonic() - t0      # the server's wait, not the client's:
                    start += waited                     # not counted against its deadline or rate
                    last = time.monotonic()
            return message

        await self.app(scope, counting_receive, send)


@dataclass
class _Upload:
    """An upload waiting for its next bytes or for more budget: its claim, when bytes last
    came, its rank (declared size), how to end it."""
    held: list[int]
    last: float
    scope: anyio.CancelScope
    rank: int = 0
    waiting: bool = False        # for budget (holding some), not for bytes
    evicted: bool = False


async def _send_error(send: Any, err: ApiError) -> None:
    body = json.dumps({"error": err.message}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    headers += [(k.lower().encode(), v.encode()) for k, v in (err.headers or {}).items()]
    await send({"type": "http.response.start", "status": err.status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
