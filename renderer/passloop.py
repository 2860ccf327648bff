"""The pass loop: what one step of a progressive render does, for the live render and the
simulation on stored stacks alike.

The vocabulary: the `schedule` is the spp at the end of each pass (pass j adds
`pass_spp[j]` samples per pixel); a block's `pass_index` is how many passes it has; it is
`pending` while it is active and has a pass left.

**One step** (the one explanation; other modules point here). The caller picks blocks
and their passes (`renderer.session.RenderSession.step`: every pending block at its next
pass, several passes per launch as blocks stop, or in a budget render the blocks
`renderer.budget.Budget.select` picks) and traces them (`BlockRenderer.render_passes`, or
a stack's recovered passes in `renderer.simulate`). `PassLoop.step` then:

1. adds each pass to the `BlockAccumulator` (exact means, even/odd half buffers, tensors on
   the accumulator's device); each pass is one row of the verdict history;
2. applies the stop rule's gate (`learning.stoprule.decide_active`): the blocks of the step
   at or past min_spp and at their next decision (`next_decision`; always at the last pass) are judged in one batched `Criterion.decide`, and those it calls
   converged leave the active set for good: never traced, featured or asked again.

The loop owns what a render accumulates: the counters and timers of its decisions, each
block's last ratio to its target (`BlockRatios`, what a budget spends by) and each unit's
decision history for a criterion that decides from it (`learning.inputs.history.Evidence`). A criterion is
configuration only. Everything per block is an array; only verdicts and numbers cross to
the host.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from learning.data.accumulator import BlockAccumulator
from learning.inputs.history import Evidence
from learning.stoprule import decide_active

from .criteria import COUNTER_NAMES, TIMER_NAMES, BlockBatch, Criterion, Decision


def schedule(step: int, max_spp: int) -> np.ndarray:
    """The spp at the end of each pass up to max_spp, int64 (the last pass may be shorter)."""
    return np.minimum(np.arange(1, -(-int(max_spp) // int(step)) + 1, dtype=np.int64) * int(step), int(max_spp))


def next_decision(spp: np.ndarray, ratio: np.ndarray, skip: float) -> np.ndarray:
    """int64 [k]: the spp at which units just judged at `spp` with ratio to target `ratio`
    are judged next. Monte Carlo noise falls as 1/sqrt(spp), so a unit r times above its
    target is predicted to reach it at spp r^2; it is judged again at spp (skip r)^2, a
    factor skip^2 before that prediction, and after the next pass where that is no later
    (r <= 1/skip, no estimate, or skip 0: every pass). Why: a decision costs the same
    whether or not the unit can stop, and far from its target it cannot (issue 50)."""
    r = np.asarray(ratio, np.float64)
    grow = np.where(np.isfinite(r), np.clip((skip * r) ** 2, 1.0, float(1 << 20)), 1.0)
    return np.floor(np.asarray(spp, np.float64) * grow).astype(np.int64)


def block_events(history: np.ndarray, block_spp: np.ndarray) -> dict[int, list[tuple[int, int]]]:
    """Each decided block's own [(spp, verdict)], in history order, from the verdict rows
    [K, n] and every block's spp after each row [K, n] (budget rounds put blocks at
    different spp in one row, so the spp are the block's own). Read once, for the report."""
    rows, cols = np.nonzero(history.T)              # block-major, rows in order within a block
    out: dict[int, list[tuple[int, int]]] = {}
    for b, s, v in zip(rows.tolist(), block_spp[cols, rows].tolist(), history[cols, rows].tolist()):
        out.setdefault(b, []).append((s, v))
    return out


