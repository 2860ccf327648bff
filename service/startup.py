"""SIGHUP while `noisestop serve` starts (imports, model loading): logged, then the process
ends as SIGTERM ends it then. Why: a hang-up in the first seconds killed the server
without a word. uvicorn's own handlers (service.serve) take over once it listens."""
from __future__ import annotations

import logging
import os
import signal
import threading
from types import FrameType

log = logging.getLogger("service.serve")


def hang_up_during_start(sig: int, frame: FrameType | None) -> None:
    log.warning("SIGHUP during start-up: exiting as for SIGTERM")
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.kill(os.getpid(), signal.SIGTERM)


def guard_start_up() -> None:
    """Install the start-up SIGHUP handler (main thread only)."""
    if threading.current_thread() is threading.main_thread() and hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, hang_up_during_start)
