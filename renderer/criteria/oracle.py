"""The oracle: a labelled stack's true thresholds, the best stops any criterion can make."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.stoprule import CONVERGED, NOISY

from .batch import UnitBatch
from .contract import Criterion, Tally
from .registry import BLOCK_ONLY, declare

if TYPE_CHECKING:
    from ..spec import RenderSpec


@declare
class OracleCriterion(Criterion):
    """Block b is converged iff spp >= T_b (None, censored: never); the ratio is T_b / spp.
    The best any criterion can do on a labelled stack: the yardstick of `spp_ratio_vs_oracle`."""

    name = "oracle"
    summary = "a labelled reference stack's true thresholds"
    grain = BLOCK_ONLY          # its thresholds are per block
    needs_thresholds = True

    def __init__(self, thresholds: Sequence[int | None]) -> None:
        if thresholds is None or isinstance(thresholds, (str, bytes)):
            raise ValueError(f"thresholds must be a sequence of positive integers or None, got {thresholds!r}")
        th = list(thresholds)
        for i, t in enumerate(th):
            if t is not None and (isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 1):
                raise ValueError(f"threshold of block {i} must be a positive integer or None, got {t!r}")
        self.thresholds: list[int | None] = [None if t is None else int(t) for t in th]

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> OracleCriterion:
        return cls(thresholds)       # type: ignore[arg-type]   # the render spec saw to them being known

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "thresholds": self.thresholds}

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        idx = np.asarray(ids, np.int64)
        bad = idx[(idx < 0) | (idx >= len(self.thresholds))]
        if bad.size:
            raise ValueError(f"block id {int(bad[0])} out of range: the oracle knows {len(self.thresholds)} blocks")
        th = np.array([np.inf if t is None else t for t in self.thresholds], np.float64)[idx]
        return np.where(batch.spp >= th, CONVERGED, NOISY).astype(np.int8), th / np.maximum(batch.spp, 1)
