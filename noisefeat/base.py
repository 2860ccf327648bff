"""FeatureBase: L-channel blocks [N, 1, H, W] -> 26 noise features.

Twelve single-channel convolutions in sequence (3x3 pad 1, 5x5 pad 2, alternating; no
bias, no activation) and a thirteenth, wavelet layer applied to the twelfth output (one
stage of PyWavelets' DWT with the detail sub-bands removed, reconstructed). For each of
the 13 outputs O_l the noise map is input - O_l.

Feature order: columns 0..12 are the mean of the noise maps of layers 1..13, columns
13..25 their (population) standard deviation.

Why the convolutions are evaluated in the frequency domain: single-channel convolutions
are the worst case for CPU convolution kernels (torch.conv2d: ~590 ms for 101 blocks of
128x128 on this machine's 2 cores). With circular padding the 12-layer stack is diagonal
in the Fourier basis, so one FFT per block gives every layer's noise variance by
Parseval's theorem (a [N, HW/2] x [HW/2, 12] matmul) and its mean from the DC term:
~150x faster and exact up to float rounding (tests compare against torch.conv2d with
padding_mode='circular'). Circular padding is the padding mode; the wrap seam it puts at
block borders appears in quick and current images alike, whose feature difference is the
model input. `layer_outputs` is the plain spatial route, kept for training and tests.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import torch
from torch import nn

from .cache import ByteLRU, default_max_bytes
from .weights import KERNEL_SIZES, kernels_hash, load_kernels
from .wavelet import lowpass_projection, quarter_mirror_index, spectral_operators

N_LAYERS = len(KERNEL_SIZES) + 1
N_FEATURES = 2 * N_LAYERS
MIN_SIZE = 8
FEATURE_NAMES: tuple[str, ...] = tuple(
    [f"mean_{i + 1:02d}" for i in range(N_LAYERS)] + [f"std_{i + 1:02d}" for i in range(N_LAYERS)])
_F32_MAX = torch.finfo(torch.float32).max
#: columns of the gain matrix: the 12 conv layers, zero-padded (see _build_operators)
_GAIN_COLUMNS = 16


#: longest run of terms one float32 matmul sums (`_weighted_sums`)
_SEGMENT = 1 << 15


def _weighted_sums(power: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """power [n, K] @ weights [K, ...] in segments of `_SEGMENT` terms, partial sums added.

    Why: one float32 matmul over the ~1 M spectrum terms of a 1024x1024 block drifted by
    4e-4 (relative) from the float64 value; sums of 32 k terms stay at float32 rounding.
    Blocks up to 128x128 take one matmul."""
    k = power.shape[1]
    if k <= _SEGMENT:
        return power @ weights
    total = power[:, :_SEGMENT] @ weights[:_SEGMENT]
    for start in range(_SEGMENT, k, _SEGMENT):
        total = total + power[:, start:start + _SEGMENT] @ weights[start:start + _SEGMENT]
    return total


def column_weights(w: int, wr: int) -> torch.Tensor:
    """rfft keeps half the columns: each but DC (and Nyquist, for even w) also stands for
    its mirror image in Parseval sums."""
    col_w = torch.full((wr,), 2.0)
    col_w[0] = 1.0
    if w % 2 == 0:
        col_w[-1] = 1.0
    return col_w


class FeatureBase(nn.Module):
    """The noise-feature base of the paper: 12 conv layers + 1 wavelet layer -> 26 features.

    Twelve single-channel convolutions in sequence (kernels 3x3, 5x5, 3x3, ...; circular
    padding), then a one-stage 2D wavelet decomposition with its high-frequency bands
    removed. For each of the 13 layer outputs O_l the noise map is ``input - O_l``; its
    mean and standard deviation are the features (`FEATURE_NAMES`). The forward pass is
    computed in the frequency domain (exact, any block size); `layer_outputs` is the
    spatial definition.

    Parameters
    ----------
    weights : str or pathlib.Path, optional
        The conv kernels: a safetensors file, or a name, 'smoothing' (default, the shipped
        deterministic initialisation) or 'pretrained' (the user's own pre-training in the
        user data directory if any, else the shipped file; `noisefeat.weights`).
    wavelet : str, default 'haar'
        The PyWavelets name of the thirteenth layer's wavelet.
    operator_cache_bytes : int, optional
        Bytes of per-block-size frequency operators kept (default: `noisefeat.cache`'s
        budget); a server seeing many block sizes stays within it.

    Attributes
    ----------
    weights_name : str
        File name of the kernels loaded.
    hash : str
        Identity of the weights and wavelet; model bundles record it and refuse another.
    """

    def __init__(self, weights: str | Path | None = None, wavelet: str = "haar",
                 operator_cache_bytes: int | None = None) -> None:
        super().__init__()
        kernels, self.weights_name = load_kernels(weights)
        self.wavelet = wavelet
        self.convs = nn.ModuleList()
        for k, w in zip(KERNEL_SIZES, kernels):
            conv = nn.Conv2d(1, 1, k, padding=k // 2, padding_mode="circular", bias=False)
            with torch.no_grad():
                conv.weight.copy_(w.reshape(1, 1, k, k))
            self.convs.append(conv)
        # per block size, bounded by bytes (noisefeat.cache: ~80 bytes a pixel per size)
        self._transfer_cache = ByteLRU(default_max_bytes() if operator_cache_bytes is None
                                       else operator_cache_bytes)

    # -- identity -------------------------------------------------------------------
    def kernels(self) -> list[torch.Tensor]:
        return [c.weight.detach()[0, 0] for c in self.convs]

    @property
    def hash(self) -> str:
        """Changes whenever the weights or the wavelet change (checked by model bundles)."""
        return kernels_hash(self.kernels(), self.wavelet)

    # -- the two routes -------------------------------------------------------------
    def layer_outputs(self, x: torch.Tensor) -> list[torch.Tensor]:
        """O_1..O_13 computed spatially with torch.conv2d (slow; for training and tests)."""
        x = self._sanitize(x)
        outs, o = [], x.to(torch.float32)
        for conv in self.convs:
            o = conv(o)
            outs.append(o)
        outs.append(lowpass_projection(o, self.wavelet))
        return outs

    def transfer(self, h: int, w: int) -> torch.Tensor:
        """Cumulative frequency responses [12, h, w//2+1] of layers 1..12 on an h x w block."""
        return torch.stack(list(self._responses(h, w)))

    def _responses(self, h: int, w: int) -> Iterator[torch.Tensor]:
        """The cumulative responses of `transfer`, one layer at a time (bounded memory)."""
        acc = None
        for conv in self.convs:
            k = conv.weight[0, 0]
            r = k.shape[-1] // 2
            emb = torch.zeros(h, w, dtype=torch.float32)
            emb = emb.index_put((torch.arange(-r, r + 1).remainder(h)[:, None],
                                 torch.arange(-r, r + 1).remainder(w)[None, :]), k)
            # conv2d is a cross-correlation: its transfer function is the conjugate FFT.
            resp = torch.conj(torch.fft.rfft2(emb))
            acc = resp if acc is None else acc * resp
            yield acc

    def _operators(self, h: int, w: int) -> dict[str, torch.Tensor]:
        """Everything forward needs that depends only on the block size and the weights.

        Cached while gradients are off (inference); rebuilt when the weights change.
        """
        version = tuple((id(c.weight), c.weight._version) for c in self.convs)
        key = (h, w)
        cached = self._transfer_cache.get(key)
        if cached is not None and cached[0] == version:
            return cached[1]
        if torch.is_grad_enabled():
            return self._build_operators(h, w)
        # built as normal tensors even under torch.inference_mode(): an inference tensor in
        # the cache would break a later autograd-tracked forward of the same size
        with torch.inference_mode(False), torch.no_grad():
            ops = self._build_operators(h, w)
        self._transfer_cache.put(key, (version, ops))
        return ops

    def _build_operators(self, h: int, w: int) -> dict[str, torch.Tensor]:
        """Only what `features_centred` reads is kept (~80 bytes a pixel of the block): the
        gain of every layer, the wavelet layer's operators, the twelfth layer's response
        for odd sizes.

        The gain matrix is [2 * h * (w//2+1), 16]: each bin twice, for the real and the
        imaginary part of the interleaved spectrum (squaring the contiguous [.., 2] view is
        ~4x faster than re*re + im*im on strided views), and 16 columns, 12 of them used (a
        [n, K] x [K, 16] matmul is 2x faster than [K, 12] here): measured, BENCHMARKS.md
        "Feature extraction"."""
        wr = w // 2 + 1
        col_w = column_weights(w, wr)
        gain = torch.zeros(h * wr, 2, _GAIN_COLUMNS)
        dcs, acc = [], None
        for layer, acc in enumerate(self._responses(h, w)):    # one layer's temporaries at a time
            gain[:, :, layer] = ((1.0 - acc).abs() ** 2 * col_w).reshape(-1, 1)
            dcs.append(acc[0, 0].real)
        assert acc is not None
        ops = {"gain": gain.reshape(-1, _GAIN_COLUMNS), "dc": torch.stack(dcs)}
        if h % 2 == 0 and w % 2 == 0:
            hh, hw = h // 2, w // 2
            analysis, synthesis = spectral_operators(self.wavelet, h, w)
            # 1/4 of the alias average folded in; the synthesis split by row halves, as the
            # noise spectrum is evaluated on [2, h/2, w/2] views (see _wavelet_even)
            ops["analysis12"] = 0.25 * analysis * acc
            ops["synthesis"] = synthesis[:, :hw].reshape(2, hh, hw).contiguous()
            ops["synthesis_nyquist"] = synthesis[:, hw].reshape(2, hh).contiguous()
            ops["col_w"] = col_w[:hw].repeat_interleave(2).repeat(h)
            ops["mirror"] = quarter_mirror_index(h, w)
        else:
            ops["resp12"] = acc
        return ops

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """The 26 features of each L-channel block.

        Parameters
        ----------
        x : torch.Tensor
            [N, 1, H, W] L* blocks (0..100 for display-referred input), any real dtype,
            H and W at least 8. Non-finite values are read as 0.

        Returns
        -------
        torch.Tensor
            float32 [N, 26], finite (each block is normalised by its largest magnitude
            first, so that huge and tiny inputs stay in float32 range).

        Raises
        ------
        ValueError
            If `x` is not [N, 1, H, W], a block is under 8x8, or the dtype is not real.
        """
        x = self._sanitize(x)
        n, _, h, w = x.shape
        if n == 0:
            return torch.zeros(0, N_FEATURES, dtype=torch.float32)
        x = x[:, 0]
        # Features are homogeneous of degree 1 in x: normalise each block by its largest
        # magnitude so that huge (1e30) and tiny (1e-30) inputs stay in float32 range.
        scale = x.abs().amax(dim=(-2, -1), keepdim=True)
        scale = torch.where(scale > 0, scale, torch.ones_like(scale))
        xs = (x / scale).to(torch.float32)
        scale = scale.to(torch.float32) if scale.dtype != torch.float64 else scale
        mu = xs.mean(dim=(-2, -1), keepdim=True)
        feats = self.features_centred(xs - mu, mu.reshape(n)) * scale.reshape(n, 1)
        return torch.nan_to_num(feats.clamp(-_F32_MAX, _F32_MAX), nan=0.0, posinf=_F32_MAX, neginf=-_F32_MAX)

    def features_centred(self, xc: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        """The 26 features of blocks given as their centred values xc [N, H, W] (float32,
        each block of mean zero) and their means mu [N]: what `forward` computes after its
        range normalisation, and what the fused extraction (noisefeat.fused) calls on L*
        blocks, whose range (0..100) needs none.

        One rfft2 per block; every conv layer's noise variance is a weighted sum of the
        power spectrum (Parseval: one matmul for the twelve), its mean follows from mu and
        the layer's DC gain, and the wavelet layer is evaluated in the same spectrum.
        """
        n, h, w = xc.shape
        spec = torch.fft.rfft2(xc)
        # mean zero by contract: the DC bin holds only the rounding left by the centring (a
        # constant block's would read as a 1e-12 wavelet-layer mean)
        spec[:, 0, 0] = 0.0
        ops = self._operators(h, w)
        parts = torch.view_as_real(spec)
        power = parts * parts                      # re^2, im^2 interleaved (x * x: 2x square() here)
        var = _weighted_sums(power.reshape(n, -1), ops["gain"])[:, :N_LAYERS - 1] / float(h * w) ** 2   # [n, 12]
        std_conv = var.clamp_min(0.0).sqrt()
        mean_conv = mu.reshape(n, 1) * (1.0 - ops["dc"])[None, :]
        if "analysis12" in ops:
            mean13, std13 = self._wavelet_even(spec, ops, mu)
        else:
            mean13, std13 = self._wavelet_odd(xc + mu.reshape(n, 1, 1), spec, ops, mu)
        return torch.cat([mean_conv, mean13.reshape(n, 1), std_conv, std13.reshape(n, 1)], dim=1)

    @staticmethod
    def _wavelet_even(spec: torch.Tensor, ops: dict[str, torch.Tensor],
                      mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and std of input - P(O_12), P the wavelet low-pass projection, on an even
        block: the noise spectrum X - S * Q(f mod (h/2, w/2)) with Q the alias average of
        the analysis response times X (aliasing form of the periodized DWT, see
        wavelet.spectral_operators), never leaving the frequency domain.

        The two row aliases are summed first (half the spectrum), the two column aliases
        then meet through one gather on the quarter grid (conjugate symmetry of a real
        block's spectrum); the noise spectrum is formed on [2, h/2, w/2] views of the half
        spectrum in one multiply-subtract, plus its Nyquist column."""
        n, h, wr = spec.shape
        hh, hw = h // 2, wr - 1
        w = 2 * hw
        z = spec * ops["analysis12"]
        rows = z[:, :hh] + z[:, hh:]                                              # [n, h/2, w/2+1]
        mirrored = torch.gather(rows.reshape(n, -1), 1, ops["mirror"].expand(n, -1)).reshape(n, hh, hw)
        q = rows[..., :hw] + mirrored.conj()                                      # [n, h/2, w/2]
        noise = torch.addcmul(spec[..., :hw].unflatten(1, (2, hh)), ops["synthesis"], q[:, None], value=-1)
        parts = torch.view_as_real(noise)
        total = _weighted_sums((parts * parts).reshape(n, -1), ops["col_w"])
        nyq = spec[..., hw].unflatten(1, (2, hh)) - ops["synthesis_nyquist"] * q[..., 0].unsqueeze(1)
        total = total + torch.view_as_real(nyq).square().sum(dim=(1, 2, 3))
        dc = noise[:, 0, 0, 0]
        var = (total - (dc.real ** 2 + dc.imag ** 2)) / float(h * w) ** 2
        mean = dc.real / float(h * w) + mu.reshape(n) * (1.0 - ops["dc"][-1])
        return mean, var.clamp_min(0.0).sqrt()

    def _wavelet_odd(self, xs: torch.Tensor, spec: torch.Tensor, ops: dict[str, torch.Tensor],
                     mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Odd sizes: one inverse FFT to O_12 and the spatial wavelet filters."""
        n, h, w = xs.shape
        o12 = torch.fft.irfft2(spec * ops["resp12"], s=(h, w)) + mu.reshape(n, 1, 1) * ops["dc"][-1]
        noise13 = xs - lowpass_projection(o12, self.wavelet)
        mean = noise13.mean(dim=(-2, -1))
        var = ((noise13 - mean[:, None, None]) ** 2).mean(dim=(-2, -1))
        return mean, var.sqrt()

    @staticmethod
    def _sanitize(x: torch.Tensor) -> torch.Tensor:
        if not isinstance(x, torch.Tensor):
            x = torch.as_tensor(x)
        if x.ndim != 4 or x.shape[1] != 1:
            raise ValueError(f"FeatureBase expects L-channel blocks [N, 1, H, W], got {tuple(x.shape)}")
        if x.shape[-1] < MIN_SIZE or x.shape[-2] < MIN_SIZE:
            raise ValueError(f"blocks must be at least {MIN_SIZE}x{MIN_SIZE} pixels, got "
                             f"{x.shape[-2]}x{x.shape[-1]}")
        if not (x.is_floating_point() or x.dtype in (torch.uint8, torch.int16, torch.int32, torch.int64)):
            raise ValueError(f"FeatureBase expects real-valued input, got dtype {x.dtype}")
        if x.dtype != torch.float64:  # float64 keeps its range until normalised
            x = x.to(torch.float32)
        return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
