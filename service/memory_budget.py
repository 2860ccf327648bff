"""Admission by memory: requests in flight claim bytes of a budget, or wait, or get 503.

Memory is claimed in two steps, from two `MemoryBudget`s, so that no request holds what it
does not use: while a body arrives, the bytes received so far from the upload budget
(service.body_limit); once it is complete, its bytes plus what decoding and classifying it
will take (service.memory_cost) from the memory budget (service.infer), its upload claim
then given back. A request whose estimate is over the whole budget gets 413 at once,
unparsed.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import anyio

from .limits import ENV_MEMORY_BUDGET
from .oip import ApiError

#: how often a claim waiting for the budget looks for stalled holders to end (seconds)
RECLAIM_POLL = 0.25


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


def busy(what: str) -> ApiError:
    """The 503 for a claim the budget did not grant in time (`what`: what was claimed)."""
    return ApiError(503, f"server busy: the memory for requests in flight is taken ({what}; serve "
                         f"--memory-budget, {ENV_MEMORY_BUDGET}); retry",
                    headers={"Retry-After": "1", "Connection": "close"})
