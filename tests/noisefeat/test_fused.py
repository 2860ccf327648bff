"""The fused feature path against the code it replaced, on realistic and extreme input.

`reference_features` is a frozen copy of the unfused pipeline (lightness, then
FeatureBase.forward). "Equal within float32 rounding" is asserted as: features within
2e-4 + 2e-4 x |old| (L* is on a 0..100 scale, where one float32 ulp is 7.6e-6; on a
1024x1024 block the old route's single float32 sum over 0.5 M spectrum terms is itself
1e-4 off, relative), L* within 1.5e-4, non-finite pixel counts equal, display ranges within two
float32 ulp (they are now encoded in float64); and, against a float64 evaluation of the definition, the new route is at most as
far off as the old one (plus a float32 ulp of L*), so no accuracy was traded for speed.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.support.extremes import CASES, extreme_halves
from learning.inputs.noise_input import halves_input_and_stats, halves_mean, halves_raw
from noisefeat import FeatureBase, extract_features, fused
from noisefeat.display import display_range, lightness
from noisefeat.extract import analyse_blocks, analyse_many
from tests.support.reference_features import old_display_range, old_extract_features, old_halves_features, old_lightness

ATOL, RTOL = 2e-4, 2e-4
#: display ranges (0..1) are now encoded in float64; the old float32 ones are off by up to 2 ulp (two roundings)
ULP2 = 2.0 ** -22


@pytest.fixture(scope="module")
def base() -> FeatureBase:
    return FeatureBase().eval()


def realistic(n: int, h: int, w: int, seed: int = 0) -> np.ndarray:
    """Shaded ramps with noise proportional to the signal and sparse HDR highlights (> 1)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = 0.05 + 0.6 * xx[..., None] * rng.random((n, 1, 1, 3)) + 0.3 * yy[..., None] * rng.random((n, 1, 1, 3))
    x = img * (1.0 + rng.standard_normal((n, h, w, 3)) * rng.uniform(0, 0.3, (n, 1, 1, 1)))
    x[:, ::17, ::13] *= 8.0
    return x.astype(np.float32)


def _fireflies() -> np.ndarray:
    x = np.random.default_rng(1).random((3, 32, 32, 3)).astype(np.float32) * 0.2
    x[1, ::7, ::5] = 1e6
    x[2, 3, 3] = 3e38
    return x


def _nonfinite() -> np.ndarray:
    x = np.random.default_rng(2).random((4, 16, 16, 3)).astype(np.float32)
    x[1, 3, 4, 0] = np.nan
    x[1, 5, 5, :] = -np.inf
    x[2, 0, 0, 2] = np.inf
    x[3] = np.nan
    return x


INPUTS = {
    "realistic 128x128": lambda: realistic(6, 128, 128),
    "realistic 64x48": lambda: realistic(5, 64, 48, 1),
    "black": lambda: np.zeros((3, 16, 16, 3), np.float32),
    "constant": lambda: np.full((3, 16, 16, 3), 0.3, np.float32),
    "constant 200x200 (non-power-of-two FFT)": lambda: np.full((2, 200, 200, 3), 0.37, np.float32),
    "fireflies and float32 max": _fireflies,
    "huge": lambda: np.random.default_rng(3).random((2, 16, 16, 3)).astype(np.float32) * np.float32(3e38),
    "tiny (below the L* knee)": lambda: (np.random.default_rng(4).random((3, 32, 32, 3)) * 1e-4).astype(np.float32),
    "1e-30": lambda: (np.random.default_rng(5).random((2, 16, 16, 3)) * 1e-30).astype(np.float32),
    "negative": lambda: np.random.default_rng(6).standard_normal((3, 32, 32, 3)).astype(np.float32),
    "NaN and Inf": _nonfinite,
    "8x8": lambda: np.random.default_rng(7).random((5, 8, 8, 3)).astype(np.float32),
    "odd 9x11": lambda: np.random.default_rng(8).random((4, 9, 11, 3)).astype(np.float32),
    "large 1024x1024": lambda: realistic(1, 1024, 1024, 2),
    "float16": lambda: (np.random.default_rng(9).random((2, 16, 16, 3)) * 2).astype(np.float16),
    "float64 beyond float32": lambda: np.random.default_rng(10).random((2, 16, 16, 3)) * 1e300,
}


