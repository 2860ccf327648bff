"""The fused feature path: linear RGB blocks -> display transform -> L* -> 26 features.

Why: run as separate whole-batch steps, the display transform and L* cost as much as the
twelve layers (measured: 27-30 ms for 101 blocks of 128x128, 6.6x a matmul of the same
multiply-adds): every step wrote a fresh full-size tensor (clip, nan_to_num, luminance,
cube root, where, range normalisation, centring) and the non-finite count walked the
blocks twice more. Here the blocks go through one short sequence of in-place operations
on two work buffers, in chunks of `display.CHUNK_PIXELS` pixels (which bounds the buffers
of large batches):

1. display transform and L* (`display.lightness_into`): one min/max pass says whether the
   chunk needs the non-finite rule or the clip at all (and gives the display range of the
   flat-block test when asked), one matrix-vector product gives the luminance, exp(log/3)
   the cube root, CIELab's toe only when some luminance is below its knee; the constant
   of L* goes into the block mean and its factor 116 into the 26 features of each block;
2. each block centred in place (its mean kept), then `FeatureBase.features_centred`: one
   rfft2, the twelve layers by Parseval in one matmul, the wavelet layer in the same
   spectrum. L* lies in 0..100, so the range normalisation of `FeatureBase.forward` (for
   inputs of any magnitude) is not needed.

The result equals the unfused route (display.lightness, then FeatureBase) within float32
rounding (tests/noisefeat/test_fused.py, against a frozen copy of the unfused pipeline), and a
block's features do not depend on the other blocks of the call (up to float32 rounding of
the batched matmuls).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .base import N_FEATURES, FeatureBase
from .display import CHUNK_PIXELS, L_SCALE, display_range, lightness_into, nonfinite_pixels


@dataclass
class RGBStats:
    """Per block, what the fused pass learns about the RGB besides its features."""

    nonfinite: np.ndarray        # int64 [N]: pixels holding a NaN or Inf channel
    display_range: np.ndarray    # float64 [N]: `display.display_range` (NaN when not asked for)


def chunk_blocks(h: int, w: int) -> int:
    """Blocks per chunk for blocks of h x w pixels (at least one)."""
    return max(1, CHUNK_PIXELS // max(1, h * w))


def _centre(g: torch.Tensor) -> torch.Tensor:
    """Subtract each block's mean in place; the means [c]."""
    mu = g.mean(dim=(-2, -1), keepdim=True)
    g.sub_(mu)
    return mu.reshape(-1)


def features(blocks: torch.Tensor, exposure: float, base: FeatureBase,
             with_range: bool = False) -> tuple[torch.Tensor, RGBStats]:
    """(float32 [N, 26] features, RGBStats) of linear RGB blocks [N, H, W, 3] (shape and
    exposure checked by the caller); the display range is computed only if `with_range`."""
    return features_of([blocks], exposure, base, [with_range])[0]


def features_of(sources: list[torch.Tensor], exposure: float, base: FeatureBase,
                with_range: list[bool] | None = None) -> list[tuple[torch.Tensor, RGBStats]]:
    """`features` of several batches of blocks of one size at once (a request's blocks and
    their quick images; or the blocks of several requests): per chunk, L* of each source
    into one buffer, then one spectral call for all of them. No source is copied."""
    with_range = with_range or [False] * len(sources)
    if len({tuple(x.shape[1:]) for x in sources}) > 1:
        raise ValueError(f"blocks of different sizes cannot share a call: {[tuple(x.shape) for x in sources]}")
    out = [(torch.empty(len(x), N_FEATURES, dtype=torch.float32),
            RGBStats(np.zeros(len(x), np.int64), np.full(len(x), np.nan))) for x in sources]
    pending = [(k, i) for k, x in enumerate(sources) for i in range(len(x))]   # (source, block)
    if not pending:
        return out
    _, h, w, _ = sources[0].shape
    step = min(len(pending), chunk_blocks(h, w))
    g_buf = torch.empty(step, h, w, dtype=torch.float32)
    work = torch.empty(step, h, w, 3, dtype=torch.float32)
    for start in range(0, len(pending), step):
        chunk = pending[start:start + step]
        runs = []                                    # (source, first block, count, slot in g_buf)
        for slot, (k, i) in enumerate(chunk):
            if runs and runs[-1][0] == k:
                runs[-1][2] += 1
            else:
                runs.append([k, i, 1, slot])
        mu_parts = []
        for k, i, c, slot in runs:
            g = g_buf[slot:slot + c]
            offset, bad, span = lightness_into(sources[k][i:i + c].contiguous(), exposure, g, work[:c],
                                               extremes=with_range[k])
            stats = out[k][1]
            if bad is not None:
                stats.nonfinite[i:i + c] = bad.numpy()
            if span is not None:
                stats.display_range[i:i + c] = span
            mu_parts.append(offset)
        g = g_buf[:len(chunk)]
        mu = _centre(g)
        for (k, i, c, slot), offset in zip(runs, mu_parts):
            mu[slot:slot + c] -= offset
        feats = base.features_centred(g, mu).mul_(L_SCALE)      # features are linear in L*
        for k, i, c, slot in runs:
            out[k][0][i:i + c] = feats[slot:slot + c]
    return out


