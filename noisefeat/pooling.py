"""Pooling an error map into one number per block: DESIGN's "Virtual observer", rule 2.

Why not the block mean: noise confined to part of a block (a grey floor beside a white
wall, fireflies beside black) is diluted by the clean rest, so a block-mean FLIP calls
visibly grainy blocks converged. The question is whether noise is visible *anywhere* in
the block, so the observer and the `flip` criterion take the largest of the means over
16x16 tiles ("tile16-max"). Tiles are aligned to the block's top-left corner; where a
side is not a multiple of 16 the last row/column of tiles is moved flush with the block's
edge (overlapping its neighbour); a side under 16 is one tile of that side.

"tile16-max+dots" (observer version 3, the default) adds a sparse-outlier term to the tile
maximum: a block fails while it holds more than a handful of pixels far off the reference on
the display (`noisefeat.dots`). That term reads the display images, not the FLIP map, so
`pool_maps` does not compute it; the observer takes the larger of the two terms.

"tile16-max" (version 2) and "mean" (the first observer's block mean) stay selectable for
comparison. "tile8-max"
(8x8 tiles) is offered to the criteria, not to labels: a criterion may pool more finely
than the observer it is calibrated against (`noisefeat.pooling.CRITERION_POOLING`).

Tile sums come from one summed-area table per map (float64), so any block size costs
the same few operations per pixel, far below FLIP's own cost.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

TILE = 16
TILE_MAX = "tile16-max"
DOTS = "tile16-max+dots"
MEAN = "mean"
#: tile side of each tile pooling
TILES = {TILE_MAX: TILE, "tile8-max": 8}
#: the poolings a labeler record may name; the first is DESIGN's observer (version 3)
POOLINGS = (DOTS, TILE_MAX, MEAN)
DEFAULT_POOLING = DOTS
#: the poolings of a FLIP map alone (`pool_maps`); DOTS is TILE_MAX and the dot term
FLIP_POOLINGS = (TILE_MAX, MEAN)
#: every pooling name (the criteria may use the finer tile too)
ALL_POOLINGS = (*POOLINGS, "tile8-max")
#: how the `flip` criterion (and the halves input's `f`) pools FLIP between the half buffers
CRITERION_POOLING = "tile8-max"


def check_pooling(pooling: object) -> str:
    """A known pooling name, else ValueError naming the known ones."""
    if not isinstance(pooling, str) or pooling not in ALL_POOLINGS:
        raise ValueError(f"unknown pooling {pooling!r}; known: {', '.join(ALL_POOLINGS)}")
    return pooling


def tile_starts(n: int, tile: int = TILE) -> np.ndarray:
    """Start offsets of the tiles along a side of n pixels (the last one flush with the edge)."""
    if n <= tile:
        return np.zeros(1, np.int64)
    starts = list(range(0, n - tile + 1, tile))
    if starts[-1] + tile < n:
        starts.append(n - tile)
    return np.asarray(starts, np.int64)


def tile_windows(h: int, w: int, tile: int = TILE) -> list[tuple[int, int, int, int]]:
    """(x, y, width, height) of the tiles of an h x w window, row-major: every `tile` pixels,
    the last flush with the edge (one tile when the window is no larger). The decision
    grain's tiles (DESIGN "Decision grain"): the renderer's units and the observer's tile
    truth cut blocks by this one rule."""
    th, tw = min(int(tile), int(h)), min(int(tile), int(w))
    return [(int(x), int(y), tw, th) for y in tile_starts(h, th) for x in tile_starts(w, tw)]


def cuts_evenly(windows: Sequence[tuple[int, int, int, int]], h: int, w: int) -> bool:
    """Whether `windows` ((x, y, w, h), row-major) are the grid of one tile size that cuts an
    `h` x `w` block evenly: then every tile's pool is a reshape, not a loop over windows."""
    if not windows:
        return False
    _, _, tw, th = windows[0]
    return h % th == 0 and w % tw == 0 and \
        list(map(tuple, windows)) == [(x, y, tw, th) for y in range(0, h, th) for x in range(0, w, tw)]


def pool_maps(maps: np.ndarray, pooling: str = TILE_MAX) -> np.ndarray:
    """float64 [N]: each map of [N, H, W] pooled (`POOLINGS`); a NaN pixel makes its map's
    value NaN. Sums are taken in float64 (a float32 map's tile means are exact to float64
    rounding)."""
    p = check_pooling(pooling)
    if p == DOTS:
        raise ValueError(f"{DOTS!r} needs the display images as well as the FLIP map: "
                         "learning.data.block_terms computes it")
    m = np.asarray(maps, np.float64)
    if m.ndim != 3:
        raise ValueError(f"maps must be [N, H, W], got shape {m.shape}")
    n, h, w = m.shape
    if n == 0:
        return np.zeros(0)
    if h == 0 or w == 0:
        raise ValueError(f"maps must have pixels, got shape {m.shape}")
    if p == MEAN:
        return m.mean(axis=(1, 2))
    th, tw = min(TILES[p], h), min(TILES[p], w)
    if h % th == 0 and w % tw == 0:            # the usual case: a plain reshape
        return m.reshape(n, h // th, th, w // tw, tw).mean(axis=(2, 4)).max(axis=(1, 2))
    sat = np.zeros((n, h + 1, w + 1))
    sat[:, 1:, 1:] = m.cumsum(1).cumsum(2)
    y0, x0 = tile_starts(h, TILES[p]), tile_starts(w, TILES[p])
    y1, x1 = y0 + th, x0 + tw
    s = sat[:, y1][:, :, x1] - sat[:, y0][:, :, x1] - sat[:, y1][:, :, x0] + sat[:, y0][:, :, x0]
    # a NaN pixel spreads through the summed-area table, but only within its own map, and
    # that map's maximum is NaN either way (max propagates NaN)
    return (s / (th * tw)).reshape(n, -1).max(axis=1)


def pool_blocks(values: np.ndarray, grid: tuple[int, int], pooling: str = TILE_MAX) -> np.ndarray:
    """float64 [gh*gw]: a frame's [H, W] map cut into its grid's blocks (row-major), each pooled."""
    v = np.asarray(values, np.float64)
    gh, gw = int(grid[0]), int(grid[1])
    if v.ndim != 2 or gh < 1 or gw < 1 or v.shape[0] % gh or v.shape[1] % gw:
        raise ValueError(f"a {v.shape} map does not split into a {gh}x{gw} grid of equal blocks")
    bh, bw = v.shape[0] // gh, v.shape[1] // gw
    blocks = v.reshape(gh, bh, gw, bw).transpose(0, 2, 1, 3).reshape(gh * gw, bh, bw)
    return pool_maps(blocks, pooling)
