"""Blender Cycles' adaptive-sampling test as a criterion: every pixel of a block must pass."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.stoprule import CONVERGED, NOISY

from .batch import UnitBatch
from .contract import Criterion, Tally
from .registry import TILE, Setting, declare

if TYPE_CHECKING:
    import torch

    from ..spec import RenderSpec


@declare
class VarianceCriterion(Criterion):
    """Blender Cycles' adaptive-sampling test, applied to every pixel of a block: a pixel passes
    when error < scale * threshold (`pixel_error`: Cycles' ``film_adaptive_sampling_convergence_check``,
    intern/cycles/kernel/film/adaptive_sampling.h, I the mean of all samples, A of the even passes;
    the kernel compares with the threshold itself, so `scale` defaults to 1). A block is converged
    when at least `quantile` of its pixels pass (Octane's "group pixels"); it is noisy until both
    halves hold a pass (with one, A equals I).
    """

    name = "variance"
    summary = "Cycles' half-buffer rule: every pixel's error under the threshold"
    grain = TILE
    settings = {"threshold": Setting(0.01, doc="Cycles' noise threshold"),
                "quantile": Setting()}
    needs_halves = True
    noise_ratio = True

    def __init__(self, threshold: float | None = None, quantile: float | None = None, scale: float = 1.0,
                 flat_shortcut: bool = True, exposure: float | None = None) -> None:
        """Render settings None: their declared defaults; `flat_shortcut`: a flat unit converges at once."""
        given = self.checked(threshold=threshold, quantile=quantile, exposure=exposure)
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        self.threshold, self.quantile, self.scale = given["threshold"], given["quantile"], float(scale)
        self.flat_shortcut, self.exposure = bool(flat_shortcut), given["exposure"]

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> VarianceCriterion:
        return cls(spec.threshold, quantile=spec.quantile, exposure=spec.exposure)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "threshold": self.threshold, "quantile": self.quantile,
                "scale": self.scale, "flat_shortcut": self.flat_shortcut}

    @staticmethod
    def _finite(x: Any) -> torch.Tensor:
        """Non-finite values as the display rule maps them (NaN, -Inf -> 0, +Inf -> 1): no error is NaN."""
        import torch

        return torch.nan_to_num(torch.as_tensor(x).to(torch.float64), nan=0.0, posinf=1.0, neginf=0.0)

    def pixel_error(self, mean: Any, half_a: Any) -> torch.Tensor:
        """Cycles' per-pixel error [..., bh, bw] (finite, >= 0), where the inputs live."""
        import torch

        i, a = self._finite(mean), self._finite(half_a)
        diff = (i - a).abs().sum(dim=-1)
        intensity = i.sum(dim=-1).clamp_min(0.0)
        norm = torch.where(intensity < 1.0, intensity.sqrt(), intensity)
        return diff / (1e-4 + norm)

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        flat = self._flat(batch, self.exposure, tally) if self.flat_shortcut else np.zeros(len(ids), bool)
        out = np.full(len(ids), NOISY, np.int8)
        ratio = np.full(len(ids), np.nan)
        ask = self._ready(batch, flat)        # one pass only: no noise estimate yet (A equals the mean)
        if ask.size:
            import torch

            sel = torch.from_numpy(ask).to(batch.mean.device)
            err = self.pixel_error(batch.mean[sel], batch.halves[0][sel]).flatten(1)   # type: ignore[index]
            limit = self.scale * self.threshold
            passed = (err < limit).to(torch.float64).mean(dim=1)
            q = torch.quantile(err, self.quantile, dim=1) if err.shape[1] <= 1 << 24 else \
                torch.from_numpy(np.quantile(err.cpu().numpy(), self.quantile, axis=1))
            out[ask] = np.where(passed.cpu().numpy() >= self.quantile, CONVERGED, NOISY)
            ratio[ask] = q.cpu().numpy() / limit
        out[flat] = CONVERGED
        ratio[flat] = 0.0
        return out, ratio
