"""The one display transform of DESIGN.md, and CIE L* of its result.

Linear HDR RGB -> x 2**exposure -> clip to [0, 1] -> sRGB.  Non-finite pixels are never
propagated: NaN and -Inf become 0 (black), +Inf becomes 1 (white, what clipping a very
bright sample gives). Callers that need to report them count them with `nonfinite_pixels`.

The exposure is a number of stops in `EXPOSURE_RANGE` ([-64, 64]: 2**64 is far beyond any
useful display scaling and far inside float range). Outside it, `check_exposure` raises
ValueError: `2.0 ** 2000` overflowed into a server error and a traceback (issue 14).
"""
from __future__ import annotations

import numpy as np
import torch

from .bounds import EXPOSURE_RANGE

# Rec. 709 / sRGB primaries, D65 white: relative luminance weights.
LUMA = (0.2126, 0.7152, 0.0722)
_LAB_EPS = (6.0 / 29.0) ** 3
_LAB_SLOPE = 1.0 / (3.0 * (6.0 / 29.0) ** 2)


def nonfinite_pixels(rgb: torch.Tensor) -> torch.Tensor:
    """Per image of a [..., H, W, C] batch: how many pixels hold a NaN or Inf channel."""
    bad = ~torch.isfinite(rgb)
    if rgb.ndim >= 1:
        bad = bad.any(dim=-1)
    return bad.flatten(start_dim=-2).sum(dim=-1) if bad.ndim >= 2 else bad.long()


def check_exposure(exposure: float) -> float:
    """`exposure` as a float if it is a number of stops in EXPOSURE_RANGE, else ValueError."""
    low, high = EXPOSURE_RANGE
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float, np.integer, np.floating)) \
            or not low <= exposure <= high:
        shown = exposure if not isinstance(exposure, int) or abs(exposure) < 10**30 else \
            f"a {len(str(abs(exposure)))}-digit number"
        raise ValueError(f"exposure must be a number of stops in [{low:g}, {high:g}], got {shown}")
    return float(exposure)


def clipped_linear(rgb: torch.Tensor, exposure: float = 0.0) -> torch.Tensor:
    """Scale by 2**exposure, map non-finite values (rule above), clip to [0, 1]; float32."""
    x = rgb.to(torch.float32)
    if exposure != 0.0:
        exposure = check_exposure(exposure)
        x = x * float(2.0 ** exposure)
    x = torch.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0)  # always a fresh tensor
    return x.clamp_(0.0, 1.0)


def srgb_encode(linear01: torch.Tensor) -> torch.Tensor:
    """sRGB transfer function (IEC 61966-2-1) on values already in [0, 1]."""
    return torch.where(linear01 <= 0.0031308, 12.92 * linear01,
                       1.055 * linear01.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)


def srgb_decode(srgb01: torch.Tensor) -> torch.Tensor:
    """Inverse of `srgb_encode`."""
    return torch.where(srgb01 <= 0.04045, srgb01 / 12.92,
                       ((srgb01.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def display(rgb: torch.Tensor | np.ndarray, exposure: float = 0.0) -> torch.Tensor:
    """Display-referred sRGB in [0, 1] of linear RGB (any float dtype, any leading shape)."""
    return srgb_encode(clipped_linear(torch.as_tensor(rgb), exposure))


def display_range(blocks: torch.Tensor | np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Per block of linear RGB [N, h, w, 3]: the largest per-channel (max - min) of its
    display-referred values, float64 [N] in [0, 1] (0 for an empty block)."""
    x = clipped_linear(torch.as_tensor(blocks), exposure)
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"expected linear RGB blocks [N, h, w, 3], got shape {tuple(x.shape)}")
    if x.shape[0] == 0 or x.shape[1] * x.shape[2] == 0:
        return np.zeros(x.shape[0])
    # the sRGB transfer is monotonic: the encoded extremes are the extremes encoded, so
    # only 2 x 3 values per block are encoded (equal to the range of `display` up to one
    # float32 rounding of torch's vectorised pow; memory: one copy of the blocks, not five)
    flat = x.reshape(x.shape[0], -1, 3)
    return (srgb_encode(flat.amax(dim=1)) - srgb_encode(flat.amin(dim=1))).amax(dim=1).double().numpy()


def lightness(rgb: torch.Tensor, exposure: float = 0.0) -> torch.Tensor:
    """CIE L* (0..100) of the display-referred image, [..., H, W, 3] -> [..., H, W].

    Lab of an sRGB pixel decodes it back to linear first, so L* of display(x) equals L*
    of the clipped linear value: computing it from there skips an encode/decode pair
    (tests check both routes agree). Written in place on one working copy: this runs on
    every block of every pass.
    """
    x = clipped_linear(rgb, exposure)
    y = x @ torch.tensor(LUMA, dtype=torch.float32)
    small = y <= _LAB_EPS
    f = y.pow_(1.0 / 3.0) if not small.any() else torch.where(small, y * _LAB_SLOPE + 4.0 / 29.0, y.pow(1.0 / 3.0))
    return f.mul_(116.0).sub_(16.0)


#: linear sRGB (D65) -> CIE XYZ, rows X, Y, Z (Y: the LUMA row, as `lightness`); D65 white
_RGB_TO_XYZ = ((0.4124564, 0.3575761, 0.1804375), LUMA, (0.0193339, 0.1191920, 0.9503041))
_WHITE = (0.95047, 1.0, 1.08883)


def relative_xyz(rgb: torch.Tensor | np.ndarray, exposure: float = 0.0) -> torch.Tensor:
    """CIE XYZ / white point of the display-referred image, [..., 3] -> [..., 3]."""
    x = clipped_linear(torch.as_tensor(rgb), exposure)
    return x @ (torch.tensor(_RGB_TO_XYZ, dtype=torch.float32).T / torch.tensor(_WHITE, dtype=torch.float32))


def lab_f(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """CIELab's f(t) of relative XYZ and its derivative f'(t) (one cube root for both)."""
    small = t <= _LAB_EPS
    f = torch.where(small, t * _LAB_SLOPE + 4.0 / 29.0, t.clamp_min(_LAB_EPS).pow(1.0 / 3.0))
    return f, torch.where(small, torch.full_like(t, _LAB_SLOPE), f / (3.0 * t.clamp_min(_LAB_EPS)))


def lab_from_f(f: torch.Tensor) -> torch.Tensor:
    """L*a*b* from f of relative X, Y, Z (the last axis)."""
    return torch.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]),
                        200.0 * (f[..., 1] - f[..., 2])], dim=-1)


def lab(rgb: torch.Tensor | np.ndarray, exposure: float = 0.0) -> torch.Tensor:
    """CIE L*a*b* of the display-referred image, [..., H, W, 3] -> [..., H, W, 3] (L* as
    `lightness`, which uses the same luminance row)."""
    return lab_from_f(lab_f(relative_xyz(rgb, exposure))[0])
