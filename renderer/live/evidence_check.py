"""What a resumed checkpoint's decision state must agree with: the half buffers it holds.

A checkpoint keeps, per unit, the sums of its decisions' noise estimates (the history
criterion's evidence, `learning.inputs.history.Evidence`) and the spp of its next decision
(`renderer.live.passloop.next_decision`). Neither can be recomputed from the file: the
scores they came from were taken on half buffers at spp long past. So a forged file (sums
zeroed, or 1e300, or every next decision put at the latest the format allows, digest
recomputed) passed every check the file alone allows and silently stopped units early or
ran them to max spp. What the file does hold is each unit's half buffers now, and every
one of its decisions estimated the same per-unit constant from them (noise falls as
1/sqrt(spp)): the criterion is asked once more, on the units as they stand, without
keeping anything (no verdict, ratio, evidence, counter or timer: the resumed render
counts as the uninterrupted one), and the checkpoint is refused in one line where

* a unit judged at the spp it holds now (no pass since) held less evidence than that very
  decision added: that decision is the same state, so the same estimate, exactly;
* a unit's mean estimate lies more than a factor EVIDENCE_RATIO from the one its halves
  give now, or is 0 while they give more (the spread of honest estimates is far inside it);
* a unit's next decision lies more than a factor NEXT_RATIO past the one its ratio now
  asks for.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..criteria import BlockBatch
from .passloop import PassLoop, next_decision

#: how far a unit's mean noise estimate may lie from its halves' estimate now
EVIDENCE_RATIO = 1e3
#: how far a unit's next decision may lie past the one its ratio now asks for
NEXT_RATIO = 1e3


def _refuse(path: Path, what: str) -> None:
    raise ValueError(f"{path}: inconsistent checkpoint: {what} (forged or damaged); delete it (or rerun "
                     "without --resume) to start over")


def check_evidence(path: Path, loop: PassLoop) -> None:
    """ValueError unless the restored loop's evidence and next decisions agree with its half
    buffers (the module docstring). Only active units that were judged are asked."""
    decided = loop.evidence.last
    ids = np.flatnonzero(loop.active & (decided > 0))
    if not ids.size or not loop.criterion.noise_ratio:
        return
    d = loop.criterion.decide(ids, BlockBatch.from_accumulator(loop.acc, ids, loop.quick, loop.tiling,
                                                               loop.evidence))
    spp = loop.acc.spp_all()[ids]
    ratio = np.asarray(d.ratio, np.float64)
    if loop.decide_skip > 0 or loop.decide_growth > 0:
        known = np.isfinite(ratio)
        asked = next_decision(spp[known], ratio[known], loop.decide_skip, loop.decide_growth)
        late = loop.next_spp[ids[known]] > NEXT_RATIO * np.maximum(asked, spp[known] + 1)
        if late.any():
            _refuse(path, f"unit {int(ids[known][late][0])}'s next decision is far past what its noise asks for")
    if d.evidence is None:
        return
    x = np.asarray(d.evidence, np.float64)
    total, weight = loop.evidence.sums[ids, 0], loop.evidence.sums[ids, 1]
    fresh = np.isfinite(x)
    # judged at the spp it holds: that decision added (spp - the one before) x, exactly
    here = fresh & (spp == decided[ids])
    if here.any():
        before = _decided_before(loop, ids[here])
        w = (spp[here] - before).astype(np.float64)
        short = (weight[here] < w) | (total[here] < w * x[here] * (1 - 1e-9))
        if short.any():
            _refuse(path, f"unit {int(ids[here][short][0])} holds less evidence than its last decision added")
    held = fresh & (weight > 0) & (x > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(held, total / np.where(weight > 0, weight, 1.0), np.nan)
        off = held & ~((mean >= x / EVIDENCE_RATIO) & (mean <= x * EVIDENCE_RATIO))
    if off.any():
        _refuse(path, f"unit {int(ids[off][0])}'s decision evidence is {mean[off][0]:.3g} per sample, its "
                      f"half buffers give {x[off][0]:.3g}")


def _decided_before(loop: PassLoop, ids: np.ndarray) -> np.ndarray:
    """int64 [k]: the spp of each unit's decision before its last one (0: none), from the
    verdict history."""
    asked = loop.history[:, ids] != 0
    out = np.zeros(len(ids), np.int64)
    for j in range(len(ids)):
        rows = np.flatnonzero(asked[:, j])
        if len(rows) >= 2:
            out[j] = loop.history_unit_spp[rows[-2], ids[j]]
    return out
