"""The virtual observer's terms per tile: each 16x16 tile of every block judged
by its FLIP mean and its own dot term, as the renderer numbers its units (block-major).

Why apart from the block terms: the tile truth (`tile_truth`, `observer.VirtualObserver.
label_tiles`) judges tiles, not blocks; its terms are cached next to a stack apart.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch

from noisefeat.dots import DOT_LEVEL, display_error, rank_pool
from noisefeat.pooling import TILE, tile_windows

from .cache import cached_array
from .frame_flip import DEFAULT_PPD, level_maps
from .stack import Stack
from .stack_format import block_shape


def tile_terms(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
               grid: Sequence[int] = (4, 4), tile: int = TILE, ppd: float = DEFAULT_PPD,
               exposure: float = 0.0) -> np.ndarray:
    """The observer's terms per tile, float64 [2, K, n_blocks * T]: for each
    block's tiles (`noisefeat.pooling.tile_windows`, block-major, as the renderer numbers
    its units), the mean of the frame's FLIP map over the tile and the tile's dot term (at
    most one outlier pixel in a 16x16 tile). `tile_errors` combines them."""
    ref = np.asarray(reference_rgb)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ValueError(f"reference must be linear RGB [H, W, 3], got shape {ref.shape}")
    block_shape(ref.shape[0], ref.shape[1], grid)
    rows = [tile_row(ref_t, lev_t, frame_map, grid, tile)
            for ref_t, lev_t, frame_map in level_maps(ref, levels_rgb, ppd, exposure)]
    if not rows:
        raise ValueError("no levels given")
    return np.asarray(rows, np.float64).transpose(1, 0, 2)


def tile_row(ref_display: torch.Tensor, level_display: torch.Tensor, frame_map: np.ndarray, grid: Sequence[int],
             tile: int) -> tuple[np.ndarray, np.ndarray]:
    """(FLIP means [n_tiles], dot terms [n_tiles]) of one frame's tiles, block-major: the
    per-tile terms of `tile_terms` and of `observer.VirtualObserver.frame_errors`."""
    gh, gw = int(grid[0]), int(grid[1])
    bh, bw = frame_map.shape[0] // gh, frame_map.shape[1] // gw
    windows = tile_windows(bh, bw, tile)

    def blocks(m: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        return m.reshape(gh, bh, gw, bw).transpose(1, 2).reshape(gh * gw, bh, bw) if isinstance(m, torch.Tensor) \
            else m.reshape(gh, bh, gw, bw).transpose(0, 2, 1, 3).reshape(gh * gw, bh, bw)
    emap = blocks(np.asarray(frame_map).astype(np.float64))
    derr = blocks(display_error(level_display, ref_display))
    flip_mean = np.stack([emap[:, y:y + h, x:x + w].mean(axis=(1, 2)) for x, y, w, h in windows], axis=1)
    dots = torch.stack([rank_pool(derr[:, y:y + h, x:x + w]) for x, y, w, h in windows], dim=1).numpy()
    return flip_mean.reshape(-1), dots.reshape(-1)


def tile_errors(terms: np.ndarray) -> np.ndarray:
    """e [K, n_tiles] from `tile_terms`: the larger of the tile's FLIP mean and its dot term
    (version 3 at the tile's grain; NaN stays NaN)."""
    return np.maximum(terms[0], terms[1])


def stack_tile_errors(stack: Stack, tile: int = TILE, ppd: float = DEFAULT_PPD, exposure: float = 0.0) -> np.ndarray:
    """e [K, n_tiles] of a stack (cached next to it, so relabelling at another tau costs no FLIP)."""
    n = stack.n_blocks * len(tile_windows(stack.block[0], stack.block[1], tile))
    terms = cached_array(stack, f"observer-tiles{tile}-e{exposure:g}-ppd{ppd:g}-l{DOT_LEVEL:g}", (2, stack.n_levels, n),
                         lambda: tile_terms(stack.reference(), stack.iter_levels(), stack.grid, tile, ppd, exposure))
    return tile_errors(terms)
