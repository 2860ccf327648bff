"""Micro-batching: the infer calls of concurrent requests to one model, answered together.

`serve --batch-window MS` (off by default; BENCHMARKS.md "Verdict service" has the
figures with and without): a request whose tensors are decoded joins the model's pending
batch; the batch runs when a worker slot is free and either `window` seconds have passed
since its first request or it holds `max_items` requests. With a window of 0 a batch is
whatever gathered while the workers were busy (no added wait when the server is idle).
`ServedModel.infer_batch` answers each request as if alone (its own offset, its own errors).
"""
from __future__ import annotations

import asyncio
from typing import Any

import anyio
import anyio.to_thread
import numpy as np

from .oip import ApiError
from .registry import ServedModel

Result = tuple[dict[str, np.ndarray], dict[str, Any]]


class MicroBatcher:
    """Joins concurrent infer calls to one served model (one event loop: no locks)."""

    def __init__(self, served: ServedModel, window: float, slots: anyio.CapacityLimiter,
                 max_items: int = 16) -> None:
        if not 0 <= window <= 1:
            raise ValueError(f"batch window must be 0..1000 ms, got {window * 1e3:g} ms")
        self.served = served
        self.window = window
        self.slots = slots
        self.max_items = max_items
        self._pending: list[tuple[tuple[dict[str, np.ndarray], float, float | None], asyncio.Future]] = []
        self._timer: asyncio.TimerHandle | None = None
        self.batches = 0
        self.batched_requests = 0

    async def infer(self, tensors: dict[str, np.ndarray], exposure: float, offset: float | None) -> Result:
        loop = asyncio.get_running_loop()
        future: asyncio.Future = loop.create_future()
        self._pending.append(((tensors, exposure, offset), future))
        if len(self._pending) >= self.max_items or self.window == 0:
            self._start(loop)
        elif self._timer is None:
            self._timer = loop.call_later(self.window, self._start, loop)
        return await future

    def _start(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        loop.create_task(self._run())

    async def _run(self) -> None:
        async with self.slots:                    # a worker slot first: the batch grows meanwhile
            batch = [(item, f) for item, f in self._pending[:self.max_items] if not f.done()]
            del self._pending[:self.max_items]
            if self._pending and self._timer is None:        # the rest: the next batch
                loop = asyncio.get_running_loop()
                self._timer = loop.call_later(self.window, self._start, loop)
            if not batch:
                return
            self.batches += 1
            self.batched_requests += len(batch)
            try:
                results = await anyio.to_thread.run_sync(self.served.infer_batch, [item for item, _ in batch])
            except Exception as exc:              # a bug: every request of the batch gets it (500)
                results = [exc] * len(batch)
        for (_, future), result in zip(batch, results):
            if future.done():                     # its client went away
                continue
            if isinstance(result, (ApiError, Exception)):
                future.set_exception(result)
            else:
                future.set_result(result)
