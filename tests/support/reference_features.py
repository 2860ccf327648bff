"""The feature pipeline as it was before the fused extraction, frozen as an oracle.

Why a frozen copy: the fused path rewrote `extract_features` (one chunked pass: display
transform, L*, spectrum, features) and the spectral code of `FeatureBase`; "equal to the
old implementation within float32 rounding" can only be tested against the old code
itself. This is the code of commit 3d81504 (noisefeat/display.py `lightness`,
noisefeat/base.py `forward` and its wavelet layer, noisefeat/wavelet.py `alias_average`),
with the operators rebuilt here from the base's kernels (`FeatureBase._responses`) and the
wavelet module's `spectral_operators` / `lowpass_projection`, which the fused path left unchanged.
Slow (no caching); for tests only.
"""
from __future__ import annotations

import numpy as np
import torch

from noisefeat.base import FeatureBase, column_weights
from noisefeat.display import LUMA
from noisefeat.wavelet import lowpass_projection, spectral_operators

_LAB_EPS = (6.0 / 29.0) ** 3
_LAB_SLOPE = 1.0 / (3.0 * (6.0 / 29.0) ** 2)
_F32_MAX = torch.finfo(torch.float32).max


def old_nonfinite_pixels(rgb: torch.Tensor) -> torch.Tensor:
    return (~torch.isfinite(rgb)).any(dim=-1).flatten(start_dim=-2).sum(dim=-1)


def old_lightness(rgb: torch.Tensor, exposure: float = 0.0) -> torch.Tensor:
    x = rgb.to(torch.float32)
    if exposure != 0.0:
        x = x * float(2.0 ** exposure)
    x = torch.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)
    y = x @ torch.tensor(LUMA, dtype=torch.float32)
    small = y <= _LAB_EPS
    f = torch.where(small, y * _LAB_SLOPE + 4.0 / 29.0, y.pow(1.0 / 3.0))
    return f.mul_(116.0).sub_(16.0)


def _alias_average(g: torch.Tensor, h: int, w: int) -> torch.Tensor:
    half_w, half_h = w // 2, h // 2
    wr = w // 2 + 1
    index = ((-torch.arange(h)) % h)[:, None] * wr + (w // 2 - torch.arange(w // 2))[None, :]
    flat = g.reshape(*g.shape[:-2], -1)
    mirrored = torch.conj(flat.index_select(-1, index.reshape(-1)).reshape(*g.shape[:-2], h, half_w))
    cols = g[..., :half_w] + mirrored
    return 0.25 * (cols[..., :half_h, :] + cols[..., half_h:, :])


def old_base(base: FeatureBase, x: torch.Tensor) -> torch.Tensor:
    """FeatureBase.forward of commit 3d81504 on [N, 1, H, W] L blocks."""
    x = torch.nan_to_num(x.to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)[:, 0]
    n, h, w = x.shape
    scale = x.abs().amax(dim=(-2, -1), keepdim=True)
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    xs = x / scale
    mu = xs.mean(dim=(-2, -1), keepdim=True)
    spec = torch.fft.rfft2(xs - mu)
    col_w = column_weights(w, w // 2 + 1)
    resp = list(base._responses(h, w))
    gain = torch.stack([((1.0 - a).abs() ** 2 * col_w).reshape(-1) for a in resp], dim=1)
    dcs = torch.stack([a[0, 0].real for a in resp])
    acc = resp[-1]
    power = (spec.real ** 2 + spec.imag ** 2).reshape(n, -1)
    std_conv = ((power @ gain) / float(h * w) ** 2).clamp_min(0.0).sqrt()
    mean_conv = mu.reshape(n, 1) * (1.0 - dcs)[None, :]
    low_dc = dcs[-1]
    if h % 2 == 0 and w % 2 == 0:
        analysis, syn = spectral_operators(base.wavelet, h, w)
        q = _alias_average(analysis * acc * spec, h, w)
        hh, hw = h // 2, w // 2
        total = torch.zeros(n)
        for rows in (slice(0, hh), slice(hh, h)):
            part = spec[:, rows, :hw] - syn[rows, :hw] * q
            total += ((part.real ** 2 + part.imag ** 2) * col_w[:hw]).sum(dim=(-2, -1))
            nyq = spec[:, rows, hw] - syn[rows, hw] * q[:, :, 0]
            total += (nyq.real ** 2 + nyq.imag ** 2).sum(dim=-1)
            if rows.start == 0:
                dc = part[:, 0, 0]
        std13 = ((total - (dc.real ** 2 + dc.imag ** 2)) / float(h * w) ** 2).clamp_min(0.0).sqrt()
        mean13 = dc.real / float(h * w) + mu.reshape(n) * (1.0 - low_dc)
    else:
        o12 = torch.fft.irfft2(spec * acc, s=(h, w)) + mu * low_dc
        noise13 = xs - lowpass_projection(o12, base.wavelet)
        mean13 = noise13.mean(dim=(-2, -1))
        std13 = ((noise13 - mean13[:, None, None]) ** 2).mean(dim=(-2, -1)).sqrt()
    feats = torch.cat([mean_conv, mean13.reshape(n, 1), std_conv, std13.reshape(n, 1)], dim=1)
    feats = (feats * scale.reshape(n, 1)).clamp(-_F32_MAX, _F32_MAX)
    return torch.nan_to_num(feats, nan=0.0, posinf=_F32_MAX, neginf=-_F32_MAX)


def old_extract_features(blocks: np.ndarray, base: FeatureBase, exposure: float = 0.0
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(features float32 [N, 26], non-finite pixel counts [N]) as commit 3d81504 computed them."""
    t = torch.as_tensor(blocks)
    with torch.no_grad():
        bad = old_nonfinite_pixels(t).numpy().astype(np.int64)
        return old_base(base, old_lightness(t, exposure)[:, None]).numpy(), bad


def old_halves_features(even: np.ndarray, odd: np.ndarray, base: FeatureBase, exposure: float = 0.0
                        ) -> np.ndarray:
    """float32 [N, 53]: the 26 features of N = L*(A) - L*(B), the 26 of C = (A + B) / 2, and
    C's mean L*, as `halves_raw` of commit 3d81504 computed them (without its last column)."""
    a, b = np.asarray(even), np.asarray(odd)
    ok_a, ok_b = (np.isfinite(x).all(axis=-1, keepdims=True) for x in (a, b))
    c = ((np.where(ok_a, a, 0.0) + np.where(ok_b, b, 0.0)) * 0.5).astype(np.float32)
    with torch.no_grad():
        la, lb = old_lightness(torch.as_tensor(a), exposure), old_lightness(torch.as_tensor(b), exposure)
        lc = old_lightness(torch.as_tensor(c), exposure)
        both = old_base(base, torch.cat([la - lb, lc])[:, None])
        n = len(a)
        return torch.cat([both[:n], both[n:], lc.mean(dim=(1, 2))[:, None]], dim=1).numpy()


def old_display_range(blocks: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """display.display_range of commit 3d81504 (clip a full copy, then min/max per channel)."""
    x = torch.as_tensor(blocks).to(torch.float32)
    if exposure != 0.0:
        x = x * float(2.0 ** exposure)
    x = torch.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)
    flat = x.reshape(x.shape[0], -1, 3)

    def encode(v: torch.Tensor) -> torch.Tensor:
        return torch.where(v <= 0.0031308, 12.92 * v, 1.055 * v.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)
    return (encode(flat.amax(dim=1)) - encode(flat.amin(dim=1))).amax(dim=1).double().numpy()
