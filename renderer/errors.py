"""The exceptions `renderer.render` raises for bad arguments, each a ValueError.

Why: the API promises ValueError (one line, naming the argument) for every bad argument,
but a missing model bundle, scene file or reference surfaced as FileNotFoundError and an
unreachable verdict server as ConnectionError, so ``except ValueError`` missed them. These
subclass both, so code catching either keeps working.
"""
from __future__ import annotations

from noisefeat.errors import InputNotFound

__all__ = ["InputNotFound", "ServerUnavailable"]


class ServerUnavailable(ValueError, ConnectionError):
    """The verdict server (`server=`) is unreachable, does not answer in time, or fails (5xx)."""
