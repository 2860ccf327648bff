"""A least-recently-used cache bounded by the bytes of the tensors it holds.

Why bytes and not entries: the feature base keeps, per block size, operators whose size
grows with the block's pixel count (about 80 bytes a pixel), so a cache bounded by an
entry count still lets a handful of large sizes take gigabytes (measured: 100 MB kept
per distinct size near 1024x1024, never released). Bounded by bytes, a server that
sees many sizes keeps the most recent ones within a fixed budget; an entry larger than
the whole budget is handed back but not kept.

Thread-safe: the verdict service runs inference in worker threads that share one
feature base, and its warm-up fills the cache before they start.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Hashable, Mapping
from typing import Any

import torch

ENV_CACHE_BYTES = "NOISESTOP_OPERATOR_CACHE_BYTES"
DEFAULT_MAX_BYTES = 256 * 1024 * 1024


def nbytes(value: Any) -> int:
    """Bytes of the tensors and arrays in `value` (nested in tuples, lists and dicts)."""
    if isinstance(value, torch.Tensor):
        return value.element_size() * value.nelement()
    if hasattr(value, "nbytes") and not isinstance(value, (bytes, str)):
        return int(value.nbytes)
    if isinstance(value, Mapping):
        return sum(nbytes(v) for v in value.values())
    if isinstance(value, (tuple, list)):
        return sum(nbytes(v) for v in value)
    return 0


class ByteLRU:
    """`get` / `put` / `clear`, evicting least-recently-used entries beyond `max_bytes`."""

    def __init__(self, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 0:
            raise ValueError(f"max_bytes must be a whole number >= 0, got {max_bytes!r}")
        self.max_bytes = max_bytes
        self._items: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> Any | None:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                return None
            self._items.move_to_end(key)
            return item[0]

    def put(self, key: Hashable, value: Any) -> Any:
        """Keep `value` (unless it alone exceeds the budget); returns it."""
        size = nbytes(value)
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self._bytes -= old[1]
            if size <= self.max_bytes:
                self._items[key] = (value, size)
                self._bytes += size
                while self._bytes > self.max_bytes:
                    _, (_, dropped) = self._items.popitem(last=False)
                    self._bytes -= dropped
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0

    @property
    def bytes(self) -> int:
        """Bytes held now (never above `max_bytes`)."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items


def default_max_bytes(environ: Mapping[str, str] | None = None) -> int:
    """NOISESTOP_OPERATOR_CACHE_BYTES if set (a whole number >= 0), else 256 MiB."""
    import os

    from .bounds import env_int
    return env_int(os.environ if environ is None else environ, ENV_CACHE_BYTES, DEFAULT_MAX_BYTES, minimum=0)
