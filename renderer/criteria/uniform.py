"""The uniform baseline: never converged, every block rendered to max spp."""
from __future__ import annotations

import numpy as np

from learning.stoprule import NOISY

from .contract import BlockBatch, Criterion, Tally


class UniformCriterion(Criterion):
    """Never converged: every block is rendered to max spp (the uniform baseline)."""

    name = "uniform"

    def _decide(self, ids: list[int], batch: BlockBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        return np.full(len(ids), NOISY, np.int8), np.full(len(ids), np.nan)
