"""A budget render (``--spp-budget N``, ``--time-limit S``): spend the samples where the noise is.

docs/guide/rendering.md, "Budgets and time limits", says what it renders. A round takes the whole blocks whose
`priority` is at least `BAND` times the largest: samples in proportion to each unit's noise per sample, which
lowers both the worst and the mean error against uniform sampling (Cauchy-Schwarz; levelling the ratio itself
helps the worst unit most but measured worse on the mean).
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
    blocks they lie in, and the unit-spp of each such block's next pass."""
    per_block = loop.tiling.tiles_per_block if loop.tiling is not None else 1
    _, block = np.unique(np.asarray(ids, np.int64) // per_block, return_inverse=True)
    need = np.zeros(int(block.max()) + 1 if block.size else 0)
    np.add.at(need, block, loop.pass_spp[loop.acc.pass_counts()[ids]])
    return block, need


@dataclass
class Budget:
    """What a budget render may still spend, and which units a round renders. `spp_budget`: samples per
    pixel averaged over the units; `time_limit`: seconds (None: none; both checked by the render spec);
    `ledger`: where the rounds' cost goes."""

    spp_budget: float | None = None
    time_limit: float | None = None
    ended: bool = False
    prioritised_rounds: int = 0
    ledger: Ledger = field(default_factory=Ledger)

    @classmethod
    def for_spec(cls, spec: RenderSpec, ledger: Ledger, resumed: bool = False) -> Budget | None:
        """The budget a render spec asks for (None: no limit). `resumed` from a budget render's
        checkpoint (units at different pass counts), a render without limits gets a budget of
        none, so its checkpoints stay a budget render's."""
        if spec.spp_budget is None and spec.time_limit is None and not resumed:
            return None
        return cls(spec.spp_budget, spec.time_limit, ledger=ledger)

    @property
    def limited(self) -> bool:
        """Whether it has a limit (a resumed render's budget of none has not)."""
        return self.spp_budget is not None or self.time_limit is not None

    def judges_every_unit(self, max_spp: int) -> bool:
        """Whether the render judges every unit it renders at every pass (no skip, no growth):
        with an spp budget below max spp, which can bind, so the ratios that pick where samples
        go are fresh. From the settings alone, so a render and its resumes decide alike."""
        return self.spp_budget is not None and self.spp_budget < max_spp

    def state(self, ratios: UnitRatios) -> BudgetState:
        """What a checkpoint keeps of the budget, with the loop's `ratios` it picks units by."""
        asked, ratio = ratios.take(np.arange(len(ratios.asked)))
        seconds, traced = self.ledger.budget_cost
        return BudgetState(prioritised_rounds=self.prioritised_rounds, ended=self.ended,
                           cost=(float(seconds), float(traced)), ratio_asked=asked, ratio=ratio)

    def restore(self, state: BudgetState) -> None:
        """Go on from a checkpoint's budget (the session puts the ratios back in the loop)."""
        self.prioritised_rounds = int(state.prioritised_rounds)
        self.ended = bool(state.ended)
        self.ledger.budget_cost = [float(c) for c in state.cost]

    def record(self, seconds: float, unit_spp: int) -> None:
        """Seconds of a round and the unit-samples it traced (the time limit's rate)."""
        cost = self.ledger.budget_cost
        cost[0] += float(seconds)
        cost[1] += float(unit_spp)

    def left(self, spp: np.ndarray, elapsed: float) -> float:
        """Unit-spp the budget still allows (inf: no bound known yet), `spp` every unit's now."""
        left = math.inf if self.spp_budget is None else self.spp_budget * len(spp) - float(spp.sum())
        seconds, traced = self.ledger.budget_cost
        if self.time_limit is not None and traced > 0:
            rate = seconds / traced
            left = min(left, max(0.0, self.time_limit - elapsed) / rate if rate > 0 else math.inf)
        return left

    def select(self, loop: PassLoop, elapsed: float = 0.0) -> list[int]:
        """The units of the next round, in unit order ([]: the budget or the units ran out): all pending ones while
        the budget covers them, else whole blocks within the band, worst first as far as an spp budget pays."""
        spp = loop.acc.spp_all()
        ids = np.flatnonzero(loop.pending())
        if not ids.size:
            return []
        if self.left(spp, elapsed) >= float((int(loop.schedule[-1]) - spp[ids]).sum()):
            return ids.tolist()                            # enough for everything: as unbudgeted
        block, need = needs(loop, ids)
        prio = np.full(len(need), -np.inf)
        np.maximum.at(prio, block, self.priority(loop, ids))   # a block: its worst unit
        top = prio.max()
        chosen = prio >= BAND * top if np.isfinite(top) else ~np.isfinite(prio)
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
        """Units `ids`' ratios brought to their spp now (inf: no estimate yet, so first), over sqrt(spp)."""
        spp = loop.acc.spp_all()[ids]
        ratio = loop.ratios.predicted(ids, spp)
        return np.where(np.isnan(ratio), np.inf, ratio) / np.sqrt(np.maximum(spp, 1))

    def finished(self, loop: PassLoop) -> bool:
        """Whether no unit is pending, or the spp budget cannot pay another pass of any block."""
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
        """report.json "budget": the limits, whether they ended the render, and the units still
        above their target, worst first."""
        ended = bool(self.ended or time_limit_reached)
        spp = loop.acc.spp_all()
        ids = np.flatnonzero(loop.active)
        _, ratio = loop.ratios.take(ids)
        above = [{"id": int(b), "ratio": None if math.isnan(r) else float(r), "spp": int(spp[b])}
                 for b, r in zip(ids.tolist(), ratio.tolist())]
        above.sort(key=lambda x: -(math.inf if x["ratio"] is None else x["ratio"]))
        return {"spp_budget": self.spp_budget, "time_limit": self.time_limit, "band": BAND,
                "judges_every_unit": self.judges_every_unit(int(loop.schedule[-1])), "ended": ended,
                "prioritised_rounds": self.prioritised_rounds,
                "above_target": above if ended else []}
