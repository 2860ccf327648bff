"""Giving the heap's free pages back to the system after a large request (glibc's malloc_trim).

Why: glibc keeps freed pages, so the server's resident size would stay at its high-water
mark after one large request, and the next large one would start from there.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


@functools.cache
def _libc() -> tuple[Callable[[int], int] | None, Callable[[], _MallInfo2] | None]:
    """glibc's malloc_trim and mallinfo2 (None where missing: not glibc, or glibc < 2.33)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None, None
    trim = getattr(libc, "malloc_trim", None)
    info = getattr(libc, "mallinfo2", None)
    if info is not None:
        info.restype = _MallInfo2
    return trim, info


#: free heap bytes above which `release_memory` trims the heap
RELEASE_ABOVE = 64 * 1024 * 1024


def release_memory(above: int = RELEASE_ABOVE) -> bool:
    """Give the heap's free pages back to the system after a request when more than `above`
    bytes of it are free (glibc keeps them, so the resident size would stay at its
    high-water mark and the next large request would start from there). True if trimmed.

    Why not after every request: trimming the few tens of MB an
    ordinary request frees makes the next one fault them all back in; for 16 blocks of
    128x128 that was 7.6 ms of CPU a request (measured). Large requests, the ones that
    matter for memory, still leave a trimmed heap. Without mallinfo2: always trims."""
    trim, info = _libc()
    if trim is None:
        return False
    if info is not None and info().fordblks <= above:
        return False
    trim(0)
    return True
