"""How well an error estimate ranks a scene's tiles: the spread s.

A stop "estimate <= c" is early on a tile when the estimate falls to c at some level
before the tile's truth. The c each tile can bear is the smallest estimate it shows
before its truth; one c for all tiles must be below nearly all of them, so the wider they
spread, the more samples the safe c costs (about exp(3.3 s) for 5 % early stops). s is the
standard deviation of log(that smallest estimate / tau) over the tiles whose truth
converges (measured: 0.28 for the halves' history on the held-out stacks).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..data.observer import label_tau
from ..data.stack import Stack


def needed_margins(stack: Stack, estimate: np.ndarray, flat: np.ndarray | None = None) -> np.ndarray:
    """float64 [m]: log(smallest estimate before its truth / tau) of each tile of `stack`
    (with its tile truth, `learning.data.relabel.with_tile_truth`) whose truth converges
    after its first estimate; `estimate` [K, n_tiles] (NaN: none), `flat` [K, n_tiles]
    (levels that stop whatever the estimate, left out)."""
    e = np.asarray(estimate, np.float64)
    if flat is not None:
        e = np.where(flat, np.nan, e)
    tau = label_tau(stack)
    out = []
    for u, truth in enumerate(stack.tile_thresholds):
        if truth is None:
            continue
        before = e[:int(np.searchsorted(stack.spp, truth)), u]
        before = before[np.isfinite(before) & (before > 0)]
        if before.size:
            out.append(np.log(before.min() / tau))
    return np.asarray(out, np.float64)


def spread(margins: np.ndarray) -> float:
    """s of `needed_margins` (of one scene or several pooled; NaN with fewer than two)."""
    m = np.asarray(margins, np.float64)
    return float(np.std(m)) if m.size > 1 else float("nan")


def needed_spread(stacks: Sequence[Stack], estimates: Mapping[str, np.ndarray]) -> float:
    """s over every tile of `stacks` (`needed_margins`; NaN when no tile converges)."""
    return spread(np.concatenate([needed_margins(s, estimates[s.scene]) for s in stacks] or [np.zeros(0)]))
