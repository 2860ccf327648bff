"""The wavelet layer: one-stage 2D DWT with the detail sub-bands removed, reconstructed.

The filter bank is PyWavelets' own: the 1D analysis and synthesis operators are read off
`pywt.dwt` / `pywt.idwt` (mode 'periodization') applied to unit vectors, so the indexing
convention is PyWavelets' by construction (read at a small reference size and wrapped to
the block's: linear in the block size, see `_taps`). They are run as strided circular filters in
torch (a few shifted slices per tap), which is far cheaper than dense matrices.
Odd sizes are extended by one replicated row/column and cropped back.
"""
from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache, wraps
from typing import TypeVar

import numpy as np
import pywt
import torch

F = TypeVar("F", bound=Callable)


def _normal_tensors(fn: F) -> F:
    """Build cached tensors outside inference mode: a tensor made under
    torch.inference_mode() and cached would break any later autograd-tracked use
    (feature-base pre-training, gradient tests) of the same block size."""
    @wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.inference_mode(False):
            return fn(*args, **kwargs)
    return wrapper  # type: ignore[return-value]


def _dense_taps(wavelet: str, n: int) -> tuple[tuple[tuple[int, float], ...], tuple[tuple[int, float], ...]]:
    """Taps read off PyWavelets applied to the n unit vectors: O(n^2), for small n only."""
    eye = np.eye(n)
    analysis = pywt.dwt(eye, wavelet, mode="periodization", axis=1)[0]  # [n, n/2]: row j = A[:, j]
    a_row = analysis[:, 0]                                                # A[0, :]
    synth = pywt.idwt(np.eye(n // 2), None, wavelet, mode="periodization", axis=1)  # [n/2, n]
    s_col = synth[0]                                                       # S[:, 0]
    a = tuple((int(m), float(a_row[m])) for m in np.flatnonzero(np.abs(a_row) > 1e-12))
    s = tuple((int(m), float(s_col[m])) for m in np.flatnonzero(np.abs(s_col) > 1e-12))
    return a, s


def _reference_size(wavelet: str) -> int:
    """An even size at which no tap wraps onto another: four filter lengths."""
    w = pywt.Wavelet(wavelet)
    return 4 * max(w.dec_len, w.rec_len, 2)


@lru_cache(maxsize=64)
def _taps(wavelet: str, n: int) -> tuple[tuple[tuple[int, float], ...], tuple[tuple[int, float], ...]]:
    """Non-zero taps (offset, weight) of the analysis row and synthesis column for even n.

    Periodized analysis is stride-2 circulant: cA[k] = sum_m a[m] x[(2k + m) mod n];
    synthesis (approximation only) is y[n'] = sum_m s[m] u[(n' - m) mod n] with u the
    zero-upsampled coefficients (u[2k] = cA[k]).

    Cost linear in n (reading the taps off an n x n identity would take 1.5 GB for
    n = 8000 and kill a server at n = 40000): above a reference size of four filter
    lengths the taps, as signed offsets, no longer depend on n, so they are read once at
    that size and wrapped modulo n (tests compare both routes over many sizes and wavelets).
    """
    ref = _reference_size(wavelet)
    if n <= ref:
        return _dense_taps(wavelet, n)
    a, s = _dense_taps(wavelet, ref)

    def wrap(taps: tuple[tuple[int, float], ...]) -> tuple[tuple[int, float], ...]:
        signed = ((m if m < ref // 2 else m - ref, w) for m, w in taps)
        return tuple(sorted((m % n, w) for m, w in signed))
    return wrap(a), wrap(s)


def _project_last(x: torch.Tensor, wavelet: str) -> torch.Tensor:
    """Approximation-only DWT + inverse along the last axis."""
    n = x.shape[-1]
    if n % 2:
        x = torch.cat([x, x[..., -1:]], dim=-1)
    a, s = _taps(wavelet, x.shape[-1])
    coeff = sum(torch.roll(x, -off, dims=-1)[..., ::2] * w for off, w in a)
    up = torch.zeros_like(x)
    up[..., ::2] = coeff
    y = sum(torch.roll(up, off, dims=-1) * w for off, w in s)
    return y[..., :n]


def lowpass_projection(x: torch.Tensor, wavelet: str = "haar") -> torch.Tensor:
    """Reconstruct [..., H, W] from its one-stage approximation sub-band only."""
    rows = _project_last(x, wavelet)
    return _project_last(rows.transpose(-1, -2), wavelet).transpose(-1, -2)


def _response(taps: tuple[tuple[int, float], ...], n: int, sign: float) -> torch.Tensor:
    """sum_m w_m exp(sign * 2 pi i f m / n) for f = 0..n-1 (complex64)."""
    f = torch.arange(n, dtype=torch.float64)
    out = torch.zeros(n, dtype=torch.complex128)
    for m, w in taps:
        out += w * torch.exp(sign * 2j * torch.pi * f * m / n)
    return out.to(torch.complex64)


@_normal_tensors
def spectral_operators(wavelet: str, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Analysis and synthesis responses on the rfft2 half-spectrum of an even h x w block.

    With c[k] = sum_m a_m x[2k + m] and y = s * (c upsampled by zeros), the periodized
    approximation-only reconstruction is, per axis, Y(f) = S(f) * 1/2 * sum over the two
    aliases f, f + n/2 of conj(A)(f) X(f), with A, S the DFTs of the taps: the 2D form
    (four aliases) is evaluated in `base.FeatureBase` without any inverse FFT.
    """
    if h % 2 or w % 2:
        raise ValueError("spectral wavelet operators need even block sizes")
    a_h, s_h = _taps(wavelet, h)
    a_w, s_w = _taps(wavelet, w)
    wr = w // 2 + 1
    analysis = _response(a_h, h, +1.0)[:, None] * _response(a_w, w, +1.0)[None, :wr]
    synthesis = _response(s_h, h, -1.0)[:, None] * _response(s_w, w, -1.0)[None, :wr]
    return analysis, synthesis


@_normal_tensors
def quarter_mirror_index(h: int, w: int) -> torch.Tensor:
    """Flat indices into a [h/2, w/2+1] array R of R[-g1 mod h/2, w/2 - g2], for the quarter
    grid g1 < h/2, g2 < w/2 (one gather).

    Why: the alias average Q(g) = 1/4 sum of G over the four aliases of g needs, on the rfft2
    half-spectrum, the columns beyond w/2, which are conj(G[-f1, w - f2]). Summing the two
    row aliases first (R = G[:h/2] + G[h/2:]) turns both mirrored terms into one entry of R:
    Q = 1/4 (R[g1, g2] + conj(R[-g1 mod h/2, w/2 - g2])).
    """
    hh, hw = h // 2, w // 2
    rows = (-torch.arange(hh)) % hh
    cols = hw - torch.arange(hw)
    return (rows[:, None] * (hw + 1) + cols[None, :]).reshape(-1)