@pytest.mark.parametrize("exposure", [0.0, 2.5, -3.0])
@pytest.mark.parametrize("name", list(INPUTS))
def test_extract_features_equals_the_old_pipeline(base, name, exposure):
    x = INPUTS[name]()
    want, want_bad = old_extract_features(x, base, exposure)
    got, bad = extract_features(x, base=base, exposure=exposure, return_nonfinite=True)
    assert got.dtype == np.float32 and np.isfinite(got).all()
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)
    np.testing.assert_array_equal(bad, want_bad)
    # features that were exactly zero stay zero (flat blocks: black, constant, 1e-30); up to
    # the centring's rounding (1e-13) on sizes whose FFT is not exact for constants
    assert np.abs(got[want == 0]).max(initial=0.0) <= (0.0 if x.shape[1] in (8, 16, 32) else 1e-9)


@pytest.mark.parametrize("name", list(INPUTS))
def test_lightness_and_display_range_equal_the_old_ones(name):
    x = INPUTS[name]()
    for exposure in (0.0, 1.5):
        torch.testing.assert_close(lightness(x, exposure), old_lightness(torch.as_tensor(x), exposure),
                                   atol=1.5e-4, rtol=0)
        np.testing.assert_allclose(display_range(x, exposure), old_display_range(x, exposure), rtol=0, atol=ULP2)
    _, stats = analyse_blocks(x, display_range=True)
    np.testing.assert_allclose(stats.display_range, old_display_range(x), rtol=0, atol=ULP2)


