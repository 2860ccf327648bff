"""How many passes one launch traces (docs/how-it-works.md, "Launches").

A launch costs about 10 ms whatever its size, so it may hold several passes; each keeps its own pass index
and is judged in turn, so stops, history and image are those of one pass per launch.
"""
from __future__ import annotations

import numpy as np


def grown_passes(n_units: int, n_pending: int, passes_left: int, grow: bool = True, undecided: int = 1,
                 lane_cap: int = 1) -> int:
    """How many passes of the pending units one launch traces (1 without `grow`, at most the passes left):
    floor(n_units / n_pending), so a launch holds about as many samples as the first, made even (the half
    buffers alternate); or, while few units can stop, `undecided` passes (`ahead_passes`), at most `lane_cap`."""
    if not grow or n_pending <= 0:
        return 1
    k = n_units // n_pending
    if k >= 2:
        k -= k % 2
    return max(1, min(max(k, min(undecided, lane_cap)), passes_left))


#: a decision may stop a unit when its ratio brought to the decision's spp is at most this (or
#: unknown); farther (the skip judges again near 1/decide_skip = 2) it is taken within a
#: launch, and one that stops the unit wastes its later passes (counted in samples_traced)
NEAR = 1.5
#: the most of a launch's unit-passes that may be traced for nothing (`ahead_passes`)
WASTE_SHARE = 1.0 / 16


def ahead_passes(offsets: np.ndarray, n: int, cap: int) -> int:
    """How many passes, up to `cap`, a launch of `n` units may trace ahead of their decisions
    while the worst case wastes at most `WASTE_SHARE` of it. `offsets`: for each unit that may
    stop (`NEAR`), the launch's passes before its decision. (Ending a launch at the first such
    decision would hold every launch to one pass while a few units hover near their target.)"""
    ks = np.arange(1, max(1, int(cap)) + 1)
    waste = np.maximum(ks[:, None] - 1 - np.asarray(offsets, np.int64)[None, :], 0).sum(axis=1)
    return int(ks[waste <= WASTE_SHARE * ks * n].max())


#: lanes one launch may hold when it traces passes ahead of a decision: at 0.2-0.5 s of two
#: cores per million lanes, a few seconds at most; a larger pass is one launch
LAUNCH_LANES = 1 << 23
