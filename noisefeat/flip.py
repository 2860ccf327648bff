"""LDR-FLIP scores of many blocks at once: FLIP maps between half buffers, pooled per block.

Why: the `flip` criterion and the bundled model's `halves` input (composition `f`) score a
block by the LDR-FLIP map between display(A) and display(B), its two half buffers, pooled.
`flip-evaluator` computes one image pair per call with direct 21-tap loops: ~4.8 ms per
64x64 block, ~250 ms per service request of 16 blocks of 128x128 (measured). The same
computation as a few large matrix products over every block of a batch costs a small
fraction of that.

Where each part lives: FLIP's colour science and filters in `noisefeat.flip_kernels`, the
filters applied as banded matrix products in `noisefeat.flip_bands`, the maps (FLIP's LDR
pipeline, `ldr_flip`, `flip_maps_tensor`) in `noisefeat.flip_maps`; here, the maps pooled
into scores as the observer pools (`noisefeat.pooling`): `flip_halves(even, odd)` takes
linear half buffers, follows the display rule (noisefeat.display: x 2^exposure, NaN/-Inf
black, +Inf white, clip to [0, 1]) and pools each block's map; `pool_tiles` pools a
block's tiles apart.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .flip_kernels import check_ppd
from .flip_maps import check_pair, maps_by_chunk
from .perceptual import DEFAULT_PPD
from .pooling import CRITERION_POOLING, MEAN, TILES, check_pooling, cuts_evenly, tile_starts


def flip_halves(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                exposure: float = 0.0, ppd: float = DEFAULT_PPD, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """float64 [N]: per block, the LDR-FLIP map between display(even) and display(odd),
    linear RGB half buffers [N, h, w, 3], pooled as the observer pools (`noisefeat.pooling`:
    the largest 16x16 tile mean, or the block mean); non-finite values follow the display
    rule.

    The display images are never encoded: FLIP decodes its sRGB input back to linear
    first, so the clipped linear values are what it computes on (to float32 rounding).
    A block whose two display images are identical gets exactly 0, as from FLIP."""
    return flip_halves_tensor(even, odd, exposure, ppd, pooling).cpu().numpy()


def flip_halves_tensor(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                       exposure: float = 0.0, ppd: float = DEFAULT_PPD,
                       pooling: str = CRITERION_POOLING) -> torch.Tensor:
    """`flip_halves` where the half buffers live: float64 [N] on their device.

    Why: the live loop keeps its accumulators on the renderer's device (a GPU with
    ``cuda_ad_rgb``), so FLIP runs there and only the N scores ever reach the host."""
    a, b = check_pair(even, odd, "half buffers")
    p = check_ppd(ppd)
    check_pooling(pooling)
    out = torch.zeros(a.shape[0], dtype=torch.float64, device=a.device)
    with torch.inference_mode():
        for i, keep, maps in maps_by_chunk(a, b, exposure, p):
            out[i + keep] = _pool(maps, pooling)
    return out


def pool_tiles(maps: torch.Tensor, windows: Sequence[tuple[int, int, int, int]],
               pooling: str = CRITERION_POOLING) -> torch.Tensor:
    """FLIP maps [N, h, w] of whole blocks pooled over each of their tiles' (x, y, w, h)
    `windows` (`noisefeat.pooling.tile_windows`), as the observer pools, float64 [N, T] on
    their device: the tiles keep their block as FLIP's context. The live criterion and the
    calibration on stacks both judge a tile by this one function."""
    check_pooling(pooling)
    n, bh, bw = maps.shape
    if cuts_evenly(windows, bh, bw):                                          # one call
        _, _, tw, th = windows[0]
        tiles = maps.reshape(n, bh // th, th, bw // tw, tw).transpose(2, 3).reshape(-1, th, tw)
        return _pool(tiles, pooling).reshape(n, len(windows))
    return torch.stack([_pool(maps[:, y:y + h, x:x + w], pooling) for x, y, w, h in windows], dim=1)


def _pool(maps: torch.Tensor, pooling: str) -> torch.Tensor:
    """`noisefeat.pooling.pool_maps` of float32 maps [N, h, w], in float64 on the maps'
    device: a reshape where the tiles cut the block evenly, else a summed-area table with
    the last tile row and column flush with the edge (`noisefeat.pooling.tile_starts`)."""
    n, h, w = maps.shape
    if pooling == MEAN:
        return maps.sum(dim=(1, 2), dtype=torch.float64) / (h * w)
    th, tw = min(TILES[pooling], h), min(TILES[pooling], w)
    if h % th == 0 and w % tw == 0:
        sums = maps.reshape(n, h // th, th, w // tw, tw).sum(dim=(2, 4), dtype=torch.float64)
        return sums.amax(dim=(1, 2)) / (th * tw)
    sat = torch.zeros((n, h + 1, w + 1), dtype=torch.float64, device=maps.device)
    sat[:, 1:, 1:] = maps.double().cumsum(1).cumsum(2)
    y0 = torch.as_tensor(tile_starts(h, TILES[pooling]), device=maps.device)
    x0 = torch.as_tensor(tile_starts(w, TILES[pooling]), device=maps.device)
    y1, x1 = y0 + th, x0 + tw
    s = sat[:, y1][:, :, x1] - sat[:, y0][:, :, x1] - sat[:, y1][:, :, x0] + sat[:, y0][:, :, x0]
    return (s / (th * tw)).reshape(n, -1).amax(dim=1)
