"""What a tile's half buffers show besides their FLIP score: the content terms a learned
estimate of the tile's true error reads.

The halves' score is blind where both halves miss the same rare paths (dark tiles: both
black where the reference is not) and where texture masks noise the halves still disagree
on. So, per tile, from the even and odd half means alone (what the live loop has at a
decision, `renderer.criteria.batch.UnitBatch.block_halves`, and what a stack's recovered
passes give, `learning.inputs.halves.iter_stack_halves`):

* brightness: log10 of the mean luminance, the share of dark display pixels (under 0.1,
  the observer's dark range) and of clipped ones (linear luminance over 1);
* the halves' own disagreement: log10 of the mean squared display difference, and the
  share of pixels where it is over 0.1 (isolated outliers, fireflies);
* missing paths: the share of pixels black in both halves, and in exactly one;
* the halves in linear light, where the display transform does not compress the dark: the
  mean per-pixel |La - Lb| / (La + Lb) of their luminances, and the same of the tile's
  totals (how far the halves are from each other in the light they gathered);
* texture: log10 of the mean display gradient of the mean image (noise under texture is
  masked).

Every value is finite for any input (black, constant, NaN/Inf, huge): non-finite radiance is
taken as the display transform takes it (`noisefeat.display.display`), logs have a floor.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch

from noisefeat.display import display
from noisefeat.pooling import cuts_evenly

#: the names of `tile_stats`' columns, in order
STAT_NAMES = ("log_luminance", "dark_share", "clipped_share", "log_halves_mse", "outlier_share",
              "black_both_share", "black_one_share", "log_texture", "relative_difference", "tile_balance")
#: display value under which a pixel counts as dark (the observer's dark range)
DARK = 0.1
#: display difference over which a pixel's halves disagree as an outlier
OUTLIER = 0.1
#: linear values are clipped to this (and +Inf taken as it), so that a tile's sums stay finite in float32
HUGE = 1e30
#: floors of the logs: below them a term is as good as zero
LOG_FLOOR = 1e-6

_LUMA = (0.2126, 0.7152, 0.0722)


def _luminance(rgb: torch.Tensor) -> torch.Tensor:
    w = torch.tensor(_LUMA, dtype=rgb.dtype, device=rgb.device)
    return (rgb * w).sum(-1)


def _window_sums(x: torch.Tensor, windows: Sequence[tuple[int, int, int, int]]) -> torch.Tensor:
    """float64 [n, T, C]: the sums of per-pixel values `x` [n, bh, bw, C] over each window of one
    size: a reshape where the windows cut the block evenly (the live loop's and the stacks'
    tiles), else a loop over them."""
    n, bh, bw, c = x.shape
    if cuts_evenly(windows, bh, bw):
        _, _, tw, th = windows[0]
        return x.reshape(n, bh // th, th, bw // tw, tw, c).sum(dim=(2, 4), dtype=torch.float64) \
            .reshape(n, len(windows), c)
    return torch.stack([x[:, y:y + h, x0:x0 + w].sum(dim=(1, 2), dtype=torch.float64)
                        for x0, y, w, h in windows], dim=1)


def tile_stats(even: torch.Tensor, odd: torch.Tensor, windows: Sequence[tuple[int, int, int, int]],
               exposure: float = 0.0) -> torch.Tensor:
    """float64 [n, T, len(STAT_NAMES)]: the content terms of every tile `windows` ((x, y, w,
    h) within a block) of blocks whose half means are `even`, `odd` (linear RGB [n, bh, bw,
    3], any float dtype and device). Finite for any input."""
    if even.shape != odd.shape or even.ndim != 4 or even.shape[-1] != 3:
        raise ValueError(f"half buffers must be two [n, h, w, 3] arrays of one shape, got "
                         f"{tuple(even.shape)} and {tuple(odd.shape)}")
    a = torch.as_tensor(even).to(torch.float32)
    b = torch.as_tensor(odd).to(device=a.device, dtype=torch.float32)
    scale = float(2.0 ** exposure)
    fa = torch.nan_to_num(a, nan=0.0, posinf=HUGE, neginf=0.0).clamp_(max=HUGE)
    fb = torch.nan_to_num(b, nan=0.0, posinf=HUGE, neginf=0.0).clamp_(max=HUGE)
    mean = 0.5 * (fa + fb).clamp_min(0.0)
    lum = (_luminance(mean) * scale).clamp_(max=HUGE)
    da, db, dm = display(a, exposure), display(b, exposure), display(mean, exposure)
    diff2 = ((da - db) ** 2).mean(-1)
    outlier = (da - db).abs().amax(-1) > OUTLIER
    black_a, black_b = da.amax(-1) <= 0.0, db.amax(-1) <= 0.0
    dark = _luminance(dm) < DARK
    gx = torch.zeros_like(dm[..., 0])
    gy = torch.zeros_like(dm[..., 0])
    gx[:, :, :-1] = (dm[:, :, 1:] - dm[:, :, :-1]).abs().mean(-1)
    gy[:, :-1, :] = (dm[:, 1:, :] - dm[:, :-1, :]).abs().mean(-1)
    la, lb = _luminance(fa.clamp_min(0.0)), _luminance(fb.clamp_min(0.0))
    both = la + lb
    relative = torch.where(both > 0, (la - lb).abs() / both.clamp_min(1e-30), torch.zeros_like(both))
    per_pixel = torch.stack([lum, dark.to(a.dtype), (lum > 1.0).to(a.dtype), diff2,
                             outlier.to(a.dtype), (black_a & black_b).to(a.dtype),
                             (black_a ^ black_b).to(a.dtype), gx + gy, relative], dim=-1)
    tiles = _window_sums(per_pixel, windows) / (windows[0][2] * windows[0][3])
    sums = _window_sums(torch.stack([la, lb], dim=-1), windows)
    total = sums.sum(-1)
    balance = torch.where(total > 0, (sums[..., 0] - sums[..., 1]).abs() / total.clamp_min(1e-300),
                          torch.zeros_like(total))
    tiles = torch.cat([tiles, balance[..., None]], dim=-1)
    for col in (0, 3, 7):
        tiles[..., col] = torch.log10(tiles[..., col].clamp_min(LOG_FLOOR))
    return tiles