def _current(a: torch.Tensor, b: torch.Tensor, out: torch.Tensor, finite: bool) -> torch.Tensor:
    """C = (A + B) / 2, a pixel not finite in one half counting as 0 there (the rule of
    learning.inputs.noise_input.halves_mean), written to `out` when the inputs are float32."""
    if not finite:
        a, b = (torch.where(torch.isfinite(x).all(dim=-1, keepdim=True), x, torch.zeros((), dtype=x.dtype))
                for x in (a, b))
    if a.dtype == b.dtype == torch.float32:
        return torch.add(a, b, out=out).mul_(0.5)
    return (a + b) * 0.5


def halves_features(even: torch.Tensor, odd: torch.Tensor, exposure: float, base: FeatureBase,
                    with_range: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, RGBStats]:
    """For N blocks' half buffers A (`even`) and B (`odd`), [N, H, W, 3] each (checked by
    the caller): the features of the noise image L*(A) - L*(B) [N, 26], those of the current
    image C = (A + B) / 2 [N, 26], C's mean L* [N], and RGBStats (non-finite pixels of A
    plus those of B; C's display range if `with_range`).

    L* of A and of B is computed once, in the chunk that also computes C's, and the noise
    and current images of a chunk go through one spectral call."""
    n, h, w, _ = even.shape
    noise_f = torch.empty(n, N_FEATURES, dtype=torch.float32)
    current_f = torch.empty(n, N_FEATURES, dtype=torch.float32)
    mean_l = torch.empty(n, dtype=torch.float32)
    stats = RGBStats(np.zeros(n, np.int64), np.full(n, np.nan))
    if n == 0:
        return noise_f, current_f, mean_l, stats
    step = min(n, chunk_blocks(h, w))
    g_buf = torch.empty(3 * step, h, w, dtype=torch.float32)
    work = torch.empty(step, h, w, 3, dtype=torch.float32)
    c_buf = torch.empty(step, h, w, 3, dtype=torch.float32)
    for i in range(0, n, step):
        a, b = even[i:i + step].contiguous(), odd[i:i + step].contiguous()
        c = len(a)
        ga, gc, gb = g_buf[:c], g_buf[c:2 * c], g_buf[2 * c:3 * c]
        off_a, bad_a, _ = lightness_into(a, exposure, ga, work[:c])
        off_b, bad_b, _ = lightness_into(b, exposure, gb, work[:c])
        for bad in (bad_a, bad_b):
            if bad is not None:
                stats.nonfinite[i:i + c] += bad.numpy()
        cur = _current(a, b, c_buf[:c], finite=bad_a is None and bad_b is None)
        off_c, _, span = lightness_into(cur.contiguous(), exposure, gc, work[:c], extremes=with_range)
        if span is not None:
            stats.display_range[i:i + c] = span
        ga.sub_(gb)                                   # the noise image, less (off_a - off_b)
        both = g_buf[:2 * c]                          # [noise; current]: one spectral call
        mu = _centre(both)
        mu[:c] -= off_a - off_b
        mu[c:] -= off_c
        out = base.features_centred(both, mu).mul_(L_SCALE)      # features are linear in L*
        noise_f[i:i + c], current_f[i:i + c] = out[:c], out[c:]
        mean_l[i:i + c] = mu[c:] * L_SCALE
    return noise_f, current_f, mean_l, stats


def halves_stats(even: torch.Tensor, odd: torch.Tensor, exposure: float) -> RGBStats:
    """RGBStats of N blocks' half buffers without their features: non-finite pixels of A
    plus those of B, and the display range of the current image C (the flat-block test),
    for inputs that read no features (the `f` composition: FLIP only)."""
    n, h, w, _ = even.shape
    stats = RGBStats(np.zeros(n, np.int64), np.zeros(n))
    step = min(max(n, 1), chunk_blocks(h, w))
    c_buf = torch.empty(step, h, w, 3, dtype=torch.float32)
    for i in range(0, n, step):
        a, b = even[i:i + step].contiguous(), odd[i:i + step].contiguous()
        c = len(a)
        bad = nonfinite_pixels(a) + nonfinite_pixels(b)
        stats.nonfinite[i:i + c] = bad.numpy()
        stats.display_range[i:i + c] = display_range(_current(a, b, c_buf[:c], finite=not bad.any()), exposure)
    return stats
