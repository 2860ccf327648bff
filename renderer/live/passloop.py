"""The pass loop: one round of a progressive render, live or simulated on stored stacks.

The loop's words (defined here; docs/codemap.md repeats them):

* a *unit* is what the loop samples, judges and stops: a tile of a block, or the block itself at block
  grain (unit u is tile u % T of block u // T: `renderer.live.block_windows`);
* a *pass* adds `pass_spp[j]` (the *step*) samples per pixel to some units; j, its *pass index*, keys its
  random numbers; `schedule` holds the spp at each pass's end; a unit's *pass count* is how many passes it
  holds (a row of the verdict history each); it is *pending* while active with a pass left;
* a *round* adds one or more passes to some units, then judges those due in one batched `Criterion.decide`
  through the stop rule's gate (`learning.stoprule.decide_active`): those called converged leave the active
  set for good (`run_round`);
* a *launch* traces the passes of one or more rounds at once (`RenderSession.advance`).

A criterion is configuration only: the loop owns what a render accumulates.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from learning.data.accumulator import UnitAccumulator
from learning.inputs.history import Evidence, last_decided_spp
from learning.stoprule import decide_active

from ..criteria import COUNTER_NAMES, TIMER_NAMES, UnitBatch, Criterion, Decision
from .ledger import Ledger
from .progress import LoopState


def schedule(step: int, max_spp: int) -> np.ndarray:
    """The spp at the end of each pass up to max_spp, int64 (the last pass may be shorter)."""
    return np.minimum(np.arange(1, -(-int(max_spp) // int(step)) + 1, dtype=np.int64) * int(step), int(max_spp))


def next_decision(spp: np.ndarray, ratio: np.ndarray, skip: float, growth: float = 0.0) -> np.ndarray:
    """int64 [k]: the spp at which units judged at `spp`, `ratio` times their target, are judged next.
    Noise falls as 1/sqrt(spp): judge again at (skip r)^2 times its spp, not before (1 + growth) times it
    (a decision costs the same whether or not the unit can stop). No estimate: the next pass."""
    r = np.asarray(ratio, np.float64)
    finite = np.isfinite(r)
    with np.errstate(over="ignore"):              # a huge ratio: the clip's top
        predicted = np.clip((skip * np.where(finite, r, 0.0)) ** 2, 1.0 + growth, float(1 << 20))
    return np.floor(np.asarray(spp, np.float64) * np.where(finite, predicted, 1.0)).astype(np.int64)


class UnitRatios:
    """Per unit, its last verdict's ratio to the target (> 1: above it; NaN: no estimate)."""

    def __init__(self, n: int) -> None:
        self.asked = np.zeros(n, bool)
        self.value = np.full(n, np.nan)
        self.spp = np.zeros(n, np.int64)        # the spp each ratio was taken at

    def put(self, ids: Any, ratio: Any, spp: Any) -> None:
        """Units `ids`' ratios, taken at their `spp` (one value for all, or one each)."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        self.asked[idx] = True
        self.value[idx] = np.asarray(ratio, np.float64).reshape(-1)
        self.spp[idx] = np.broadcast_to(np.asarray(spp, np.int64), idx.shape)

    def predicted(self, ids: Any, spp: Any) -> np.ndarray:
        """float64 [k]: the ratios of units `ids` brought to `spp` [k] by 1/sqrt(spp) (NaN where
        unknown), so a unit whose decisions skip passes is ranked by its noise now."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        now = np.maximum(np.asarray(spp, np.float64).reshape(-1), 1.0)
        return self.take(idx)[1] * np.sqrt(np.maximum(self.spp[idx], 1) / now)

    def take(self, ids: Any) -> tuple[np.ndarray, np.ndarray]:
        """(asked bool [k], ratio float64 [k], NaN where unknown) of units `ids`."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        return self.asked[idx].copy(), np.where(self.asked[idx], self.value[idx], np.nan)


class PassLoop:
    """Active set, accumulator, verdict history and ratios of one render's units. `grid`: the units as
    (rows, columns), row-major. `tiling` (the renderer's `BlockWindows`) puts tiles back into their blocks
    for a criterion that judges a tile in its block's context. `decide_skip`, `decide_growth`: see
    `next_decision`. `quick`: the quick image's blocks [n, bh, bw, 3] when the criterion reads them."""

    def __init__(self, criterion: Criterion, grid: tuple[int, int], unit_shape: tuple[int, int],
                 schedule: Sequence[int], min_spp: int | None, quick: np.ndarray | None = None,
                 device: Any = None, tiling: Any = None, decide_skip: float = 0.0, decide_growth: float = 0.0,
                 ledger: Ledger | None = None) -> None:
        self.criterion, self.min_spp, self.device = criterion, min_spp, device
        self.ledger = Ledger(COUNTER_NAMES, TIMER_NAMES) if ledger is None else ledger
        # skipping needs a ratio that predicts where the noise goes
        self.decide_skip = decide_skip if criterion.noise_ratio else 0.0
        self.decide_growth = decide_growth if criterion.noise_ratio else 0.0
        self.tiling = tiling if tiling is not None and tiling.tiles_per_block > 1 else None
        self.schedule = np.asarray(schedule, np.int64)
        self.pass_spp = np.diff(self.schedule, prepend=0)
        self.acc = UnitAccumulator(grid, unit_shape, device=device)
        n = self.acc.n_units
        self.ratios = UnitRatios(n)
        self.evidence = Evidence(n)
        self.quick = None
        if quick is not None:
            self.quick, made = criterion.prepare(quick)
            self.ledger.add(made, {"features_s": float(made.pop("features_s", 0.0))})
        self.active = np.ones(n, bool)
        self.stop_spp = np.zeros(n, np.int64)
        self.next_spp = np.zeros(n, np.int64)          # each unit's next decision (`next_decision`)
        self.history = np.zeros((0, n), np.int8)
        self.history_spp = np.zeros(0, np.int64)
        self.history_unit_spp = np.zeros((0, n), np.int64)   # every unit's spp after each row
        self.rendered = np.zeros(0, np.int64)

    def pending(self) -> np.ndarray:
        """bool [n]: the units that still get passes (active, with a pass left)."""
        return self.active & (self.acc.pass_counts() < len(self.schedule))

    def due_pass(self, ids: Any, first: Any) -> np.ndarray:
        """int64 [k]: for units `ids` whose next pass is `first` [k], the first pass index at or
        after it whose round judges them (at their next decision and min_spp, at the latest
        their last pass). The passes before it cannot stop them."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        target = np.maximum(self.next_spp[idx], 0 if self.min_spp is None else int(self.min_spp))
        at = np.searchsorted(self.schedule, target, side="left") if self.criterion.stops else len(self.schedule)
        return np.clip(np.maximum(at, np.asarray(first, np.int64).reshape(-1)), 0, len(self.schedule) - 1)

    def run_round(self, ids: Sequence[int], passes: Sequence[tuple[Any, int | Sequence[int]]]) -> np.ndarray:
        """One round: add `passes`, (images [len(ids), uh, uw, 3], pass_spp: one for all or one
        per unit) pairs, to units `ids`, then judge those due. Returns the round's last history
        row, int8 [n]: +1 converged now, -1 noisy, 0 not asked."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        if not idx.size:
            raise ValueError("a round renders at least one unit")
        if not passes:
            raise ValueError("a round adds at least one pass")
        if not self.active[idx].all():
            raise ValueError(f"units {idx[~self.active[idx]].tolist()} are stopped: they get no samples")
        rows_spp = []
        for images, pass_spp in passes:
            self.acc.add_batch(idx, images, pass_spp)
            rows_spp.append(self.acc.spp_all())
        # due: at its next decision (a criterion that never stops: never) or at its last pass
        reached = rows_spp[-1][idx] >= self.next_spp[idx] if self.criterion.stops else False
        due = idx[reached | (self.acc.pass_counts()[idx] == len(self.schedule))]
        row = decide_active(self.active, rows_spp[-1], self.min_spp, self.judge, among=due) if due.size \
            else np.zeros(len(self.active), np.int8)
        stopped = row > 0
        self.stop_spp[stopped] = rows_spp[-1][stopped]
        rows = np.zeros((len(passes), len(self.active)), np.int8)
        rows[-1] = row
        self.history = np.vstack([self.history, rows])
        self.history_spp = np.append(self.history_spp, [int(r[idx].max()) for r in rows_spp])
        self.history_unit_spp = np.vstack([self.history_unit_spp, np.stack(rows_spp)])
        self.rendered = np.append(self.rendered, [len(idx)] * len(passes))
        return row

    def judge(self, ids: Sequence[int]) -> np.ndarray:
        """The criterion's verdicts int8 [k] on units as they stand; keeps their ratios and next
        decisions, puts the cost in the ledger. Only a round calls it: a decision off the
        units' schedule would move their next decision and evidence."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        d: Decision = self.criterion.decide(idx, UnitBatch.from_accumulator(self.acc, idx, self.quick, self.tiling,
                                                                            self.evidence))
        spp = self.acc.spp_all()[idx]
        self.ratios.put(idx, d.ratio, spp)
        self.next_spp[idx] = next_decision(spp, d.ratio, self.decide_skip, self.decide_growth)
        if d.evidence is not None:
            self.evidence.add(idx, d.evidence, spp)
        self.ledger.add(d.counts, d.timers)
        return d.verdict

    @property
    def events(self) -> dict[int, list[tuple[int, int]]]:
        """Each decided unit's own [(spp, verdict)], in order (a budget row holds units at different spp)."""
        units, rows = np.nonzero(self.history.T)        # unit-major, rows in order within a unit
        out: dict[int, list[tuple[int, int]]] = {}
        for u, s, v in zip(units.tolist(), self.history_unit_spp[rows, units].tolist(),
                           self.history[rows, units].tolist()):
            out.setdefault(u, []).append((s, v))
        return out

    @property
    def rows(self) -> int:
        """The verdict history's rows so far: one a pass of a round."""
        return int(self.history.shape[0])

    def state(self) -> LoopState:
        """What a checkpoint keeps of the loop: its live accumulator and arrays, not copies."""
        return LoopState(acc=self.acc, active=self.active, stop_spp=self.stop_spp, history=self.history,
                         history_spp=self.history_spp, history_unit_spp=self.history_unit_spp,
                         rendered=self.rendered, evidence=self.evidence.sums, next_spp=self.next_spp)

    def restore(self, state: LoopState) -> None:
        """Continue from a validated checkpoint's state (the session restores the ledger)."""
        self.acc = UnitAccumulator.from_state(state.acc.state(), device=self.device)
        self.active = np.asarray(state.active, bool).copy()
        self.stop_spp = np.asarray(state.stop_spp, np.int64).copy()
        self.history = np.asarray(state.history, np.int8).reshape(-1, len(self.active))
        self.history_spp = np.asarray(state.history_spp, np.int64)
        self.rendered = np.asarray(state.rendered, np.int64)
        self.history_unit_spp = np.asarray(state.history_unit_spp, np.int64).reshape(self.history.shape)
        self.evidence.restore(state.evidence, last_decided_spp(self.history, self.history_unit_spp))
        self.next_spp = np.asarray(state.next_spp, np.int64).copy()
