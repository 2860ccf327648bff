"""A stack's rows for the learned per-tile error estimate: every tile at every
level, as the live loop at tile grain would see it had it decided there, with the
observer's same-samples error of the tile as the target's truth.

The content terms are cached next to the stack like the halves' FLIP (`learning.data.cache`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from noisefeat.pooling import TILE, tile_windows

from ..data.cache import cached_array
from ..data.stack import Stack
from ..data.tile_terms import stack_tile_errors
from .halves import iter_stack_halves, stack_tile_terms
from .history import running
from .tile_features import tile_features, target
from .tile_stats import STAT_NAMES, tile_stats


def stack_tile_stats(stack: Stack, tile: int = TILE, exposure: float = 0.0, progress: bool = False) -> np.ndarray:
    """float64 [K, n_tiles, len(STAT_NAMES)]: `tile_stats` of every tile at every level
    (level 0, one pass, has no odd half: zeros). Cached next to the stack."""
    windows = tile_windows(stack.block[0], stack.block[1], tile)
    shape = (stack.n_levels, stack.n_blocks * len(windows), len(STAT_NAMES))

    def compute() -> np.ndarray:
        out = np.zeros(shape)
        for k, even, odd in iter_stack_halves(stack, progress):
            stats = tile_stats(torch.as_tensor(even), torch.as_tensor(odd), windows, exposure)
            out[k] = stats.reshape(shape[1:]).numpy()
        return out
    return cached_array(stack, f"tile{tile}-stats-v3-e{exposure:g}", shape, compute)


@dataclass(frozen=True)
class TileTable:
    """One stack's rows: `X` [K, n, F] (`tile_features`), `y` [K, n] (`target`; NaN where
    no truth), `e_hist` [K, n] and `true_error` [K, n], `flat` [K, n], `dots` [K, n] and
    the stack's `spp` [K]; level 0 (no odd half) has no estimate (e_hist NaN)."""

    scene: str
    X: np.ndarray
    y: np.ndarray
    e_hist: np.ndarray
    true_error: np.ndarray
    flat: np.ndarray
    dots: np.ndarray
    spp: np.ndarray


def stack_tile_table(stack: Stack, tile: int = TILE, exposure: float = 0.0, progress: bool = False) -> TileTable:
    """The stack's `TileTable` at `tile` grain."""
    terms = stack_tile_terms(stack, tile, exposure, progress=progress)
    e_last, dots, flat = terms[0], terms[1], terms[2] > 0.5
    e_hist = running(e_last, stack.spp)
    per_block = len(tile_windows(stack.block[0], stack.block[1], tile))
    k, n = e_last.shape
    block_e = np.repeat(e_last.reshape(k, n // per_block, 1, per_block), per_block, axis=2).reshape(k, n, per_block)
    spp = np.broadcast_to(np.asarray(stack.spp, np.float64)[:, None], (k, n))
    X = tile_features(e_last, e_hist, spp, dots, block_e, stack_tile_stats(stack, tile, exposure, progress))
    truth = stack_tile_errors(stack, tile, exposure=exposure)
    return TileTable(stack.scene, X, target(truth, e_hist), e_hist, truth, flat, dots, np.asarray(stack.spp))