class BlockRatios:
    """Per block, how far its last verdict was from the target, as a ratio (> 1: above it;
    NaN: no estimate): arrays indexed by block id, read and written a batch at a time."""

    def __init__(self, n: int) -> None:
        self.asked = np.zeros(n, bool)
        self.value = np.full(n, np.nan)

    def put(self, ids: Any, ratio: Any) -> None:
        idx = np.asarray(ids, np.int64).reshape(-1)
        self.asked[idx] = True
        self.value[idx] = np.asarray(ratio, np.float64).reshape(-1)

    def take(self, ids: Any) -> tuple[np.ndarray, np.ndarray]:
        """(asked bool [k], ratio float64 [k], NaN where unknown) of blocks `ids`."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        return self.asked[idx].copy(), np.where(self.asked[idx], self.value[idx], np.nan)


class PassLoop:
    """Active set, accumulator, verdict history, decision counters and ratios of one render.

    Its units are a live render's tiles (`grid` = (blocks, tiles a block), `block` the tile's
    shape; `tiling`, the renderer's `BlockWindows`, puts them back into blocks for a
    criterion that judges a tile in its block's context), or blocks. `schedule`: the spp at
    the end of each pass; `min_spp`: no decision below it (None: from the first pass);
    `decide_skip`: how far a unit's decisions skip towards its predicted stop
    (`next_decision`; 0: every pass).
    `quick`: the quick image's blocks [n, bh, bw, 3] when the criterion reads them
    (prepared once here). `device`: where the accumulator's tensors live (the renderer's).
    `state()` / `restore` is what the live render checkpoints.
    """

    def __init__(self, criterion: Criterion, grid: tuple[int, int], block: tuple[int, int],
                 schedule: Sequence[int], min_spp: int | None, quick: np.ndarray | None = None,
                 device: Any = None, tiling: Any = None, decide_skip: float = 0.0) -> None:
        self.criterion, self.min_spp, self.device = criterion, min_spp, device
        #: the skip of `next_decision`, for a criterion whose ratio it can predict from
        self.decide_skip = decide_skip if criterion.noise_ratio else 0.0
        self.tiling = tiling if tiling is not None and tiling.tiles_per_block > 1 else None
        self.schedule = np.asarray(schedule, np.int64)
        self.pass_spp = np.diff(self.schedule, prepend=0)
        self.acc = BlockAccumulator(grid, block, device=device)
        n = self.acc.n_blocks
        self.counters = {k: 0 for k in COUNTER_NAMES}
        self.timers = {k: 0.0 for k in TIMER_NAMES}
        self.ratios = BlockRatios(n)
        self.evidence = Evidence(n)
        self.quick = None
        if quick is not None:
            self.quick, made = criterion.prepare(quick)
            self._count(made, {"features_s": float(made.pop("features_s", 0.0))})
        self.active = np.ones(n, bool)
        self.stop_spp = np.zeros(n, np.int64)
        self.next_spp = np.zeros(n, np.int64)          # each unit's next decision (`next_decision`)
        self.history = np.zeros((0, n), np.int8)
        self.history_spp = np.zeros(0, np.int64)
        self.history_block_spp = np.zeros((0, n), np.int64)   # every block's spp after each row
        self.rendered = np.zeros(0, np.int64)

    def pending(self) -> np.ndarray:
        """bool [n]: the blocks that still get passes (active, with a pass left)."""
        return self.active & (self.acc.passes_all() < len(self.schedule))

    def step(self, ids: Sequence[int], passes: Sequence[tuple[Any, int | Sequence[int]]]) -> np.ndarray:
        """One step (the module docstring): add `passes` to the blocks `ids` (each an
        (images [len(ids), bh, bw, 3], pass_spp) pair: one spp for all or one per block;
        images on any device), then judge them through the stop rule's gate.

        The verdicts go in the step's last history row. Returns that row, int8 [n]: +1
        converged now, -1 noisy, 0 not asked.
        """
        idx = np.asarray(ids, np.int64).reshape(-1)
        if not idx.size:
            raise ValueError("a step renders at least one block")
        if not passes:
            raise ValueError("a step adds at least one pass")
        if not self.active[idx].all():
            raise ValueError(f"blocks {idx[~self.active[idx]].tolist()} are stopped: they get no samples")
        rows_spp = []
        for images, pass_spp in passes:
            self.acc.add_batch(idx, images, pass_spp)
            rows_spp.append(self.acc.spp_all())
        due = idx[(rows_spp[-1][idx] >= self.next_spp[idx]) | (self.acc.passes_all()[idx] == len(self.schedule))]
        row = decide_active(self.active, rows_spp[-1], self.min_spp, self.judge, among=due) if due.size \
            else np.zeros(len(self.active), np.int8)
        stopped = row > 0
        self.stop_spp[stopped] = rows_spp[-1][stopped]
        rows = np.zeros((len(passes), len(self.active)), np.int8)
        rows[-1] = row
        self.history = np.vstack([self.history, rows])
        self.history_spp = np.append(self.history_spp, [int(r[idx].max()) for r in rows_spp])
        self.history_block_spp = np.vstack([self.history_block_spp, np.stack(rows_spp)])
        self.rendered = np.append(self.rendered, [len(idx)] * len(passes))
        return row

    def judge(self, ids: Sequence[int]) -> np.ndarray:
        """The criterion's verdicts int8 [k] on blocks as they stand, counted, their ratios
        kept; the active set is `step`'s to change (a resumed budget render asks blocks
        judged before the interruption again: same state, same answer)."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        d: Decision = self.criterion.decide(idx, BlockBatch.from_accumulator(self.acc, idx, self.quick, self.tiling,
                                                                            self.evidence))
        self.ratios.put(idx, d.ratio)
        self.next_spp[idx] = next_decision(self.acc.spp_all()[idx], d.ratio, self.decide_skip)
        if d.evidence is not None:
            self.evidence.add(idx, d.evidence, self.acc.spp_all()[idx])
        self._count(d.counts, d.timers)
        return d.verdict

    def _count(self, counts: dict[str, Any] | Any, timers: dict[str, float] | Any) -> None:
        for k, v in counts.items():
            self.counters[k] = self.counters.get(k, 0) + int(v)
        for k, v in timers.items():
            self.timers[k] = self.timers.get(k, 0.0) + float(v)

    @property
    def events(self) -> dict[int, list[tuple[int, int]]]:
        """Each decided block's own [(spp, verdict)], in order (`block_events`)."""
        return block_events(self.history, self.history_block_spp)

    # -- checkpointing ---------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return {"acc": self.acc.state(), "active": self.active, "stop_spp": self.stop_spp,
                "history": self.history, "history_spp": self.history_spp,
                "history_block_spp": self.history_block_spp, "rendered": self.rendered,
                "evidence": self.evidence.sums, "next_spp": self.next_spp}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a validated checkpoint's state (`renderer.checkpoint`)."""
        acc = state["acc"]
        self.acc = BlockAccumulator.from_state(acc.state() if isinstance(acc, BlockAccumulator) else acc,
                                               device=self.device)
        self.active = np.asarray(state["active"], bool).copy()
        self.stop_spp = np.asarray(state["stop_spp"], np.int64).copy()
        self.history = np.asarray(state["history"], np.int8).reshape(-1, len(self.active))
        self.history_spp = np.asarray(state["history_spp"], np.int64)
        self.rendered = np.asarray(state["rendered"], np.int64)
        self.history_block_spp = np.asarray(state["history_block_spp"], np.int64).reshape(self.history.shape)
        asked = self.history != 0                      # each unit's last decision, what its next weight counts from
        last_row = np.where(asked.any(axis=0), len(asked) - 1 - np.argmax(asked[::-1], axis=0), -1)
        self.evidence.restore(state["evidence"], np.where(
            last_row >= 0, self.history_block_spp[np.maximum(last_row, 0), np.arange(len(self.active))], 0))
        self.next_spp = np.asarray(state["next_spp"], np.int64).copy()
        self.counters.update({k: int(v) for k, v in state.get("counters", {}).items() if k in COUNTER_NAMES})
        self.timers.update({k: float(v) for k, v in state.get("timers", {}).items() if k in TIMER_NAMES})
