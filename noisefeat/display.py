"""The one display transform of DESIGN.md, and CIE L* of its result.

Linear HDR RGB -> x 2**exposure -> clip to [0, 1] -> sRGB.  Non-finite pixels are never
propagated: NaN and -Inf become 0 (black), +Inf becomes 1 (white, what clipping a very
bright sample gives). Callers that need to report them count them with `nonfinite_pixels`.

The exposure is a number of stops in `EXPOSURE_RANGE` ([-64, 64]: 2**64 is far beyond any
useful display scaling and far inside float range). Outside it, `check_exposure` raises
ValueError, since `2.0 ** 2000` would overflow into a server error and a traceback.

`lightness_into` is the one implementation of display transform + L*: it runs on
every block of every pass, so it works in place on one work buffer, skips the clip when
nothing needs clipping, and takes the cube root as exp(log(.)/3) (torch's pow is 2-5x
slower here), with CIELab's linear toe only when some luminance is below its knee.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .bounds import EXPOSURE_RANGE

# Rec. 709 / sRGB primaries, D65 white: relative luminance weights.
LUMA = (0.2126, 0.7152, 0.0722)
_LAB_EPS = (6.0 / 29.0) ** 3
_LAB_SLOPE = 1.0 / (3.0 * (6.0 / 29.0) ** 2)


def nonfinite_pixels(rgb: torch.Tensor) -> torch.Tensor:
    """Per image of a [..., H, W, C] batch: how many pixels hold a NaN or Inf channel.

    One min/max pass answers "none" (the usual case) before any per-pixel mask is built."""
    if rgb.ndim >= 3 and rgb.numel() and rgb.is_floating_point():
        low, high = torch.aminmax(rgb)
        if math.isfinite(float(low)) and math.isfinite(float(high)):
            return torch.zeros(rgb.shape[:-3], dtype=torch.int64)
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
    x = torch.as_tensor(blocks)
    if x.ndim != 4 or x.shape[-1] != 3:
        raise ValueError(f"expected linear RGB blocks [N, h, w, 3], got shape {tuple(x.shape)}")
    if x.shape[0] == 0 or x.shape[1] * x.shape[2] == 0:
        return np.zeros(x.shape[0])
    x = x.to(torch.float32)
    if exposure != 0.0:
        x = x * float(2.0 ** check_exposure(exposure))
    lo, hi = block_extremes(x.contiguous())
    if not bool(torch.isfinite(lo).all() & torch.isfinite(hi).all()):
        lo, hi = block_extremes(clipped_linear(x))           # the display rule first (rare)
    return _encoded_range(lo, hi)


def _encoded_range(lo: torch.Tensor, hi: torch.Tensor) -> np.ndarray:
    """display_range from per-channel extremes [N, 3] of the linear values: the clip and the
    sRGB transfer are monotonic, so the encoded extremes are the extremes clipped and
    encoded (2 x 3 values per block). Encoded in float64: torch's vectorised float32 pow
    rounds differently in vector lanes and in the scalar tail, which would make a block's
    range (by 1 ulp) depend on how many blocks share the call."""
    lo, hi = lo.double().clamp(0.0, 1.0), hi.double().clamp(0.0, 1.0)
    return (srgb_encode(hi) - srgb_encode(lo)).amax(dim=1).cpu().numpy()


def block_extremes(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per block and channel, (min, max) of a contiguous [N, h, w, C] tensor, [N, C] each
    (NaN where a channel holds one).

    Two-level reductions over contiguous rows: torch's reduction over a middle axis whose
    inner size is 3 is ~20x slower on this CPU (measured: 2.3 ms against 0.1 ms for 16
    blocks of 128x128)."""
    n, h, w, c = x.shape
    rows = x.reshape(n, h, w * c)
    return rows.amin(1).view(n, w, c).amin(1), rows.amax(1).view(n, w, c).amax(1)


_LUMA32 = torch.tensor(LUMA, dtype=torch.float32)
#: L* = L_SCALE * (G - OFFSET), G as `lightness_into` leaves it: Y^(1/3), with CIELab's
#: linear toe below the knee as max(Y, eps)^(1/3) + slope (min(Y, eps) - eps), whose second
#: term is exactly 0 above the knee (so a block's G does not depend on its chunk's branch).
#: The factor 116 is left to the caller: the features are linear in L*, so the fused path
#: scales its 26 numbers a block instead of every pixel
L_SCALE = 116.0
OFFSET = 16.0 / 116.0
#: pixels per chunk of `lightness` and of the fused feature path (128 blocks of 128x128):
#: bounds the work buffers (about 40 bytes a pixel) of large batches. Smaller chunks that
#: stay in cache measured slower on 2 threads: each operation pays torch's thread
#: fork/join, and 16-block chunks took 17.5 ms for 101 blocks against 13.5 ms in one chunk
CHUNK_PIXELS = 1 << 21


