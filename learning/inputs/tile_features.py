"""The inputs of the learned per-tile error estimate, one function for the stored
stacks and the live loop, so that what is trained on is what is decided on.

A row is one tile at one decision: its halves' score now (`e_last`) and its history's
(`e_hist`, `learning.inputs.history`), the spp, the dot term, its block's other tiles at this
decision (their scores' largest and mean: the neighbours' state, which reaches a tile
through the observer's filters), and the tile's content terms (`learning.inputs.tile_stats`).
The target the estimate learns is log(true error) - log(e_hist): how far the halves'
history is from the observer's error on this tile (`target`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .tile_stats import LOG_FLOOR, STAT_NAMES

#: the columns of `tile_features`, in order
FEATURE_NAMES = ("log_e_hist", "log_e_last", "log_spp", "log_dots", "block_log_e_max", "block_log_e_mean") \
    + STAT_NAMES


def _log(x: Any) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.log(np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=LOG_FLOOR, posinf=1e30), LOG_FLOOR, None))


def tile_features(e_last: np.ndarray, e_hist: np.ndarray, spp: np.ndarray, dots: np.ndarray,
                  block_e: np.ndarray, stats: np.ndarray) -> np.ndarray:
    """float64 [..., len(FEATURE_NAMES)], finite: rows of tiles at a decision. `e_last`,
    `e_hist`, `spp`, `dots` [...]: the tiles' halves score, history score, spp and dot term
    (NaN: none, taken as the floor); `block_e` [..., T]: this decision's scores of every tile
    of each tile's block; `stats` [..., len(STAT_NAMES)] (`tile_stats`)."""
    be = _log(block_e)
    cols = [_log(e_hist), _log(e_last), np.log(np.maximum(np.asarray(spp, np.float64), 1.0)), _log(dots),
            be.max(axis=-1), be.mean(axis=-1)]
    shape = np.broadcast_shapes(*(np.shape(c) for c in cols))
    out = np.concatenate([np.stack([np.broadcast_to(c, shape) for c in cols], axis=-1),
                          np.broadcast_to(np.asarray(stats, np.float64), shape + (len(STAT_NAMES),))], axis=-1)
    return np.nan_to_num(out, nan=0.0, posinf=70.0, neginf=-70.0)


def target(true_error: np.ndarray, e_hist: np.ndarray) -> np.ndarray:
    """log(true error) - log(e_hist) (NaN where either is missing or not positive)."""
    t, e = np.asarray(true_error, np.float64), np.asarray(e_hist, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((t > 0) & (e > 0) & np.isfinite(t) & np.isfinite(e), np.log(t) - np.log(e), np.nan)
