"""A render in progress, typed (a misspelt key or a wrong dtype fails where it is made, not when a
checkpoint is read back): what it has done (`Progress`) and what a resume must match (`RunSettings`);
`renderer.live.checkpoint` alone turns these into arrays and back."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.data.accumulator import UnitAccumulator

if TYPE_CHECKING:
    from .plan import RenderPlan


@dataclass(frozen=True)
class RunSettings:
    """The spec as rendered: what a resume must match and report.json repeats. `resolution`
    is (width, height); `grid`, `block` and `tile` are (rows, columns) and (height, width);
    `quick` is the quick image's kind ("none" when the criterion reads none); `spp_budget`
    None: no sample budget."""

    scene: str
    resolution: tuple[int, int]
    grid: tuple[int, int]
    block: tuple[int, int]
    tile: tuple[int, int]
    exposure: float
    step: int
    min_spp: int
    max_spp: int
    decide_skip: float
    decide_growth: float
    seed: int
    quick_spp: int
    quick: str
    criterion: Mapping[str, Any]
    variant: str
    defines: Mapping[str, Any]
    tau: float
    spp_budget: float | None = None

    @classmethod
    def of(cls, plan: RenderPlan) -> RunSettings:
        spec, br, crit = plan.spec, plan.renderer, plan.criterion
        return cls(scene=plan.scene, **br.geometry(), exposure=float(spec.exposure),
                   step=int(spec.step), min_spp=int(spec.min_spp), max_spp=int(spec.max_spp),
                   decide_skip=float(spec.decide_skip), decide_growth=float(spec.decide_growth),
                   seed=int(spec.seed), quick_spp=int(spec.quick_spp),
                   quick=crit.quick_kind if crit.needs_quick else "none", criterion=crit.describe(),
                   variant=plan.variant, defines=dict(spec.defines or {}), tau=float(spec.tau),
                   spp_budget=None if spec.spp_budget is None else float(spec.spp_budget))


@dataclass
class LoopState:
    """The loop's share (`PassLoop.state`). Per unit (n): `active`, `stop_spp` (0 while
    active), decision `evidence` float64 [n, 2] (sum, samples weighed) and `next_spp`, the spp
    of its next decision. Per history row (a pass, or a budget round's pass): verdicts
    `history` int8 [rows, n], the largest spp `history_spp`, every unit's spp after it
    `history_unit_spp` [rows, n] and the units it rendered, `rendered`."""

    acc: UnitAccumulator
    active: np.ndarray
    stop_spp: np.ndarray
    history: np.ndarray
    history_spp: np.ndarray
    history_unit_spp: np.ndarray
    rendered: np.ndarray
    evidence: np.ndarray
    next_spp: np.ndarray

    @property
    def rows(self) -> int:
        """The verdict history's rows: report.json "passes", the checkpoint's "pass_index"."""
        return int(self.history.shape[0])


@dataclass
class BudgetState:
    """A budget render's share (`Budget.state`): the rounds that rendered only some units,
    whether the budget ended, what the rounds cost (seconds, unit-spp traced), and each unit's
    last ratio to its target (`ratio_asked`: whether it has one)."""

    prioritised_rounds: int
    ended: bool
    cost: tuple[float, float]
    ratio_asked: np.ndarray
    ratio: np.ndarray


@dataclass
class Progress:
    """What a checkpoint holds and a resume goes on from. `counters` and `timers`: the
    ledger's (wall_s up to the moment it was taken); `quick`: float32 [H, W, 3], None when the
    criterion reads none; `budget`: None unless a budget render."""

    loop: LoopState
    done: bool = False
    counters: dict[str, int] = field(default_factory=dict)
    timers: dict[str, float] = field(default_factory=dict)
    quick: np.ndarray | None = None
    budget: BudgetState | None = None

    @property
    def rows(self) -> int:
        return self.loop.rows
