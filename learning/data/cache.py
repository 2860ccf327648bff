"""Arrays computed from a stack, cached next to it (`<stack>/.cache/<name>.npz`).

Features, half-buffer FLIP values and observer errors are read by every train, calibrate
and evaluate run and cost minutes to compute, so each is kept with the stack's content key
and trusted only while the stack's data is unchanged.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from noisefeat.atomic import atomic_write

from .npz import read_npz
from .stack import Stack

log = logging.getLogger(__name__)
CACHE_DIR = ".cache"


def _atomic_savez(path: Path, **arrays: np.ndarray) -> None:
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays))


def cached_array(stack: Stack, name: str, shape: tuple[int, ...], compute: Callable[[], np.ndarray],
                 dtype: type | None = None) -> np.ndarray:
    """An array computed from a stack, kept in `<stack>/.cache/<name>.npz` (written
    atomically) with the stack's content key (`Stack.content_key`: size and mtime of every
    level, the reference, the quick images and meta.json). Read back only when the key,
    shape (and dtype) match and the file is intact; else computed again from the stack,
    so a changed or damaged stack is recomputed (and a damaged file refused there), never
    trusted."""
    cache = stack.path / CACHE_DIR / f"{name}.npz"
    key = stack.content_key()
    if cache.exists():
        try:
            z = read_npz(cache, max_bytes=_cache_limit(shape))
            arr, stored = z.get("a"), z.get("key")
            if arr is not None and stored is not None and str(stored) == key and arr.shape == shape \
                    and (dtype is None or arr.dtype == dtype):
                return arr
            log.info("%s: made from other stack contents; recomputing", cache)
        except ValueError as exc:
            log.warning("%s: unreadable cache (%s); recomputing", cache, exc)
    arr = compute()
    if stack.content_key() == key:      # the stack did not change while we read it
        try:
            cache.parent.mkdir(exist_ok=True)
            _atomic_savez(cache, a=arr, key=np.array(key))
        except OSError as exc:          # a read-only dataset is still readable: just not cached
            log.warning("%s: not cached (%s)", cache, exc.strerror or exc)
    return arr


def _cache_limit(shape: tuple[int, ...]) -> int:
    return 8 * math.prod(shape) + (1 << 16)
