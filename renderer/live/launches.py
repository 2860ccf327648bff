"""How many passes one launch traces: the rule that keeps the device busy and its launches few.

A launch costs about 10 ms here whatever its size (building and hashing the path tracer's
kernel, starting Dr.Jit's thread pool), 3-4 % of a 16-spp pass at 256x256 (BENCHMARKS.md,
"Speed"), so the live loop (`renderer.live.session.RenderSession.plan`) puts
several passes in one launch where that changes nothing but the launches: each pass keeps
its own pass index (its random numbers) and is judged in turn, a round each
(`renderer.live.passloop`), so the stops, history and image are those of one pass per launch.
"""
from __future__ import annotations

import numpy as np


def grown_passes(n_units: int, n_pending: int, passes_left: int, grow: bool = True, undecided: int = 1,
                 lane_cap: int = 1) -> int:
    """How many passes of the pending units one launch traces (the module docstring: why
    several, and why that changes nothing but the launches). Two reasons to trace more than one:

    * as units stop, the remaining ones get more passes per launch, so each launch holds
      about as many samples as the first (all units, one pass): floor(n_units / n_pending),
      made even (a pass goes to each half buffer in turn, so an even count keeps them
      balanced);
    * while few units can stop, `undecided` passes (`ahead_passes`) go in one launch, at
      most `lane_cap` (`LAUNCH_LANES`).

    Capped by the passes left; 1 without `grow`. A unit still gets its decisions at its own
    passes, and the passes traced past its stop are dropped."""
    if not grow or n_pending <= 0:
        return 1
    k = n_units // n_pending
    if k >= 2:
        k -= k % 2
    return max(1, min(max(k, min(undecided, lane_cap)), passes_left))


#: a decision that may stop a unit: one where the unit's ratio, brought to the decision's spp
#: (`renderer.live.passloop.UnitRatios.predicted`), is at most this (or unknown). Farther
#: from its target (the skip judges a unit again at a predicted ratio near 1/decide_skip = 2)
#: a decision is taken within a launch as if it could not stop the unit; one that does drops
#: the launch's later passes of the unit, traced for nothing (samples_traced counts them)
NEAR = 1.5
#: the most of a launch's unit-passes that may be traced for nothing (`ahead_passes`)
WASTE_SHARE = 1.0 / 16


def ahead_passes(offsets: np.ndarray, n: int, cap: int) -> int:
    """How many passes a launch of `n` units may trace ahead of their decisions: the most, up
    to `cap`, whose worst case wastes at most `WASTE_SHARE` of the launch. `offsets`: for each
    unit that may stop (`NEAR`; its decision's pass from `renderer.live.passloop.PassLoop.due_pass`),
    the passes of the launch before its decision (0: the first pass judges it); worst case,
    each stops there and drops the rest of its passes. Why not end a launch at the first such
    decision: a few units hovering near their target are judged at every pass (the growth
    floor) and would hold every launch to one pass, each costing its fixed 10 ms, for a
    waste of a few tiles' passes."""
    ks = np.arange(1, max(1, int(cap)) + 1)
    waste = np.maximum(ks[:, None] - 1 - np.asarray(offsets, np.int64)[None, :], 0).sum(axis=1)
    return int(ks[waste <= WASTE_SHARE * ks * n].max())


#: lanes (samples) one launch may hold when it traces passes ahead of a decision
#: (`grown_passes`): 2^23, 0.2-0.5 s of this machine's two cores per million lanes, so a
#: launch of a few seconds at most; a pass larger than this is one launch
LAUNCH_LANES = 1 << 23
