"""How deep a JSON text nests, measured on its bytes before anything is built.

Why: parsing is the one step whose cost is not linear in the body. Lists nested 20 deep
cost 0.8 s of CPU a MiB to parse (ordinary number arrays: 0.02), and a parser builds every
object while holding the GIL. An OIP request needs little depth: the request object, its
`inputs` list, an input object, its `data` (flat, or nested once per tensor axis, at most
`MAX_RANK`); parameters are flat. Anything deeper is refused (400) from a byte scan, in
slices of `CHUNK` bytes (numpy, no Python object per byte), brackets inside strings not
counted.
"""
from __future__ import annotations

import numpy as np

#: bytes scanned at a time: the scan's working memory is SCAN_BYTES_PER_BYTE times this at
#: most (512 KB), whatever the body's size; 8 KiB slices scan 60 MiB in ~0.7 s
CHUNK = 1 << 13
#: the scan's working arrays per byte of a slice, measured with tracemalloc: ~16 for plain
#: JSON, ~58 where strings are full of backslashes (int64 positions); `memory_cost.json_cost`
#: counts this much
SCAN_BYTES_PER_BYTE = 64

_OPEN = np.zeros(256, np.int8)
_OPEN[[ord("["), ord("{")]] = 1
_OPEN[[ord("]"), ord("}")]] = -1


def max_depth(text: bytes | bytearray | memoryview) -> int:
    """The deepest nesting of lists and objects in a JSON text (0 for a bare scalar).

    Quotes preceded by an odd run of backslashes do not end a string; brackets between
    quotes are not counted. On text that is not JSON the figure is still defined (and the
    parser will refuse the text anyway)."""
    data = np.frombuffer(memoryview(text).cast("B"), np.uint8)
    depth, best, in_string, slashes = 0, 0, False, 0
    for start in range(0, data.size, CHUNK):
        c = data[start:start + CHUNK]
        quote = c == ord('"')
        if quote.any() or in_string:
            quote &= ~_escaped(c, slashes)
            inside = (np.cumsum(quote, dtype=np.int32) & 1).astype(bool)
            if in_string:
                inside = ~inside
            # a quote opens (or closes) a string: neither it nor what it encloses counts
            step = np.where(inside | quote, 0, _OPEN[c])
            in_string = bool(inside[-1])
        else:
            step = _OPEN[c]
        running = np.cumsum(step, dtype=np.int32) + depth
        if running.size:
            best = max(best, int(running.max()))
            depth = int(running[-1])
        slashes = _trailing_backslashes(c, slashes)
    return best


def _escaped(c: np.ndarray, carried: int) -> np.ndarray:
    """True where a byte follows an odd run of backslashes (`carried`: the run that ended
    the previous slice)."""
    back = c == ord("\\")
    if not back.any() and carried == 0:
        return np.zeros(c.size, bool)
    idx = np.arange(c.size, dtype=np.int64)
    last_other = np.maximum.accumulate(np.where(back, -1, idx))   # last non-backslash at or before i
    before = np.empty(c.size, np.int64)                           # backslashes just before byte i
    before[0] = carried
    run = idx[:-1] - last_other[:-1]                              # run ending at i-1
    all_back = last_other[:-1] < 0                                # the slice so far is all backslashes
    before[1:] = np.where(all_back, run + carried, run)
    return (before & 1).astype(bool)


def _trailing_backslashes(c: np.ndarray, carried: int) -> int:
    back = np.flatnonzero(c != ord("\\"))
    if back.size == 0:
        return carried + c.size
    return c.size - 1 - int(back[-1])
