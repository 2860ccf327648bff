"""How visible the difference between two images is, at a fraction of FLIP's cost.

NVIDIA FLIP (the virtual observer's metric) spends most of its time on large 2D filters.
Its colour pipeline, for two images that differ only by noise (the half buffers A and B of
a block), reduces to: a CIELab difference whose chroma is scaled by lightness (the Hunt
effect), each channel low-passed by FLIP's contrast-sensitivity Gaussians at the viewing
distance (67 pixels per degree), the HyAB distance |dL| + |(da, db)|, raised to 0.7 and
compressed into [0, 1]; the error is averaged over the block. This module computes that
with separable Gaussian filters on the Lab difference (FLIP filters in its opponent
space first, and adds an edge/point pipeline; both are left out), batched over blocks.
On the training dataset its log correlates 0.995 with log FLIP(A, B) (docs/guide/training.md,
"Model inputs"), while the FeatureBase's std features, whose pooling is quadratic and blind to
chroma, explain about three quarters of its variance.

`pooled_colour_error(a, b)` is the `p` part of the `halves` model input
(`learning.inputs.noise_input`). Non-finite pixels follow the display rule.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
from torch.nn import functional as F

from .display import lab, lab_f, lab_from_f, relative_xyz

#: FLIP's contrast-sensitivity filters (Andersson et al. 2020, Table 1): per channel, the
#: Gaussians a * sqrt(pi / b) * exp(-pi^2 x^2 / b), x in degrees: (a, b) pairs
CSF = {"L": ((1.0, 0.0047),), "a": ((1.0, 0.0053),), "b": ((34.1, 0.04), (13.5, 0.025))}
QC, PC, PT = 0.7, 0.4, 0.95          # FLIP's HyAB exponent and compression knee
DEFAULT_PPD = 67.0


@lru_cache(maxsize=16)
def csf_kernel(channel: str, ppd: float) -> torch.Tensor:
    """The channel's normalised 1D CSF kernel at `ppd` pixels per degree (a separable
    Gaussian mixture: each Gaussian of a 2D mixture is the outer product of its 1D one)."""
    widest = max(math.sqrt(b / (2 * math.pi ** 2)) for _, b in CSF[channel]) * ppd
    r = max(1, math.ceil(3 * widest))
    x = np.arange(-r, r + 1) / ppd
    k = sum(a * math.sqrt(math.pi / b) * np.exp(-math.pi ** 2 * x ** 2 / b) for a, b in CSF[channel])
    return torch.tensor(k / k.sum(), dtype=torch.float32)


#: sides up to this many pixels are filtered by a banded matrix product (one BLAS call per
#: axis, much faster than a single-channel conv2d on a CPU); wider ones by conv2d
MATRIX_SIDE = 512


@lru_cache(maxsize=32)
def _filter_matrix(channel: str, ppd: float, n: int) -> torch.Tensor:
    """[n, n] M with (x @ M)[j] = sum_t k[t] x[clamp(j + t - r)]: the 1D filter along an
    axis of n pixels, edges replicated, as one matrix."""
    k = csf_kernel(channel, ppd).double()
    r = len(k) // 2
    m = torch.zeros(n, n, dtype=torch.float64)
    cols = torch.arange(n)
    for t, w in enumerate(k):
        m.index_put_((torch.clamp(cols + t - r, 0, n - 1), cols), w, accumulate=True)
    return m.float()


def _blur(x: torch.Tensor, channel: str, ppd: float) -> torch.Tensor:
    """[N, H, W] separably filtered by the channel's CSF kernel, edges replicated (FLIP
    clamps at borders too)."""
    h, w = x.shape[-2:]
    if max(h, w) <= MATRIX_SIDE:
        return _filter_matrix(channel, ppd, h).T @ (x @ _filter_matrix(channel, ppd, w))
    k = csf_kernel(channel, ppd)
    r = len(k) // 2
    y = F.conv2d(F.pad(x[:, None], (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))[:, 0]


def _hunt(lab_img: torch.Tensor) -> torch.Tensor:
    return torch.stack([lab_img[..., 0], 0.01 * lab_img[..., 0] * lab_img[..., 1],
                        0.01 * lab_img[..., 0] * lab_img[..., 2]], dim=-1)


def hunt_difference(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray,
                    exposure: float = 0.0) -> torch.Tensor:
    """[N, H, W, 3]: Hunt-adjusted Lab of a minus that of b, to first order around their
    mean (one cube root per pixel instead of two: the two halves differ only by noise, and
    where they differ a lot the block is plainly noisy whatever the exact figure)."""
    xa, xb = relative_xyz(a, exposure), relative_xyz(b, exposure)
    if xa.shape != xb.shape or xa.ndim != 4:
        raise ValueError(f"expected two linear RGB block arrays [N, H, W, 3] of one shape, got "
                         f"{tuple(xa.shape)} and {tuple(xb.shape)}")
    f, slope = lab_f((xa + xb) * 0.5)
    mean = lab_from_f(f)
    df = slope * (xa - xb)
    dl = 116.0 * df[..., 1]
    dab = torch.stack([500.0 * (df[..., 0] - df[..., 1]), 200.0 * (df[..., 1] - df[..., 2])], dim=-1)
    # d(0.01 L a) = 0.01 (L da + a dL), likewise for b
    hunt = 0.01 * (mean[..., :1] * dab + mean[..., 1:] * dl[..., None])
    return torch.cat([dl[..., None], hunt], dim=-1)


@lru_cache(maxsize=1)
def _cmax() -> float:
    """FLIP's largest colour error: HyAB between Hunt-adjusted green and blue, ^ QC."""
    g, b = _hunt(lab(torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])))
    return float(((g[0] - b[0]).abs() + torch.linalg.vector_norm(g[1:] - b[1:])) ** QC)


def pooled_colour_error(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray, exposure: float = 0.0,
                        ppd: float = DEFAULT_PPD) -> torch.Tensor:
    """float32 [N]: per block, the mean FLIP-style colour error between linear RGB blocks
    a and b, [N, H, W, 3] each (module docstring). 0 for identical blocks; in [0, 1]."""
    d = hunt_difference(a, b, exposure)
    if d.shape[0] == 0:
        return torch.zeros(0)
    dl, da, db = (_blur(d[..., i], c, float(ppd)) for i, c in enumerate("Lab"))
    e = (dl.abs() + torch.sqrt(da * da + db * db)).pow(QC)
    cmax = _cmax()
    knee = PC * cmax
    e = torch.where(e < knee, e * (PT / knee), PT + (e - knee) / (cmax - knee) * (1.0 - PT))
    return e.clamp_(0.0, 1.0).mean(dim=(1, 2))
