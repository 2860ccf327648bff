"""FLIP's separable filters as banded matrix products, over many blocks at once.

Why: FLIP's own loops apply each 21-tap filter pixel by pixel; here each 1D pass is one
GEMM. The axis is cut into tiles of about `TILE` pixels, each tile's window (tile plus the
filter radius on both sides, indices clamped: the nearest edge pixel repeated, as FLIP's
loops clamp indices) is gathered once, and one GEMM applies every filter that axis needs
(`noisefeat.flip_kernels.filter_bank`). Arithmetic is float32 as in FLIP; only the order
of the sums differs.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

from .flip_kernels import filter_bank

#: tile length of the banded products (pixels of output per gathered window)
TILE = 16


def tiling(n: int) -> tuple[int, int]:
    """(tile length, number of tiles) for an axis of n pixels: tiles of about TILE."""
    count = -(-n // TILE)
    return -(-n // count), count


def _radius(ppd: float, names: tuple[str, ...]) -> int:
    """The widest radius among the filters `names`: the margin one gathered window needs."""
    return max(len(filter_bank(ppd)[k]) for k in names) // 2


@lru_cache(maxsize=128)
def _band(ppd: float, names: tuple[str, ...], t: int, transpose: bool = False) -> torch.Tensor:
    """[t + 2r, k t] float32 (or its contiguous transpose): column (i, j) applies filter
    names[i] to the window of output j; r is the widest filter's radius."""
    bank, r = filter_bank(ppd), _radius(ppd, names)
    m = np.zeros((t + 2 * r, len(names), t))
    for i, name in enumerate(names):
        taps = bank[name]
        pad = r - len(taps) // 2
        for j in range(t):
            m[pad + j:pad + j + len(taps), i, j] = taps
    m = m.reshape(t + 2 * r, len(names) * t)
    return torch.from_numpy(np.ascontiguousarray(m.T if transpose else m).astype(np.float32))


@lru_cache(maxsize=256)
def _band_on(ppd: float, names: tuple[str, ...], t: int, transpose: bool, device: torch.device) -> torch.Tensor:
    """`_band` on `device`, copied there once (the GPU loop calls FLIP every pass)."""
    return _band(ppd, names, t, transpose).to(device)


@lru_cache(maxsize=64)
def _row_windows(n: int, r: int, device: torch.device = torch.device("cpu")) -> tuple[torch.Tensor, int, int]:
    """Clamped indices of every tile's window along an axis of n pixels: (idx, t, count)."""
    t, count = tiling(n)
    idx = (np.arange(count)[:, None] * t + np.arange(-r, t + r)[None]).clip(0, n - 1)
    return torch.from_numpy(idx.reshape(-1).astype(np.int64)).to(device), t, count


def along_w(x: torch.Tensor, ppd: float, groups: list[tuple[str, ...]]) -> list[torch.Tensor]:
    """[B, H, W] -> per group of filter names, [B, H, nT, k, T]: each filter along W,
    borders clamped; the groups share one gathered window matrix, one GEMM each."""
    b, h, w = x.shape
    r = max(_radius(ppd, g) for g in groups)
    t, count = tiling(w)
    # clamped borders: the edge pixel repeated (a concatenation is ~8x faster than a gather)
    xp = torch.cat([x[..., :1].expand(b, h, r), x, x[..., -1:].expand(b, h, r + count * t - w)], dim=2)
    win = xp.unfold(2, t + 2 * r, t).reshape(b * h * count, t + 2 * r)
    out = []
    for names in groups:
        q = _radius(ppd, names)
        sub = win if q == r else win[:, r - q:win.shape[1] - (r - q)]
        out.append((sub @ _band_on(ppd, names, t, False, x.device)).view(b, h, count, len(names), t))
    return out


def along_h(x: torch.Tensor, ppd: float, names: tuple[str, ...], out: torch.Tensor | None = None,
            add: bool = False) -> torch.Tensor:
    """[B, H, *rest] -> [B, nT, k, T, *rest]: each filter along H, borders clamped; written
    into (or, with `add`, added to) `out`, a contiguous tensor of that many elements."""
    b, h, rest = x.shape[0], x.shape[1], x.shape[2:]
    idx, t, count = _row_windows(h, _radius(ppd, names), x.device)
    win = x.index_select(1, idx).view(b * count, len(idx) // count, -1)
    band = _band_on(ppd, names, t, True, x.device).expand(b * count, len(names) * t, len(idx) // count)
    if out is None:
        res = torch.bmm(band, win)
    elif add:
        res = out.view(b * count, len(names) * t, -1).baddbmm_(band, win)
    else:
        res = torch.bmm(band, win, out=out.view(b * count, len(names) * t, -1))
    return res.view(b, count, len(names), t, *rest)

