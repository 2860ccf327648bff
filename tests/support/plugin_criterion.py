"""A criterion declared in one file, outside the package: importing this module is
all it takes for every door to offer it (`renderer.render`, ``noisestop render`` and the
``noisestop`` Mitsuba plugin; tests/renderer/test_criterion_in_one_file.py).

``halves_gap``: a unit is converged when the mean gap between its two half buffers, relative
to its brightness, is at most `threshold` (its own default and range, declared below).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from learning.stoprule import CONVERGED, NOISY
from renderer.criteria import TILE, UnitBatch, Criterion, Setting, Tally, declare
from renderer.spec import RenderSpec

#: the threshold when none is given, and the largest it takes (the row's is 1000)
GAP_DEFAULT, GAP_HIGH = 0.03, 10.0


@declare
class HalvesGapCriterion(Criterion):
    """Converged when mean |A - B| / (mean (A + B) / 2 + 0.01) <= threshold (A, B: the half
    buffers); at once when flat; noisy while one half is empty."""

    name = "halves_gap"
    summary = "a test's: the relative gap between the half buffers"
    grain = TILE
    settings = {"threshold": Setting(GAP_DEFAULT, high=GAP_HIGH, doc="the largest relative gap")}
    needs_halves = True
    noise_ratio = True

    def __init__(self, threshold: float | None = None, exposure: float | None = None) -> None:
        given = self.checked(threshold=threshold, exposure=exposure)
        self.threshold, self.exposure = given["threshold"], given["exposure"]

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> HalvesGapCriterion:
        return cls(spec.threshold, exposure=spec.exposure)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "threshold": self.threshold}

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        import torch

        flat = self._flat(batch, self.exposure, tally)
        ask = self._ready(batch, flat)
        ratio = np.where(flat, 0.0, np.nan)
        if ask.size:
            a, b = batch.halves      # type: ignore[misc]
            sel = torch.from_numpy(ask).to(a.device)
            a, b = a[sel].flatten(1), b[sel].flatten(1)
            gap = (a - b).abs().mean(dim=1) / ((a + b).mean(dim=1) / 2 + 0.01)
            ratio[ask] = gap.cpu().numpy() / self.threshold
        with np.errstate(invalid="ignore"):
            return np.where(flat | (ratio <= 1), CONVERGED, NOISY).astype(np.int8), ratio
