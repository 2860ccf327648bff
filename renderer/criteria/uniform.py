"""The uniform baseline: never converged, every block rendered to max spp."""
from __future__ import annotations

import numpy as np

from learning.stoprule import NOISY

from .batch import UnitBatch
from .contract import Criterion, Tally
from .registry import declare


@declare
class UniformCriterion(Criterion):
    """Never converged (the uniform baseline)."""

    name = "uniform"
    summary = "never: max_spp everywhere, the baseline"
    stops = False

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        return np.full(len(ids), NOISY, np.int8), np.full(len(ids), np.nan)
