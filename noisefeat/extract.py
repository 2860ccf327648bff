"""numpy-facing feature extraction: linear RGB blocks -> display -> L* -> 26 features."""
from __future__ import annotations

import logging
import os
from functools import lru_cache

import numpy as np
import torch

from .base import MIN_SIZE, FeatureBase
from .display import check_exposure, lightness, nonfinite_pixels

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def default_base() -> FeatureBase:
    """The package's feature base, built once per process.

    NOISESTOP_FEATURE_WEIGHTS (a path, 'smoothing' or 'pretrained') selects other weights,
    e.g. for the feature-base ablation.
    """
    return FeatureBase(os.environ.get("NOISESTOP_FEATURE_WEIGHTS") or None).eval()


def _as_blocks(blocks: np.ndarray | torch.Tensor) -> torch.Tensor:
    t = torch.as_tensor(blocks)
    if t.ndim != 4 or t.shape[-1] != 3:
        raise ValueError(f"expected linear RGB blocks [N, H, W, 3], got shape {tuple(t.shape)}")
    if not t.is_floating_point():
        raise ValueError(f"expected floating-point linear RGB, got dtype {t.dtype}")
    if t.shape[0] and (t.shape[1] < MIN_SIZE or t.shape[2] < MIN_SIZE):
        raise ValueError(f"blocks must be at least {MIN_SIZE}x{MIN_SIZE} pixels, got "
                         f"{t.shape[1]}x{t.shape[2]}")
    return t


def extract_features(blocks: np.ndarray | torch.Tensor, *, exposure: float = 0.0,
                     base: FeatureBase | None = None,
                     return_nonfinite: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Linear RGB [N, H, W, 3] -> float32 [N, 26] (see FeatureBase for the order).

    The model input is extract_features(quick) - extract_features(current).
    Non-finite pixels follow the display rule (NaN/-Inf -> black, +Inf -> white); they are
    counted per block, logged, and returned when `return_nonfinite` is set.
    """
    t = _as_blocks(blocks)
    exposure = check_exposure(exposure)
    base = base or default_base()
    bad = nonfinite_pixels(t).numpy().astype(np.int64) if t.shape[0] else np.zeros(0, np.int64)
    if bad.any():
        log.warning("%d non-finite pixels in %d of %d blocks (NaN/-Inf read as black, +Inf as white)",
                    int(bad.sum()), int((bad > 0).sum()), len(bad))
    with torch.inference_mode():
        feats = base(lightness(t, exposure)[:, None]).numpy() if t.shape[0] else \
            np.zeros((0, 26), np.float32)
    return (feats, bad) if return_nonfinite else feats
