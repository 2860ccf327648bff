"""Sparse outliers ("dots"): the observer's version-3 term and the criteria's guard.

Why: FLIP at 67 pixels per degree blurs single pixels away, and the observer pools it by
16x16 tile means, so a block holding a few dozen light dots on black scored 0.013-0.015
(under tau 0.02) while a person at 1:1 sees every dot (Cycles' own test is per pixel for
the same reason). The term counts pixels instead of averaging them:

* a pixel's display error is the largest per-channel difference of the two display images
  (DESIGN's display transform, values in [0, 1]);
* a block may hold one outlier pixel per `DOT_DENSITY` pixels (16 in a 64x64 block), an
  outlier being a pixel whose display error exceeds `DOT_LEVEL` * tau (0.03 at tau 0.02);
* so the block's term is its r-th largest display error / DOT_LEVEL, r = allowed + 1
  (`dot_rank`), and the block passes iff that is <= tau: the same "e <= tau" as FLIP,
  so one number per block (the larger of the two terms) carries every rule and relabelling
  at another tau needs no new pass over the pixels.

The level was chosen by measurement on `make run`'s near-black blocks (BENCHMARKS.md
"Observer version 3"): at 2.5 tau (0.05, the reports' yardstick) a stopped block kept 11-14
such pixels and, visible at 3x, a hundred fainter ones (0.03-0.05) that uniform's same
blocks did not show; at 1.5 tau they stop with 0-1 pixels over 0.05. Reports count pixels
over that yardstick, `REPORT_LEVEL` * tau (0.05 = 13 of 255 levels at tau 0.02).

The criteria see the dots through their half buffers A and B (`halves_dots`). The image
shown is (up to one pass) their mean M; a pixel's error against the truth is estimated by
the larger of |d(M) - d(A)| and |d(M) - d(B)|: with Gaussian noise either has the spread of
M's own error (M - A = (B - A) / 2), and a firefly that landed in A alone leaves B at the
truth, so |d(M) - d(B)| is the dot's own display error. Both scale with `DOT_LEVEL` * tau.
"""
from __future__ import annotations

import numpy as np
import torch

from .display import display

#: an outlier's display error, in units of tau (0.03, about 8 of 255 levels, at tau 0.02)
DOT_LEVEL = 1.5
#: the yardstick reports count dots by (display error > 0.05 at tau 0.02)
REPORT_LEVEL = 2.5
#: one outlier pixel is tolerated per this many pixels (16 in a 64x64 block)
DOT_DENSITY = 256
#: the settings a labeler record and a calibration name (another setting is another observer)
OBSERVER_DOTS = {"dot_level": DOT_LEVEL, "dot_density": DOT_DENSITY}


def dot_rank(h: int, w: int) -> int:
    """r: a block of h x w pixels fails when its r-th largest display error is an outlier
    (one allowed per DOT_DENSITY pixels, at least one)."""
    return max(1, (int(h) * int(w)) // DOT_DENSITY) + 1


def rank_pool(maps: torch.Tensor) -> torch.Tensor:
    """float64 [N]: per map of [N, h, w], the r-th largest value (`dot_rank`) / DOT_LEVEL,
    so that `<= tau` is the rule; 0 where a map has fewer than r pixels; NaN where a map
    holds a NaN (never converged, as every pooling)."""
    if maps.ndim != 3:
        raise ValueError(f"maps must be [N, h, w], got shape {tuple(maps.shape)}")
    n, h, w = maps.shape
    r = dot_rank(h, w)
    out = torch.zeros(n, dtype=torch.float64, device=maps.device)
    if n == 0 or h * w < r:
        return out
    flat = maps.reshape(n, h * w)
    out = torch.topk(flat, r, dim=1).values[:, r - 1].to(torch.float64) / DOT_LEVEL
    return torch.where(torch.isnan(flat).any(dim=1), torch.full_like(out, float("nan")), out)


def display_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[..., h, w]: per pixel, the largest per-channel |a - b| of two display images [..., 3]."""
    return (a - b).abs().amax(dim=-1)


def reference_dots(reference: np.ndarray | torch.Tensor, tests: np.ndarray | torch.Tensor,
                   exposure: float = 0.0) -> np.ndarray:
    """float64 [N]: the observer's dot term of linear RGB images [N, h, w, 3] against their
    reference [N, h, w, 3] (or one [h, w, 3] for all)."""
    ref = display(reference, exposure)
    test = display(tests, exposure)
    if test.ndim != 4 or test.shape[-1] != 3 or ref.shape[-3:] != test.shape[-3:]:
        raise ValueError(f"expected linear RGB images [N, h, w, 3] and a reference of their size, "
                         f"got {tuple(test.shape)} and {tuple(ref.shape)}")
    return rank_pool(display_error(test, ref)).cpu().numpy()


def halves_dots(even: torch.Tensor, odd: torch.Tensor, exposure: float = 0.0) -> torch.Tensor:
    """float64 [N], where the tensors are: the criteria's dot term of blocks [N, h, w, 3]
    from their half buffers A, B (module docstring), comparable to tau. M = (A + B) / 2 in
    float32, from the halves alone: the live loop, the stored stacks and the verdict server
    (which gets only A and B, as float32) then judge the very same numbers."""
    a, b = even.to(torch.float32), odd.to(torch.float32)
    m = display((a + b) * 0.5, exposure)
    err = torch.maximum(display_error(m, display(a, exposure)), display_error(m, display(b, exposure)))
    return rank_pool(err)


def count_outliers(image: np.ndarray, reference: np.ndarray, tau: float, exposure: float = 0.0,
                   level: float = REPORT_LEVEL) -> int:
    """How many pixels of a linear RGB image [h, w, 3] differ from the reference by more
    than `level` * tau on the display (REPORT_LEVEL: what `make run` and reports count)."""
    err = display_error(display(image, exposure), display(reference, exposure))
    return int((err > level * float(tau)).sum())
