"""Test helper: a block's window as array slices (the renderer keeps windows as (x, y, w, h))."""
from __future__ import annotations

from typing import Any


def block_slices(windows: Any, block_id: int) -> tuple[slice, slice]:
    """(rows, columns) slices that cut block `block_id` of `windows` (a `BlockWindows`, e.g.
    a `BlockRenderer`) out of a [H, W, ...] frame."""
    x, y, w, h = windows.window(block_id)
    return slice(y, y + h), slice(x, x + w)
