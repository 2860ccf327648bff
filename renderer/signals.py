"""Ctrl-C and SIGTERM during a render: finish the pass, checkpoint, then stop.

The checkpoint is written on a time interval, not after every pass (issue 16), so an
interrupt must not simply kill the loop: the passes since the last checkpoint would be
lost, and an interrupt inside `BlockAccumulator.add_many` would leave a half-added pass.
`DeferredStop` turns the first SIGINT/SIGTERM into a request the loop reads between
passes; a second one stops at once (the default behaviour). SIGKILL cannot be caught:
`--resume` then continues from the last checkpoint, still bit for bit.
"""
from __future__ import annotations

import logging
import signal
import threading
from types import FrameType, TracebackType
from typing import Any

logger = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class DeferredStop:
    """Context manager: ``requested`` is the first signal's name once one arrived.

    Outside the main thread (Dask workers) signals cannot be handled; it then does
    nothing and the process's own handling applies.
    """

    def __init__(self) -> None:
        self.requested: str | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.requested is not None:            # second signal: stop now
            self._restore()
            raise KeyboardInterrupt(f"{name} again: stopped without finishing the pass")
        self.requested = name
        logger.warning("%s: finishing the pass under way, then writing the checkpoint "
                       "(send it again to stop at once)", name)

    def __enter__(self) -> DeferredStop:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._restore()
