"""A budget render: spend a limited number of samples (or seconds) where the noise is.

Without a budget every pass renders every active unit (the words: `renderer.live.passloop`).
Users with a deadline want the best image by that time instead (Cycles, Arnold and
LuxCore pair a noise target with a time limit), so with ``--spp-budget N`` (samples per
pixel averaged over the units) or ``--time-limit S`` each round renders the blocks whose
units are farthest from their target, one pass each (with a time limit, as many as the time
left pays for, at most a grown launch's: `renderer.live.session.RenderSession.plan`):

* The loop's `ratios` (`renderer.live.passloop.UnitRatios`) hold, per unit, its last score
  relative to the criterion's threshold (flip: the half-buffer FLIP over c(tau); > 1 is
  above the target). Units with no estimate yet (before their first decision) come
  first, all together.
* Priority = ratio / sqrt(spp). Noise falls as 1/sqrt(spp), so a unit's ratio is about
  a_u / sqrt(spp_u) with a_u its noise per sample; levelling the priority gives each unit
  samples in proportion to a_u. Against uniform sampling with the same samples that
  lowers both the worst unit's error (the noisiest unit gets more than its share) and
  the mean error (Cauchy-Schwarz: sum sqrt(a_u) <= sqrt(U sum a_u)); levelling the ratio
  itself (``per_sample=False``: samples in proportion to a_u^2, every unit to the same
  error) helps the worst unit most but measured worse on the mean.
* A round renders the blocks whose priority (their worst pending unit's) is at least
  `band` times the largest: the worst alone at first, then, as it comes down, every
  block within the band (water filling, in rounds large enough to trace well). A round
  takes every pending unit of a block it picks: a tile is judged in its block's context,
  so only a block whose tiles move together keeps the unbudgeted render's samples and
  decisions.
* While the budget left covers every active unit to max spp, rounds render all of them:
  a budget that does not bind renders exactly what the unbudgeted loop renders, pass for
  pass.
* Decisions: an spp budget below max spp (one that can bind: known from the settings)
  judges every unit it renders at every pass, so the ratios that pick where its samples
  go are fresh (`judges_every_unit`, in report.json too). Otherwise (a larger spp budget,
  a time limit) units are judged when the unbudgeted render judges them, decisions
  skipped and spaced alike (`renderer.live.passloop.next_decision`), and the ratio a
  block is ranked by is brought from its last decision to its spp now.

A unit's j-th pass always draws the samples of pass index j (`BlockRenderer.submit_passes`
traces units at different pass counts in one launch; a round is the loop's,
`PassLoop.run_round`), and it is judged at the spp its own decisions ask for, so a block
goes through the very states of the unbudgeted render (deciding as the budget render
does), only in another order: the units that stop, stop at that render's spp, and a
resume of a render a time limit ended, with or without the limit, ends in the
uninterrupted render's image. What the rounds cost (seconds and unit-spp: the time limit's
rate) is in the render's ledger (`renderer.live.ledger`). When the budget ends, the units
still above the target are listed with their ratios (`above_target`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..spec import RenderSpec
from .ledger import Ledger
from .passloop import PassLoop, UnitRatios
from .progress import BudgetState

#: a round renders the active units whose priority is at least this share of the largest
BAND = 0.8


def needs(loop: PassLoop, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(block [k], need [b]): for pending units `ids`, the index of their block among the
    blocks they lie in, and what each such block's next pass costs (the unit-spp of its
    units' next passes). A budget round takes whole blocks: a tile is judged in its
    block's context (`renderer.live.block_windows`), so a block whose units all move
    together gets the samples and decisions of the unbudgeted render, whatever the order."""
    per_block = loop.tiling.tiles_per_block if loop.tiling is not None else 1
    _, block = np.unique(np.asarray(ids, np.int64) // per_block, return_inverse=True)
    need = np.zeros(int(block.max()) + 1 if block.size else 0)
    np.add.at(need, block, loop.pass_spp[loop.acc.pass_counts()[ids]])
    return block, need


@dataclass
class Budget:
    """What a budget render may still spend, and which units a round renders.

    `spp_budget`: samples per pixel averaged over the units (None: no sample budget);
    `time_limit`: seconds (None: none). `band`: see the module docstring. The limits are
    the render spec's (`renderer.spec`), checked there. `ledger`: where the rounds' cost
    goes (the render's; by default one of its own).
    """

    spp_budget: float | None = None
    time_limit: float | None = None
    band: float = BAND
    per_sample: bool = True
    ended: bool = False
    prioritised_rounds: int = 0
    ledger: Ledger = field(default_factory=Ledger)

    def __post_init__(self) -> None:
        if not 0.0 < self.band <= 1.0:
            raise ValueError(f"band must be in (0, 1], got {self.band!r}")

    @classmethod
    def for_spec(cls, spec: RenderSpec, ledger: Ledger, resumed: bool = False) -> Budget | None:
        """The budget a render spec asks for (None: neither an spp budget nor a time limit),
        reporting to the render's `ledger`. `resumed`: the render goes on from a budget
        render's checkpoint, whose units may be at different pass counts: without limits it
        gets a budget of none (every pending unit each round, at its own next pass), so its
        checkpoints stay a budget render's."""
        if spec.spp_budget is None and spec.time_limit is None and not resumed:
            return None
        return cls(spec.spp_budget, spec.time_limit, ledger=ledger)

    @property
    def limited(self) -> bool:
        """Whether it has a limit (a resumed render's budget of none has not: `for_spec`)."""
        return self.spp_budget is not None or self.time_limit is not None

    def judges_every_unit(self, max_spp: int) -> bool:
        """Whether the render judges every unit it renders at every pass (its decisions
        neither skipped nor spaced: `renderer.live.passloop.next_decision`): with an spp
        budget below max spp, which can bind, so that its ratios, which pick where the
        samples go, are fresh. Known from the settings alone, so every round of a render and
        of its resumes decides alike. A larger spp budget never binds, and a time limit does
        not change decisions: the render decides as without a budget."""
        return self.spp_budget is not None and self.spp_budget < max_spp

    def state(self, ratios: UnitRatios) -> BudgetState:
        """What a checkpoint keeps of the budget, so a resumed budget render goes on as the
        interrupted one would have (`renderer.live.checkpoint`; "cost": the ledger's), with
        the loop's `ratios` it picks units by."""
        asked, ratio = ratios.take(np.arange(len(ratios.asked)))
        seconds, traced = self.ledger.budget_cost
        return BudgetState(prioritised_rounds=self.prioritised_rounds, ended=self.ended,
                           cost=(float(seconds), float(traced)), ratio_asked=asked, ratio=ratio)

    def restore(self, state: BudgetState) -> None:
        """Go on from a checkpoint's budget (its ratios are the loop's: the session puts them back)."""
        self.prioritised_rounds = int(state.prioritised_rounds)
        self.ended = bool(state.ended)
        self.ledger.budget_cost = [float(c) for c in state.cost]

    def record(self, seconds: float, unit_spp: int) -> None:
        """Seconds of a round and the unit-samples it traced, into the ledger (the time
        budget's rate)."""
        cost = self.ledger.budget_cost
        cost[0] += float(seconds)
        cost[1] += float(unit_spp)

    def left(self, spp: np.ndarray, elapsed: float) -> float:
        """Unit-spp the budget still allows (inf: no bound known yet), `spp` every unit's
        now: what `select` picks by, and what sizes a time-limited round's launch
        (`renderer.live.session.RenderSession.plan`)."""
        left = math.inf
        seconds, traced = self.ledger.budget_cost
        if self.spp_budget is not None:
            left = self.spp_budget * len(spp) - float(spp.sum())
        if self.time_limit is not None and traced > 0:
            rate = seconds / traced
            left = min(left, max(0.0, self.time_limit - elapsed) / rate if rate > 0 else math.inf)
        return left

    def select(self, loop: PassLoop, elapsed: float = 0.0) -> list[int]:
        """The units of the next round, in unit order ([]: the budget or the units ran out).

        While the budget left covers every pending unit to max spp: all of them (the
        unbudgeted round). Otherwise whole blocks (`needs`): those whose priority is within
        the band of the largest, worst first as far as an spp budget pays for them."""
        spp = loop.acc.spp_all()
        ids = np.flatnonzero(loop.pending())
        if not ids.size:
            return []
        left = self.left(spp, elapsed)
        if left >= float((int(loop.schedule[-1]) - spp[ids]).sum()):
            return ids.tolist()                            # enough for everything: as unbudgeted
        block, need = needs(loop, ids)
        prio = np.full(len(need), -np.inf)
        np.maximum.at(prio, block, self.priority(loop, ids))   # a block: its worst unit
        top = prio.max()
        chosen = prio >= self.band * top if np.isfinite(top) else ~np.isfinite(prio)
        if self.spp_budget is not None:                    # what fits, worst first
            order = np.flatnonzero(chosen)[np.argsort(-prio[chosen], kind="stable")]
            room = self.spp_budget * loop.acc.n_units - float(spp.sum())
            chosen = np.zeros(len(need), bool)
            for i in order.tolist():     # greedy: a block that does not fit leaves its room to the next
                if need[i] <= room:
                    chosen[i] = True
                    room -= need[i]
        picked = ids[chosen[block]]
        if not picked.size:
            self.ended = True
        elif picked.size < ids.size:
            self.prioritised_rounds += 1                   # units now at different pass counts
        return picked.tolist()

    def priority(self, loop: PassLoop, ids: np.ndarray) -> np.ndarray:
        """The priority `select` ranks units `ids` by: each one's last ratio to its target
        brought to its spp now (`UnitRatios.predicted`; inf: no estimate yet, so first),
        over sqrt(spp) with `per_sample`."""
        spp = loop.acc.spp_all()[ids]
        ratio = loop.ratios.predicted(ids, spp)
        ratio = np.where(np.isnan(ratio), np.inf, ratio)
        if self.per_sample:
            ratio = ratio / np.sqrt(np.maximum(spp, 1))
        return ratio

    def finished(self, loop: PassLoop) -> bool:
        """Whether the render is over: no unit is pending, or the sample budget cannot pay
        for another pass of any block's pending units (the budget ended)."""
        left = np.flatnonzero(loop.pending())
        if not left.size:
            return True
        if self.spp_budget is None:
            return False
        _, need = needs(loop, left)
        if float(need.min()) > self.spp_budget * loop.acc.n_units - float(loop.acc.spp_all().sum()):
            self.ended = True
        return self.ended

    def describe(self, loop: PassLoop, time_limit_reached: bool = False) -> dict[str, Any]:
        """report.json "budget": the limits, whether they ended the render, and the units
        still above their target (worst first) with their last ratio to it."""
        ended = bool(self.ended or time_limit_reached)
        spp = loop.acc.spp_all()
        ids = np.flatnonzero(loop.active)
        _, ratio = loop.ratios.take(ids)
        above = [{"id": int(b), "ratio": None if math.isnan(r) else float(r), "spp": int(spp[b])}
                 for b, r in zip(ids.tolist(), ratio.tolist())]
        above.sort(key=lambda x: -(math.inf if x["ratio"] is None else x["ratio"]))
        return {"spp_budget": self.spp_budget, "time_limit": self.time_limit, "band": self.band,
                "judges_every_unit": self.judges_every_unit(int(loop.schedule[-1])), "ended": ended,
                "prioritised_rounds": self.prioritised_rounds,
                "above_target": above if ended else []}
