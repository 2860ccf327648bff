"""The body's own limits, enforced as it arrives: size, speed, and the memory it holds.

`BodyLimitMiddleware` is plain ASGI so that it guards every route, including those whose
body FastAPI would read itself: a declared Content-Length over the limit is answered 413
at once, and the bytes actually received are counted too (chunked uploads declare no
length, and a client may lie about it). While a body arrives, the bytes received so far
are claimed (in steps of `RESERVE_STEP`) from the upload budget (`UPLOAD_BODIES` bodies of
the largest size; service.memory_budget), given back once the route has claimed the whole
request's cost (service.infer). A body must also arrive within `UploadPolicy.deadline`
seconds, at `UploadPolicy.min_rate` bytes a second at least after a grace period, and
never stall for `UploadPolicy.stall` seconds (service.upload_policy): a slow uploader is
answered 408 instead of holding a request slot and memory.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

import anyio

from .memory_budget import MemoryBudget, busy
from .oip import ApiError
from .upload_policy import ENV_BODY_DEADLINE, ENV_MIN_BODY_RATE, UploadPolicy

#: the memory of a body in flight is claimed in steps of this many bytes as it arrives
RESERVE_STEP = 1 << 20
#: bodies being received may hold this many times --max-body-bytes together (a pool of
#: its own: bodies waiting for the memory budget must not starve the one being decoded)
UPLOAD_BODIES = 4
#: an upload that has sent nothing for this many seconds while other requests wait for the
#: upload budget is ended (408) and its claim given back (burst-then-stall clients held the
#: whole budget for the 30 s stall limit, and every normal request got 503 or 408)
STALL_EVICT = 1.0
#: where BodyLimitMiddleware puts a request's upload claim for the route to hand it over
UPLOAD_CLAIM = "noisestop.upload_claim"


def too_large(limit: int) -> ApiError:
    """The 413 for a body over `limit` bytes (declared or received)."""
    return ApiError(413, f"request body exceeds the limit of {limit} bytes",
                    headers={"Connection": "close"})


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
