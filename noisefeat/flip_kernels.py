"""FLIP's colour science and filter kernels (FLIP.h of NVlabs/flip; Andersson et al., HPG 2020).

Why a module of its own: these are the numbers FLIP defines (its RGB <-> XYZ matrices, D65
white, contrast-sensitivity Gaussians, edge and point detectors, CIELab's f, the largest
colour error); `noisefeat.flip_maps` computes the maps with them, and tests check them
against FLIP's own values apart from any map.

* colour: linear RGB -> YCxCz (FLIP's RGB->XYZ matrix and D65 white); each channel
  low-passed by its contrast-sensitivity filter (Y, Cx: one Gaussian; Cz: the sum of two,
  separated as FLIP separates them), all of radius ceil(3 sqrt(0.04 / (2 pi^2)) ppd)
  (10 pixels at 67 ppd);
* features: a Gaussian and its first and second derivatives (sigma 0.5 * 0.082 ppd,
  radius ceil(3 sigma): 9 pixels at 67 ppd, each lobe normalised as FLIP does).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from .perceptual import QC

#: FLIP's linear sRGB -> XYZ (its exact rational entries) and XYZ -> linear sRGB (D65)
RGB_TO_XYZ = ((10135552 / 24577794, 8788810 / 24577794, 4435075 / 24577794),
              (2613072 / 12288897, 8788810 / 12288897, 887015 / 12288897),
              (1425312 / 73733382, 8788810 / 73733382, 70074185 / 73733382))
XYZ_TO_RGB = ((3.241003275, -1.537398934, -0.498615861),
              (-0.969224334, 1.875930071, 0.041554224),
              (0.055639423, -0.204011202, 1.057148933))
ILLUMINANT = (0.950428545, 1.0, 1.088900371)
INV_ILLUMINANT = (1.052156925, 1.0, 0.918357670)
#: contrast-sensitivity Gaussians a * sqrt(pi / b) * exp(-pi^2 x^2 / b) per channel (Y, Cx,
#: Cz), x in degrees; Cz is the sum of two (FLIP's GaussianConstants a1, b1, a2, b2)
CSF_Y, CSF_CX, CSF_CZ = (1.0, 0.0047), (1.0, 0.0053), ((34.1, 0.04), (13.5, 0.025))
CSF_WIDEST_B = 0.04
GW = 0.082                           # feature detector width (degrees); its exponent is 1/2

_f32 = np.float32


def check_ppd(ppd: float) -> float:
    """FLIP's pixels per degree as a positive finite float, else ValueError."""
    try:
        p = float(ppd)
    except (TypeError, ValueError):
        raise ValueError(f"ppd must be a positive number, got {ppd!r}") from None
    if not math.isfinite(p) or p <= 0:
        raise ValueError(f"ppd must be a positive finite number, got {ppd!r}")
    return p


def spatial_radius(ppd: float) -> int:
    """FLIP's colour-filter radius in pixels (float32 arithmetic, as in FLIP)."""
    pi_sq = _f32(math.pi) * _f32(math.pi)
    return int(math.ceil(_f32(3.0) * np.sqrt(_f32(CSF_WIDEST_B) / (_f32(2.0) * pi_sq)) * _f32(ppd)))


def feature_sigma(ppd: float) -> float:
    """FLIP's edge/point detector's standard deviation in pixels (0.5 x 0.082 degrees)."""
    return float(_f32(0.5) * _f32(GW) * _f32(ppd))


@lru_cache(maxsize=16)
def colour_kernels(ppd: float) -> np.ndarray:
    """[4, 2r + 1] float64: FLIP's separated colour filters, rows Y, Cx, Cz1, Cz2.

    Y and Cx are normalised to sum 1; Cz1 and Cz2 are the square roots of the two Cz
    Gaussians, scaled together so that the 2D filter Cz1 x Cz1 + Cz2 x Cz2 sums to 1."""
    r = spatial_radius(ppd)
    x = (np.arange(-r, r + 1) / ppd) ** 2

    def gauss(a: float, b: float, root: bool = False) -> np.ndarray:
        amp = math.sqrt(a * math.sqrt(math.pi / b)) if root else a * math.sqrt(math.pi / b)
        return amp * np.exp(-math.pi ** 2 * x / b)

    y, cx = gauss(*CSF_Y), gauss(*CSF_CX)
    z1, z2 = (gauss(a, b, root=True) for a, b in CSF_CZ)
    norm = math.sqrt(z1.sum() ** 2 + z2.sum() ** 2)
    return np.stack([y / y.sum(), cx / cx.sum(), z1 / norm, z2 / norm])


