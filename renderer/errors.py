"""The exceptions `renderer.render` raises for bad arguments, each a ValueError (as the API
promises) and also FileNotFoundError or ConnectionError, so either ``except`` catches them."""
from __future__ import annotations

from noisefeat.errors import InputNotFound

__all__ = ["InputNotFound", "ServerUnavailable"]


class ServerUnavailable(ValueError, ConnectionError):
    """The verdict server (`server=`) is unreachable, does not answer in time, or fails (5xx)."""
