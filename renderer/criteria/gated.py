"""The learned model at tile grain: its block verdict gates the block's tiles, whose own
flip verdicts still apply inside it (DESIGN "Decision grain")."""
from __future__ import annotations

from typing import Any

import numpy as np

from learning.stoprule import CONVERGED, NOISY

from .batch import UnitBatch
from .contract import Criterion, Tally


class GatedCriterion(Criterion):
    """A tile stops when the model calls its whole block converged (the unit it was trained on)
    *and* flip calls the tile converged: the model cannot tell a block's clean tiles from its noisy
    one, and flip alone stops a tile on its own noisy estimate. The block is put together from its
    tiles as they stand; the ratio is the larger of the two. The model's `from_spec` builds it."""

    name = "model"
    needs_halves = True

    def __init__(self, gate: Criterion, tiles: Criterion) -> None:
        self.gate, self.tiles = gate, tiles
        self.needs_quick, self.quick_kind = gate.needs_quick, gate.quick_kind

    def describe(self) -> dict[str, Any]:
        return {**self.gate.describe(), "tiles": self.tiles.describe()}

    def prepare(self, quick: np.ndarray) -> tuple[np.ndarray, Tally]:
        return self.gate.prepare(quick)

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, ...]:
        verdict, ratio, evidence = self.tiles.assess(ids, batch, tally)     # the tiles' history is flip's
        whole, block_ids, row = batch.whole_blocks()
        gate, gate_ratio, *_ = self.gate.assess(block_ids.tolist(), whole, tally)
        both = (np.asarray(verdict) > 0) & (np.asarray(gate)[row] > 0)
        tally.add("gated_tiles", int(((np.asarray(verdict) > 0) & ~both).sum()))
        return (np.where(both, CONVERGED, NOISY).astype(np.int8), np.fmax(ratio, np.asarray(gate_ratio)[row]),
                evidence)