@lru_cache(maxsize=16)
def feature_kernels(ppd: float) -> np.ndarray:
    """[3, 2r + 1] float64: FLIP's feature filters, rows Gaussian (sum 1), first and second
    derivative (positive lobes sum to 1, negative ones to -1)."""
    sd = feature_sigma(ppd)
    r = int(math.ceil(float(_f32(3.0) * _f32(sd))))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-x * x / (2 * sd * sd))
    dg, ddg = -x * g, (x * x / (sd * sd) - 1.0) * g

    def lobes(k: np.ndarray) -> np.ndarray:
        return np.where(k > 0, k / k[k > 0].sum(), k / -k[k < 0].sum())
    return np.stack([g / g.sum(), lobes(dg), lobes(ddg)])


def trimmed(kernel: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """`kernel` without the outer taps below `tol` x its peak: they cannot change a float32
    sum (FLIP's Y and Cx filters span 21 taps at 67 ppd, but their outer four and three on
    each side weigh under 1e-9 of the centre one), and a narrower filter costs less."""
    small = np.abs(kernel) < tol * np.abs(kernel).max()
    cut = 0
    while cut < len(kernel) // 2 and small[cut] and small[-1 - cut]:
        cut += 1
    return kernel[cut:len(kernel) - cut]


@lru_cache(maxsize=16)
def filter_bank(ppd: float) -> dict[str, np.ndarray]:
    """FLIP's 1D filters at `ppd` by name: the colour filters Y, Cx (trimmed), Cz1, Cz2 and
    the feature filters g, dg, ddg."""
    ck, fk = colour_kernels(ppd), feature_kernels(ppd)
    return {"Y": trimmed(ck[0]), "Cx": trimmed(ck[1]), "Cz1": ck[2], "Cz2": ck[3],
            "g": fk[0], "dg": fk[1], "ddg": fk[2]}


_LAB_EPS = (6.0 / 29.0) ** 3
_LAB_SLOPE = 1.0 / (3.0 * (6.0 / 29.0) ** 2)


def lab_f_inplace(t: torch.Tensor) -> torch.Tensor:
    """CIELab's f, in place: the cube root above (6/29)^3 and FLIP's line below, written
    without a branch as cbrt(m) + slope (t - m), m = max(t, (6/29)^3), and the cube root
    as exp(log(m) / 3) (torch's pow with a float exponent is ~3x slower)."""
    m = t.clamp_min(_LAB_EPS)
    return t.sub_(m).mul_(_LAB_SLOPE).add_(m.log_().mul_(1.0 / 3.0).exp_())


@lru_cache(maxsize=8)
def colour_matrices(device: torch.device = torch.device("cpu")) -> tuple[torch.Tensor, ...]:
    """float32 (to_opp, opp_bias, from_opp, rgb_bias, to_xyz): linear RGB -> Y, Cx, Cz;
    filtered Y, Cx, Cz -> linear RGB; linear RGB -> XYZ / white ([3, 3] and [3, 1])."""
    to_xyz = np.diag(INV_ILLUMINANT) @ np.asarray(RGB_TO_XYZ)
    opp = np.array([[0.0, 116.0, 0.0], [500.0, -500.0, 0.0], [0.0, 200.0, -200.0]])
    # Y, Cx, Cz -> X, Y, Z (times the white) -> RGB: affine, as is RGB -> Y, Cx, Cz
    back = np.array([[1 / 116, 1 / 500, 0.0], [1 / 116, 0.0, 0.0], [1 / 116, 0.0, -1 / 200]])
    from_opp = np.asarray(XYZ_TO_RGB) @ np.diag(ILLUMINANT) @ back
    rgb_bias = np.asarray(XYZ_TO_RGB) @ np.diag(ILLUMINANT) @ np.full(3, 16 / 116)
    mats = (opp @ to_xyz, np.array([-16.0, 0.0, 0.0]), from_opp, rgb_bias, to_xyz)
    return tuple(torch.tensor(m.reshape(3, -1), dtype=torch.float32, device=device) for m in mats)


@lru_cache(maxsize=1)
def cmax() -> float:
    """FLIP's largest colour error: Hunt-adjusted HyAB between green and blue, ^ 0.7."""
    to_xyz = colour_matrices()[4]
    f = lab_f_inplace(to_xyz @ torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))   # green, blue
    lum, a, b = 116.0 * f[1] - 16.0, 500.0 * (f[0] - f[1]), 200.0 * (f[1] - f[2])
    ha, hb = 0.01 * lum * a, 0.01 * lum * b
    dist = (lum[0] - lum[1]).abs() + torch.sqrt((ha[0] - ha[1]) ** 2 + (hb[0] - hb[1]) ** 2)
    return float(dist ** QC)