def test_chunks_do_not_mix_blocks(base, monkeypatch):
    """More blocks than a chunk holds (chunks of 4 blocks here), with a non-finite block, a
    dark block (the L* toe) and a bright one in different chunks: each row equals that
    block computed alone, and L* does not depend on the chunk's branch at all."""
    import sys
    monkeypatch.setattr(sys.modules["noisefeat.display"], "CHUNK_PIXELS", 4 * 64 * 64)
    monkeypatch.setattr(fused, "CHUNK_PIXELS", 4 * 64 * 64)
    per_chunk = fused.chunk_blocks(64, 64)
    assert per_chunk == 4
    n = 2 * per_chunk + 3
    x = realistic(n, 64, 64, 11)
    x[per_chunk + 1, 5, 5] = np.nan
    x[2 * per_chunk + 2] *= 1e-3
    x[3] += 0.5
    L = lightness(x)
    for i in (0, 3, per_chunk + 1, 2 * per_chunk + 2):
        torch.testing.assert_close(L[i], lightness(x[i:i + 1])[0], atol=0, rtol=0)
    feats, bad = extract_features(x, base=base, return_nonfinite=True)
    assert bad.tolist() == [1 if i == per_chunk + 1 else 0 for i in range(n)]
    for i in range(n):
        np.testing.assert_allclose(feats[i], extract_features(x[i:i + 1], base=base)[0], atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(feats, old_extract_features(x, base)[0], atol=ATOL, rtol=RTOL)
    raw = halves_raw(x, x[::-1].copy(), base=base)
    np.testing.assert_allclose(raw[:, :53], old_halves_features(x, x[::-1].copy(), base), atol=ATOL, rtol=RTOL)


def _definition_float64(base: FeatureBase, L: torch.Tensor) -> np.ndarray:
    """The 26 features by their definition, in float64: twelve circular convolutions in
    space, the wavelet layer by its spatial filters, mean and std of each noise map."""
    from torch.nn import functional as F

    from noisefeat.wavelet import lowpass_projection
    x = L.double()[:, None]
    outs, o = [], x
    for k in base.kernels():
        r = k.shape[-1] // 2
        o = F.conv2d(F.pad(o, (r, r, r, r), mode="circular"), k.double()[None, None])
        outs.append(o)
    outs.append(lowpass_projection(o, base.wavelet))
    means = torch.stack([(x - o)[:, 0].mean((-2, -1)) for o in outs], 1)
    stds = torch.stack([(x - o)[:, 0].std((-2, -1), correction=0) for o in outs], 1)
    return torch.cat([means, stds], 1).numpy()


@pytest.mark.parametrize("shape", [(4, 64, 64), (1, 512, 512)])
def test_fused_route_is_as_accurate_as_the_old_one(base, shape):
    """Both float32 routes against the definition evaluated in float64 on float64 L*: the
    new one is no further off than the old one (up to a float32 ulp of L*)."""
    x = realistic(*shape, 12)
    y = np.clip(x.astype(np.float64), 0.0, 1.0) @ np.array([0.2126, 0.7152, 0.0722])
    L64 = np.where(y > (6 / 29) ** 3, 116 * np.cbrt(y) - 16, 116 * y / (3 * (6 / 29) ** 2))
    exact = _definition_float64(base, torch.from_numpy(L64))
    old_err = np.abs(old_extract_features(x, base)[0] - exact).max()
    new_err = np.abs(extract_features(x, base=base) - exact).max()
    assert new_err <= old_err + 1e-5, (new_err, old_err)


@pytest.mark.parametrize("case", [c for c in CASES if c != "empty"] + ["realistic"])
def test_halves_features_equal_the_old_halves_raw(base, case):
    a = realistic(3, 64, 64, 13)
    b = (a * (1.0 + 0.05 * np.random.default_rng(14).standard_normal(a.shape))).astype(np.float32)
    if case != "realistic":
        a, b = extreme_halves(case, a, b)
    raw = halves_raw(a, b, base=base)
    want = old_halves_features(a, b, base)
    np.testing.assert_allclose(raw[:, :want.shape[1]], want, atol=ATOL, rtol=RTOL)
    # the statistics of the same pass: counts of both halves, the flat test on their mean
    _, stats = halves_input_and_stats(a, b, composition="n+c+l", base=base)
    expect_bad = old_extract_features(a, base)[1] + old_extract_features(b, base)[1]
    np.testing.assert_array_equal(stats.nonfinite, expect_bad)
    np.testing.assert_allclose(stats.display_range, old_display_range(halves_mean(a, b)), rtol=0, atol=ULP2)
    _, flip_stats = halves_input_and_stats(a, b, composition="f")   # no features: its own pass
    np.testing.assert_array_equal(flip_stats.nonfinite, expect_bad)
    np.testing.assert_array_equal(flip_stats.display_range, stats.display_range)


def test_empty_batches(base):
    assert extract_features(np.zeros((0, 16, 16, 3), np.float32), base=base).shape == (0, 26)
    assert halves_raw(np.zeros((0, 16, 16, 3), np.float32), np.zeros((0, 16, 16, 3), np.float32)).shape == (0, 54)
    assert lightness(np.zeros((0, 3), np.float32)).shape == (0,)


def test_several_batches_in_one_call_equal_separate_calls(base, monkeypatch):
    """analyse_many (a request's blocks and quick images in one spectral pass) gives each
    batch what analyse_blocks gives it alone, across a chunk boundary too."""
    monkeypatch.setattr(fused, "CHUNK_PIXELS", 5 * 32 * 32)      # chunks of 5 blocks: 3 + 2 mixed
    a = realistic(3, 32, 32, 15)
    b = _nonfinite()[:, :16, :16].repeat(2, axis=1).repeat(2, axis=2)[:4]
    together = analyse_many([a, b, a[:1]], base=base, display_range=[True, False, True])
    for (feats, stats), x, with_range in zip(together, [a, b, a[:1]], [True, False, True]):
        want, want_stats = analyse_blocks(x, base=base, display_range=with_range)
        np.testing.assert_allclose(feats, want, atol=1e-5, rtol=1e-5)
        np.testing.assert_array_equal(stats.nonfinite, want_stats.nonfinite)
        np.testing.assert_array_equal(stats.display_range, want_stats.display_range)
    assert np.isnan(together[1][1].display_range).all()            # not asked for
    with pytest.raises(ValueError, match="different sizes"):
        analyse_many([a, np.zeros((1, 16, 16, 3), np.float32)], base=base)
