"""Ctrl-C and SIGTERM during a render: finish the pass, checkpoint, then stop (killing the loop would
lose the passes since the last timed checkpoint, or leave a pass half-added); a second signal stops at
once, even inside a native Mitsuba call, where Python handlers wait for the call to return: a watcher
thread reads the interpreter's wake-up fd, which the C-level handler writes at once."""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from types import FrameType, TracebackType
from typing import Any

logger = logging.getLogger(__name__)

SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: exit status of a process stopped by a second signal (128 + SIGINT, as shells report Ctrl-C)
EXIT_STATUS = 130


class DeferredStop:
    """Context manager: ``requested`` is the first signal's name once one arrived; a second
    one ends the process (one line on stderr, exit status 130). Outside the main thread (Dask
    workers), where signals cannot be handled, it does nothing."""

    def __init__(self) -> None:
        self.requested: str | None = None
        self._previous: dict[int, Any] = {}
        self._pipe: tuple[int, int] | None = None
        self._old_wakeup = -1
        self._watcher: threading.Thread | None = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if self.requested is not None:            # second signal: the watcher ends the process
            if self._watcher is not None and self._watcher.is_alive():
                time.sleep(1.0)                    # it is doing so now
            self._restore()
            raise KeyboardInterrupt(f"{name} again: stopped without finishing the pass")
        self.requested = name
        logger.warning("%s: finishing the pass under way, then writing the checkpoint "
                       "(send it again to stop at once)", name)

    def __enter__(self) -> DeferredStop:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handle)
            self._start_watcher()
        return self

    def _start_watcher(self) -> None:
        try:
            r, w = os.pipe()
            os.set_blocking(w, False)
            self._old_wakeup = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        except (OSError, ValueError):              # no wake-up fd: the Python handler alone
            return
        self._pipe = (r, w)
        self._watcher = threading.Thread(target=self._watch, args=(r,), name="second-signal", daemon=True)
        self._watcher.start()

    def _watch(self, fd: int) -> None:
        seen = 0
        while True:
            try:
                data = os.read(fd, 64)
            except OSError:
                return
            if not data:                           # the pipe was closed: the block ended
                return
            for signum in data:
                if signum in SIGNALS:
                    seen += 1
                    if seen >= 2:
                        self._stop_now(signal.Signals(signum).name)

    def _stop_now(self, name: str) -> None:
        with contextlib.suppress(Exception):       # stopping regardless
            sys.stderr.flush()
        os.write(2, f"\nnoisestop: interrupted: {name} again: stopped at once, without finishing the "
                    "pass (--resume continues from the last checkpoint)\n".encode())
        os._exit(EXIT_STATUS)

    def _restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        if self._pipe is not None:
            with contextlib.suppress(ValueError):
                signal.set_wakeup_fd(self._old_wakeup)
            r, w = self._pipe
            self._pipe = None
            os.close(w)                            # the watcher reads EOF and ends
            self._watcher.join(1.0)                # there is one whenever there is a pipe
            os.close(r)

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._restore()
