"""One pass of a progressive render, the same for the live render and the simulation.

Both the live loop (`renderer.adaptive`, passes from Mitsuba) and the simulation on stored
stacks (`renderer.simulate`, passes recovered from the levels) do, per pass: add the new
samples of the still-active blocks to the `BlockAccumulator` (exact means, even/odd half
buffers), and once spp >= min_spp ask the criterion about the active blocks only through
the stop rule's `decide_active`; a block it calls converged leaves the active set for
good. `PassLoop` is that step and its state; each caller brings its own source of passes.
Because both judge the very same `BlockView`s, the two routes cannot drift apart.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from learning.data.accumulator import BlockAccumulator
from learning.stoprule import decide_active

from .criteria import BlockView, Criterion


class PassLoop:
    """Active set, accumulator and verdict history of one render of `n` blocks.

    `quick`: the criterion's quick-image blocks [n, bh, bw, 3] (None if it needs none).
    The state (`state()` / `from_state`) is what the live render checkpoints.
    """

    def __init__(self, criterion: Criterion, grid: tuple[int, int], block: tuple[int, int],
                 min_spp: int | None, quick: np.ndarray | None = None) -> None:
        self.criterion, self.min_spp, self.quick = criterion, min_spp, quick
        self.acc = BlockAccumulator(grid, block)
        n = self.acc.n_blocks
        self.active = np.ones(n, bool)
        self.stop_spp = np.zeros(n, np.int64)
        self.history = np.zeros((0, n), np.int8)
        self.history_spp = np.zeros(0, np.int64)
        self.rendered = np.zeros(0, np.int64)
        self.events: dict[int, list[tuple[int, int]]] = {}    # block -> its own [(spp, verdict)]

    @property
    def active_ids(self) -> list[int]:
        return np.flatnonzero(self.active).tolist()

    def add_pass(self, ids: Sequence[int], images: np.ndarray, pass_spp: int) -> np.ndarray:
        """Accumulate one pass of the blocks `ids` (the active ones), then judge them.

        Returns the pass's verdict row, int8 [n]: +1 converged now, -1 noisy, 0 not asked.
        """
        ids = [int(b) for b in ids]
        self.acc.add_many(ids, images, int(pass_spp))
        spp = self.acc.spp(ids[0])
        row = decide_active(self.active, spp, self.min_spp, self._ask)
        self.stop_spp[row > 0] = spp
        for b in np.flatnonzero(row).tolist():
            self.events.setdefault(b, []).append((int(spp), int(row[b])))
        self.history = np.vstack([self.history, row[None]])
        self.history_spp = np.append(self.history_spp, spp)
        self.rendered = np.append(self.rendered, len(ids))
        return row

    def add_passes(self, ids: Sequence[int], images: np.ndarray, pass_spp: Sequence[int]) -> np.ndarray:
        """Accumulate one pass of each block `ids` with its own size, then judge those at or
        past min_spp: the step of a budget render, whose blocks hold different pass counts.

        With every active block listed at the same pass count this is `add_pass` (same
        sums, same blocks asked, same rule); the history row is stamped with the largest
        spp of the round, and `events` keeps each block's own (spp, verdict) list.
        Returns the round's verdict row, int8 [n].
        """
        ids = [int(b) for b in ids]
        if len(ids) != len(images) or len(ids) != len(pass_spp):
            raise ValueError(f"{len(ids)} block ids, {len(images)} images and {len(pass_spp)} pass sizes")
        if not ids:
            raise ValueError("a round renders at least one block")
        if not self.active[ids].all():
            raise ValueError(f"blocks {[b for b in ids if not self.active[b]]} are stopped: they get no samples")
        for b, img, s in zip(ids, images, pass_spp):
            self.acc.add(b, img, int(s))
        spp = np.array([self.acc.spp(b) for b in ids], np.int64)
        ready = np.zeros(len(self.active), bool)
        ready[[b for b, s in zip(ids, spp) if self.min_spp is None or s >= self.min_spp]] = True
        row = decide_active(ready, 0, None, self._ask)      # the rule on the blocks past min spp
        stopped = row > 0
        self.active[stopped] = False
        for b, s in zip(ids, spp):
            if row[b] > 0:
                self.stop_spp[b] = s
            if row[b] != 0:
                self.events.setdefault(b, []).append((int(s), int(row[b])))
        self.history = np.vstack([self.history, row[None]])
        self.history_spp = np.append(self.history_spp, int(spp.max()))
        self.rendered = np.append(self.rendered, len(ids))
        return row

    def judge(self, ids: Sequence[int]) -> np.ndarray:
        """The criterion's verdicts on blocks as they stand, changing nothing here: refreshes
        `criterion.ratios` (a resumed budget render has none from before)."""
        return self._ask([int(b) for b in ids])

    def _ask(self, ids: list[int]) -> np.ndarray:
        acc, halves = self.acc, self.criterion.needs_halves   # two extra divisions per block: only when used
        return self.criterion.decide(ids, [BlockView(
            mean=acc.mean(b), spp=acc.spp(b), nonfinite=acc.nonfinite(b),
            halves=acc.half_buffer(b) if halves else None,
            half_spp=acc.half_spp(b) if halves else None,
            quick=None if self.quick is None else self.quick[b]) for b in ids])

    # -- checkpointing ---------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        return {"acc": self.acc.state(), "active": self.active, "stop_spp": self.stop_spp,
                "history": self.history, "history_spp": self.history_spp, "rendered": self.rendered,
                "events": self.events}

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a validated checkpoint's state (`renderer.checkpoint`)."""
        acc = state["acc"]
        self.acc = acc if isinstance(acc, BlockAccumulator) else BlockAccumulator.from_state(acc)
        self.active = np.asarray(state["active"], bool).copy()
        self.stop_spp = np.asarray(state["stop_spp"], np.int64).copy()
        self.history = np.asarray(state["history"], np.int8).reshape(-1, len(self.active))
        self.history_spp = np.asarray(state["history_spp"], np.int64)
        self.rendered = np.asarray(state["rendered"], np.int64)
        # a checkpoint is only written while every active block is at the same pass
        self.events = {b: [(int(self.history_spp[i]), int(self.history[i, b]))
                           for i in np.flatnonzero(self.history[:, b] != 0)] for b in range(len(self.active))}
        self.events = {b: e for b, e in self.events.items() if e}
