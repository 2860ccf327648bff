"""numpy-facing feature extraction: linear RGB blocks -> display -> L* -> 26 features
(through the fused path of noisefeat.fused)."""
from __future__ import annotations

import logging
import os
from functools import lru_cache

import numpy as np
import torch

from . import fused
from .base import MIN_SIZE, FeatureBase
from .display import check_exposure
from .fused import RGBStats

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def default_base() -> FeatureBase:
    """The package's feature base, built once per process.

    NOISESTOP_FEATURE_WEIGHTS (a path, 'smoothing' or 'pretrained') selects other weights,
    e.g. for the feature-base ablation.
    """
    with torch.inference_mode(False):   # normal tensors even if first asked for under inference mode
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
    """The 26 noise features of each block: display transform, L*, then the feature base.

    The paper's model input is ``extract_features(quick) - extract_features(current)``.
    Computed by the fused path (`noisefeat.fused`): one chunked pass from RGB to features,
    equal to ``FeatureBase()(lightness(blocks))`` within float32 rounding.

    Parameters
    ----------
    blocks : numpy.ndarray or torch.Tensor
        Linear (scene-referred) RGB blocks [N, H, W, 3], H and W at least 8; any size.
    exposure : float, default 0.0
        Display exposure in stops: the blocks are multiplied by 2**exposure before the
        display transform (DESIGN "Display transform").
    base : FeatureBase, optional
        The feature base to use; default: the package's (`default_base()`).
    return_nonfinite : bool, default False
        Also return the count of non-finite pixels per block.

    Returns
    -------
    numpy.ndarray or tuple of numpy.ndarray
        float32 [N, 26] features in `FEATURE_NAMES` order (mean and std of the 13 noise
        maps); with `return_nonfinite`, (features, int64 [N] non-finite pixel counts).
        Non-finite pixels follow the display rule (NaN and -Inf read as black, +Inf as
        white), so features are always finite.

    Raises
    ------
    ValueError
        On a wrong shape, a block under 8x8, or an exposure out of range.
    """
    feats, stats = analyse_blocks(blocks, exposure=exposure, base=base)
    return (feats, stats.nonfinite) if return_nonfinite else feats


def analyse_blocks(blocks: np.ndarray | torch.Tensor, *, exposure: float = 0.0,
                   base: FeatureBase | None = None, display_range: bool = False) -> tuple[np.ndarray, RGBStats]:
    """(float32 [N, 26] features, RGBStats) of linear RGB blocks [N, H, W, 3]: the features,
    the non-finite pixel count of each block and, if `display_range`, its display range
    (what the flat-block test reads), all from the one fused pass."""
    return analyse_many([blocks], exposure=exposure, base=base, display_range=[display_range])[0]


def analyse_many(batches: list[np.ndarray | torch.Tensor], *, exposure: float = 0.0,
                 base: FeatureBase | None = None,
                 display_range: list[bool] | None = None) -> list[tuple[np.ndarray, RGBStats]]:
    """`analyse_blocks` of several batches of blocks of one size in one fused call (a
    request's blocks and quick images: one spectral pass for both)."""
    ts = [_as_blocks(b) for b in batches]
    exposure = check_exposure(exposure)
    base = base or default_base()
    with torch.inference_mode():
        results = fused.features_of(ts, exposure, base, display_range)
    for _, stats in results:
        _log_nonfinite(stats.nonfinite)
    return [(f.numpy(), stats) for f, stats in results]


def _log_nonfinite(bad: np.ndarray) -> None:
    if bad.any():
        log.warning("%d non-finite pixels in %d of %d blocks (NaN/-Inf read as black, +Inf as white)",
                    int(bad.sum()), int((bad > 0).sum()), len(bad))