def lightness_into(x: torch.Tensor, exposure: float, out: torch.Tensor, work: torch.Tensor,
                   extremes: bool = False) -> tuple[float, torch.Tensor | None, np.ndarray | None]:
    """L* of linear RGB x [..., 3] (contiguous, any float dtype) written to `out` [...]
    float32 as G, where L* = L_SCALE * (G - offset); `work` is a float32 buffer shaped like x
    (overwritten).

    Returns (OFFSET, non-finite pixel counts per block of a [c, h, w, 3] x or None when x
    holds none, the display range per block (`display_range`) if `extremes` else None).
    `exposure` must be checked already (check_exposure). The scale and offset are left to
    the caller: the feature path subtracts each block's mean anyway.
    """
    raw = x
    if x.dtype != torch.float32:
        work.copy_(x)
        x = work
    if exposure != 0.0:
        x = torch.mul(x, float(2.0 ** exposure), out=work)      # as clipped_linear
    if extremes:
        lo, hi = block_extremes(x)
        low, high = float(lo.min()), float(hi.max())
    else:
        low, high = (float(v) for v in torch.aminmax(x))
    bad = span = None
    if not (math.isfinite(low) and math.isfinite(high)):
        # the display rule (rare: non-finite input, or the exposure overflowed float32)
        bad = nonfinite_pixels(raw) if raw.ndim >= 3 else None
        x = torch.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0, out=work).clamp_(0.0, 1.0)
        if extremes:
            lo, hi = block_extremes(x)
        low = float(x.min())
    elif low < 0.0 or high > 1.0:
        x = torch.clamp(x, 0.0, 1.0, out=work)
        low = max(low, 0.0)
    if extremes:
        span = _encoded_range(lo, hi)
    torch.matmul(x, _LUMA32, out=out)
    # the cube root as exp(log(Y) / 3) on Y itself (its log is at most 4.7 in magnitude, so
    # the log's rounding stays ~1e-7 relative): L* within 2 float32 ulp
    if low >= _LAB_EPS * (1.0 + 1e-3):        # every Y above the knee (the weights sum to 1)
        out.log_().mul_(1.0 / 3.0).exp_()
        return OFFSET, bad, span
    toe = work.view(-1)[:out.numel()].view(out.shape)        # x has been read: reuse its buffer
    torch.clamp_max(out, _LAB_EPS, out=toe).sub_(_LAB_EPS)   # min(Y, eps) - eps: 0 above the knee
    out.clamp_min_(_LAB_EPS).log_().mul_(1.0 / 3.0).exp_()
    out.add_(toe, alpha=_LAB_SLOPE)
    return OFFSET, bad, span


def lightness(rgb: torch.Tensor | np.ndarray, exposure: float = 0.0) -> torch.Tensor:
    """CIE L* (0..100) of the display-referred image, [..., 3] -> [...] float32.

    Lab of an sRGB pixel decodes it back to linear first, so L* of display(x) equals L*
    of the clipped linear value: computing it from there skips an encode/decode pair
    (tests check both routes agree). Chunked through `lightness_into`.
    """
    exposure = check_exposure(exposure)
    t = torch.as_tensor(rgb)
    if t.ndim < 1 or t.shape[-1] != 3:
        raise ValueError(f"expected linear RGB [..., 3], got shape {tuple(t.shape)}")
    if not t.is_floating_point():
        t = t.to(torch.float32)
    pixels = t.reshape(-1, 3)
    out = torch.empty(pixels.shape[0], dtype=torch.float32)
    if len(pixels):
        work = torch.empty(min(CHUNK_PIXELS, len(pixels)), 3, dtype=torch.float32)
        for i in range(0, len(pixels), CHUNK_PIXELS):
            x = pixels[i:i + CHUNK_PIXELS].contiguous()
            o = out[i:i + len(x)]
            o.sub_(lightness_into(x, exposure, o, work[:len(x)])[0]).mul_(L_SCALE)
    return out.reshape(t.shape[:-1])


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
