"""A resumed checkpoint's checks against the scene and the criterion: what the file alone cannot
vouch for (`renderer.live.checkpoint` vouches for the rest). A refusal is a ValueError naming the file."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from learning.data.accumulator import UnitAccumulator
from learning.inputs.history import last_decided_spp

from ..criteria import UnitBatch
from .passloop import PassLoop, next_decision

if TYPE_CHECKING:
    from .blocks import BlockRenderer


def _refuse(path: Path, what: str) -> None:
    raise ValueError(f"{path}: inconsistent checkpoint: {what} (forged or damaged); delete it (or rerun "
                     "without --resume) to start over")


#: how far a resumed checkpoint's mean radiance may lie from its first pass traced again
RADIANCE_RATIO = 1e6


def check_radiance(path: Path, acc: UnitAccumulator, br: BlockRenderer, first_spp: int, seed: int) -> None:
    """ValueError unless a checkpoint's radiance is what its scene renders (sums scaled x1e30, digest
    recomputed, pass every check of the file alone): the first pass, which depends only on (seed, pixel,
    pass), is traced again and the mean held must lie within RADIANCE_RATIO of its mean (unless black)."""
    units = np.flatnonzero(acc.pass_counts() > 0)
    if not units.size:
        return
    again = np.nan_to_num(br.render_full(int(first_spp), seed, 0).astype(np.float64), nan=0.0, posinf=0.0,
                          neginf=0.0)
    traced = float(np.abs(again).mean())
    held = float(acc.means(units).abs().mean().cpu())
    if traced > 0 and not traced / RADIANCE_RATIO <= held <= traced * RADIANCE_RATIO:
        _refuse(path, f"its mean radiance is {held / traced:.3g} times what its first pass traces again")


#: how far a unit's mean noise estimate may lie from its halves' estimate now
EVIDENCE_RATIO = 1e3
#: how far a unit's next decision may lie past the one its ratio now asks for
NEXT_RATIO = 1e3


def check_evidence(path: Path, loop: PassLoop) -> None:
    """ValueError unless a resumed loop's decision evidence and next decisions agree with the half
    buffers its checkpoint holds. Neither can be recomputed from the file (forged sums, zeroed or 1e300,
    stop units early or run them to max spp), but every decision estimated one per-unit constant (noise
    falls as 1/sqrt(spp)), so the criterion is asked once more on the active, judged units, keeping
    nothing. Refused: a unit judged at the spp it holds with less evidence than that decision added
    (half of it, for a tile's context), a mean estimate more than EVIDENCE_RATIO from its halves' now
    (honest ones: within 3x on cornell), a next decision more than NEXT_RATIO past what its ratio asks."""
    decided = loop.evidence.last
    ids = np.flatnonzero(loop.active & (decided > 0))
    if not ids.size or not loop.criterion.noise_ratio:
        return
    d = loop.criterion.decide(ids, UnitBatch.from_accumulator(loop.acc, ids, loop.quick, loop.tiling,
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
    # judged at the spp it holds: that decision added (spp - the one before) x
    here = fresh & (spp == decided[ids])
    if here.any():
        w = (spp[here] - _decided_before(loop, ids[here])).astype(np.float64)
        short = (weight[here] < w) | (total[here] < 0.5 * w * x[here])
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
    """int64 [k]: the spp of each unit's decision before its last one (0: none)."""
    asked = loop.history[:, ids] != 0
    if asked.any():                    # each unit's last decision left out, the last before it remains
        asked[len(asked) - 1 - np.argmax(asked[::-1], axis=0), np.arange(len(ids))] = False
    return last_decided_spp(asked, loop.history_unit_spp[:, ids])
