"""One step of a progressive render, the same for the live render and the simulation.

Both the live loop (`renderer.adaptive`, passes from Mitsuba) and the simulation on stored
stacks (`renderer.simulate`, passes recovered from the levels) do, per step: add the new
samples of the blocks rendered to the `BlockAccumulator` (exact means, even/odd half
buffers), then ask the criterion, in one batched call, about those of them at or past
min_spp; a block it calls converged leaves the active set for good. A step is one pass of
every active block (a plain pass), one pass of some blocks at their own pass counts (a
budget round), or several passes of the same blocks traced in one launch (a grown pass,
`renderer.adaptive`): `PassLoop.step` is all three, so they cannot drift apart.

Everything per block is an array: the pass images stay on the accumulator's device, the
criterion gets a `BlockBatch`, and only verdicts and counters cross to the host.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from learning.data.accumulator import BlockAccumulator
from learning.stoprule import CONVERGED, NOISY

from .criteria import BlockBatch, Criterion


def block_events(history: np.ndarray, block_spp: np.ndarray) -> dict[int, list[tuple[int, int]]]:
    """Each decided block's own [(spp, verdict)], in history order, from the verdict rows
    [K, n] and every block's spp after each row [K, n] (budget rounds put blocks at
    different spp in one row, so the spp are the block's own). Read once, for the report."""
    rows, cols = np.nonzero(history.T)              # block-major, rows in order within a block
    out: dict[int, list[tuple[int, int]]] = {}
    for b, s, v in zip(rows.tolist(), block_spp[cols, rows].tolist(), history[cols, rows].tolist()):
        out.setdefault(b, []).append((s, v))
    return out


class PassLoop:
    """Active set, accumulator and verdict history of one render of `n` blocks.

    `quick`: the criterion's quick-image blocks [n, bh, bw, 3] (None if it needs none).
    `device`: where the accumulator's tensors live (the renderer's). The state
    (`state()` / `restore`) is what the live render checkpoints.
    """

    def __init__(self, criterion: Criterion, grid: tuple[int, int], block: tuple[int, int],
                 min_spp: int | None, quick: np.ndarray | None = None, device: Any = None) -> None:
        self.criterion, self.min_spp, self.quick, self.device = criterion, min_spp, quick, device
        criterion.start_render()               # a new render: nothing carried over from the last
        self.acc = BlockAccumulator(grid, block, device=device)
        n = self.acc.n_blocks
        self.active = np.ones(n, bool)
        self.stop_spp = np.zeros(n, np.int64)
        self.history = np.zeros((0, n), np.int8)
        self.history_spp = np.zeros(0, np.int64)
        self.history_block_spp = np.zeros((0, n), np.int64)   # every block's spp after each row
        self.rendered = np.zeros(0, np.int64)

    @property
    def active_ids(self) -> list[int]:
        return np.flatnonzero(self.active).tolist()

    def step(self, ids: Sequence[int], passes: Sequence[tuple[Any, int | Sequence[int]]]) -> np.ndarray:
        """Add `passes` to the blocks `ids` (each an (images [len(ids), bh, bw, 3], spp) pair:
        one spp for all or one per block; images on any device), then judge those of
        `ids` at or past min_spp, in one batched call.

        Each pass is one row of the verdict history (the checkpoint's invariant: a row per
        pass); the verdicts go in the step's last row. Returns that row, int8 [n]: +1
        converged now, -1 noisy, 0 not asked.
        """
        idx = np.asarray(ids, np.int64).reshape(-1)
        if not idx.size:
            raise ValueError("a step renders at least one block")
        if not passes:
            raise ValueError("a step adds at least one pass")
        if not self.active[idx].all():
            raise ValueError(f"blocks {idx[~self.active[idx]].tolist()} are stopped: they get no samples")
        rows_spp = []                     # each pass is a history row; only the last one is judged
        for images, pass_spp in passes:
            self.acc.add_batch(idx, images, pass_spp)
            rows_spp.append(self.acc.spp_all())
        spp = self.acc.spp_all()[idx]
        asked = idx if self.min_spp is None else idx[spp >= self.min_spp]
        row = np.zeros(len(self.active), np.int8)
        if asked.size:
            verdict = np.asarray(self.criterion.decide(asked.tolist(), self._batch(asked)))
            row[asked] = np.where(verdict > 0, CONVERGED, NOISY)
        stopped = row > 0
        self.active[stopped] = False
        self.stop_spp[stopped] = self.acc.spp_all()[stopped]
        rows = np.zeros((len(passes), len(self.active)), np.int8)
        rows[-1] = row
        self.history = np.vstack([self.history, rows])
        self.history_spp = np.append(self.history_spp, [int(r[idx].max()) for r in rows_spp])
        self.history_block_spp = np.vstack([self.history_block_spp, np.stack(rows_spp)])
        self.rendered = np.append(self.rendered, [len(idx)] * len(passes))
        return row

    @property
    def events(self) -> dict[int, list[tuple[int, int]]]:
        """Each decided block's own [(spp, verdict)], in order (`block_events`)."""
        return block_events(self.history, self.history_block_spp)

    def judge(self, ids: Sequence[int]) -> np.ndarray:
        """The criterion's verdicts on blocks as they stand, changing nothing here: refreshes
        `criterion.ratios` (a resumed budget render has none from before)."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        return self.criterion.decide(idx.tolist(), self._batch(idx))

    def _batch(self, idx: np.ndarray) -> BlockBatch:
        return BlockBatch.from_accumulator(self.acc, idx, self.quick)

    # -- checkpointing ---------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return {"acc": self.acc.state(), "active": self.active, "stop_spp": self.stop_spp,
                "history": self.history, "history_spp": self.history_spp,
                "history_block_spp": self.history_block_spp, "rendered": self.rendered}

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
