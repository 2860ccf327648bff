"""A budget render: spend a limited number of samples (or seconds) where the noise is.

Without a budget every pass renders every active block. Users with a deadline want the
best image by that time instead (Cycles, Arnold and LuxCore pair a noise target with a
time limit), so with ``--spp-budget N`` (samples per pixel averaged over the blocks) or
``--time-limit S`` each round renders the active blocks farthest from their target:

* The loop's `ratios` (`renderer.passloop.BlockRatios`) hold, per block, its last score
  relative to the criterion's threshold (flip: the half-buffer FLIP over c(tau); > 1 is
  above the target). Blocks with no estimate yet (before their first decision) come
  first, all together.
* Priority = ratio / sqrt(spp). Noise falls as 1/sqrt(spp), so a block's ratio is about
  a_b / sqrt(spp_b) with a_b its noise per sample; levelling the priority gives each block
  samples in proportion to a_b. Against uniform sampling with the same samples that
  lowers both the worst block's error (the noisiest block gets more than its share) and
  the mean error (Cauchy-Schwarz: sum sqrt(a_b) <= sqrt(B sum a_b)); levelling the ratio
  itself (``per_sample=False``: samples in proportion to a_b^2, every block to the same
  error) helps the worst block most but measured worse on the mean.
* A round renders the blocks whose priority is at least `band` times the largest: the
  worst alone at first, then, as it comes down, every block within the band (water
  filling, in rounds large enough to trace well).
* While the budget left covers every active block to max spp, rounds render all of them:
  a roomy budget renders exactly what the unbudgeted loop renders, pass for pass.

A block's j-th pass always draws the samples of pass j (`BlockRenderer.render_passes`; a
round is a step, `renderer.passloop`), so a block ends with the very image the unbudgeted
loop gives it at the same spp; blocks that reach the target stop as always. When the
budget ends, the blocks still above the target are listed with their ratios
(`above_target`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .passloop import PassLoop
from .spec import RenderSpec

#: a round renders the active blocks whose priority is at least this share of the largest
BAND = 0.8


@dataclass
class Budget:
    """What a budget render may still spend, and which blocks a round renders.

    `spp_budget`: samples per pixel averaged over the blocks (None: no sample budget);
    `time_limit`: seconds (None: none). `band`: see the module docstring. The limits are
    the render spec's (`renderer.spec`), checked there.
    """

    spp_budget: float | None = None
    time_limit: float | None = None
    band: float = BAND
    per_sample: bool = True
    ended: bool = False
    prioritised_rounds: int = 0
    _cost: list[float] = field(default_factory=lambda: [0.0, 0.0])   # render seconds, block-spp rendered

    def __post_init__(self) -> None:
        if not 0.0 < self.band <= 1.0:
            raise ValueError(f"band must be in (0, 1], got {self.band!r}")

    @classmethod
    def for_spec(cls, spec: RenderSpec) -> Budget | None:
        """The budget a render spec asks for (None: neither an spp budget nor a time limit)."""
        if spec.spp_budget is None and spec.time_limit is None:
            return None
        return cls(spec.spp_budget, spec.time_limit)

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps of the budget, so a resumed budget render goes on as the
        interrupted one would have (`renderer.checkpoint`)."""
        return {"prioritised_rounds": self.prioritised_rounds, "ended": self.ended, "cost": list(self._cost)}

    def restore(self, state: dict[str, Any]) -> None:
        self.prioritised_rounds = int(state["prioritised_rounds"])
        self.ended = bool(state["ended"])
        self._cost = [float(c) for c in state["cost"]]

    def record(self, seconds: float, block_spp: int) -> None:
        """Seconds of a round and the block-samples it traced (the time budget's rate)."""
        self._cost[0] += float(seconds)
        self._cost[1] += float(block_spp)

    def _left(self, spp: np.ndarray, elapsed: float) -> float:
        """Block-spp the budget still allows (inf: no bound known yet)."""
        left = math.inf
        if self.spp_budget is not None:
            left = self.spp_budget * len(spp) - float(spp.sum())
        if self.time_limit is not None and self._cost[1] > 0:
            rate = self._cost[0] / self._cost[1]
            left = min(left, max(0.0, self.time_limit - elapsed) / rate if rate > 0 else math.inf)
        return left

    def select(self, loop: PassLoop, elapsed: float = 0.0) -> list[int]:
        """The blocks of the next round, in block order ([]: the budget or the blocks ran out)."""
        acc = loop.acc
        n = acc.n_blocks
        spp, passes = acc.spp_all(), acc.passes_all()
        ids = np.flatnonzero(loop.pending())
        if not ids.size:
            return []
        next_spp = loop.pass_spp[passes[ids]]           # what each block's next pass costs
        left = self._left(spp, elapsed)
        if left >= float((int(loop.schedule[-1]) - spp[ids]).sum()):
            return ids.tolist()                            # enough for everything: as unbudgeted
        known, _ = loop.ratios.take(ids)
        unknown = ids[~known & ((spp[ids] >= loop.min_spp) if loop.min_spp is not None else True)]
        if unknown.size:            # judged before a resume: ask again (same state, same answer)
            loop.judge(unknown.tolist())
        ratio = self.priority(loop, ids)
        top = ratio.max()
        chosen = ratio >= self.band * top if np.isfinite(top) else ~np.isfinite(ratio)
        if self.spp_budget is not None:                    # what fits, worst first
            order = np.flatnonzero(chosen)[np.argsort(-ratio[chosen], kind="stable")]
            room = self.spp_budget * n - float(spp.sum())
            fit = []                 # greedy: a block that does not fit leaves its room to the next
            for i, need in zip(order.tolist(), next_spp[order].tolist()):
                if need <= room:
                    fit.append(i)
                    room -= need
            order = np.asarray(fit, np.int64)
            chosen = np.zeros(len(ids), bool)
            chosen[order] = True
        picked = ids[chosen]
        if not picked.size:
            self.ended = True
        elif picked.size < ids.size:
            self.prioritised_rounds += 1                   # blocks now out of step
        return picked.tolist()

    def priority(self, loop: PassLoop, ids: np.ndarray) -> np.ndarray:
        """The priority `select` ranks blocks `ids` by: each one's last ratio to its target
        (inf: no estimate yet, so first), over sqrt(spp) with `per_sample`."""
        _, ratio = loop.ratios.take(ids)
        ratio = np.where(np.isnan(ratio), np.inf, ratio)
        if self.per_sample:
            ratio = ratio / np.sqrt(np.maximum(loop.acc.spp_all()[ids], 1))
        return ratio

    def finished(self, loop: PassLoop) -> bool:
        """Whether the render is over: no block is pending, or the sample budget cannot pay
        for another pass of any of them (the budget ended)."""
        acc = loop.acc
        left = loop.pending()
        if not left.any():
            return True
        if self.spp_budget is None:
            return False
        next_spp = loop.pass_spp[acc.passes_all()[left]]
        if int(next_spp.min()) > self.spp_budget * acc.n_blocks - float(acc.spp_all().sum()):
            self.ended = True
        return self.ended

    def describe(self, loop: PassLoop, time_limit_reached: bool = False) -> dict[str, Any]:
        """report.json "budget": the limits, whether they ended the render, and the blocks
        still above their target (worst first) with their last ratio to it."""
        ended = bool(self.ended or time_limit_reached)
        spp = loop.acc.spp_all()
        ids = np.flatnonzero(loop.active)
        _, ratio = loop.ratios.take(ids)
        above = [{"id": int(b), "ratio": None if math.isnan(r) else float(r), "spp": int(spp[b])}
                 for b, r in zip(ids.tolist(), ratio.tolist())]
        above.sort(key=lambda x: -(math.inf if x["ratio"] is None else x["ratio"]))
        return {"spp_budget": self.spp_budget, "time_limit": self.time_limit, "band": self.band,
                "ended": ended, "prioritised_rounds": self.prioritised_rounds,
                "above_target": above if ended else []}
