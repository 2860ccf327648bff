"""The pooled colour error (FLIP's colour pipeline in separable filters): zero for equal
images, growing with the noise, seeing chroma noise, tracking FLIP itself, and finite and
bounded on every input a renderer can produce."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.support.extremes import CASES, extreme_halves
from learning.inputs.halves import halves_flip
from noisefeat.display import lab, lightness
from noisefeat.perceptual import csf_kernel, pooled_colour_error

RNG = np.random.default_rng(11)


def smooth(n: int = 6, size: int = 48) -> np.ndarray:
    """Smooth colourful content: ramps of random colours."""
    t = np.linspace(0, 1, size, dtype=np.float32)
    lo, hi = RNG.random((n, 1, 1, 3)) * 0.4, RNG.random((n, 1, 1, 3)) * 0.6
    return (lo + (hi - lo) * t[None, None, :, None] * t[None, :, None, None]).astype(np.float32)


def test_lab_lightness_is_lightness():
    x = RNG.random((2, 8, 8, 3)).astype(np.float32) * 2
    torch.testing.assert_close(lab(x)[..., 0], lightness(torch.as_tensor(x)), atol=1e-4, rtol=0)
    white = lab(np.ones((1, 1, 1, 3), np.float32))[0, 0, 0]
    torch.testing.assert_close(white, torch.tensor([100.0, 0.0, 0.0]), atol=0.05, rtol=0)


def test_kernels_are_normalised_and_widen_with_distance():
    for c in "Lab":
        k = csf_kernel(c, 67.0)
        assert abs(float(k.sum()) - 1.0) < 1e-6 and len(k) % 2 == 1
        assert len(csf_kernel(c, 134.0)) > len(k)          # twice the pixels per degree
    assert len(csf_kernel("b", 67.0)) > len(csf_kernel("L", 67.0))    # blue-yellow is blurriest


def test_zero_for_equal_images_and_growing_with_noise():
    a = smooth()
    assert np.all(pooled_colour_error(a, a).numpy() == 0)
    errs = [pooled_colour_error(a, np.clip(a + RNG.normal(0, s, a.shape), 0, None).astype(np.float32)).numpy()
            for s in (0.002, 0.01, 0.05)]
    assert (errs[0] < errs[1]).all() and (errs[1] < errs[2]).all()


def test_chroma_noise_counts_where_lightness_noise_is_none():
    """Noise that keeps every pixel's luminance: invisible to L* features, seen here."""
    a = np.full((1, 32, 32, 3), 0.3, np.float32)
    w = np.array([0.2126, 0.7152, 0.0722], np.float32)
    d = RNG.normal(0, 0.03, (1, 32, 32, 3)).astype(np.float32)
    d -= (d @ w)[..., None] * w / (w @ w)          # remove the luminance component
    b = a + d
    assert float((lightness(torch.as_tensor(b)) - lightness(torch.as_tensor(a))).abs().max()) < 1e-3
    assert float(pooled_colour_error(a, b)[0]) > 0.01


def test_it_tracks_flip_between_the_halves():
    """log of the pooled error against log FLIP on noisy blocks of several contents and
    noise levels (the property that makes it a cheap stand-in for FLIP)."""
    a = np.concatenate([smooth(4), np.full((2, 48, 48, 3), 0.6, np.float32)])
    mine, flip = [], []
    for s in (0.003, 0.01, 0.03, 0.1):
        b = np.clip(a + RNG.normal(0, s, a.shape) * (0.5 + a), 0, None).astype(np.float32)
        mine += pooled_colour_error(a, b).tolist()
        flip += halves_flip(a, b).tolist()
    assert np.corrcoef(np.log10(mine), np.log10(flip))[0, 1] > 0.97


@pytest.mark.parametrize("case", CASES)
def test_extreme_inputs_give_finite_bounded_errors(case):
    a = RNG.random((2, 16, 16, 3)).astype(np.float32) * 0.5
    a, b = extreme_halves(case, a, a * 0.9)
    e = pooled_colour_error(a, b).numpy()
    assert e.shape == (len(a),) and np.isfinite(e).all() and ((0 <= e) & (e <= 1)).all()
    if case in ("black", "constant", "huge"):      # equal display images: no error at all
        assert (e == 0).all()


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"\[N, H, W, 3\]"):
        pooled_colour_error(np.zeros((8, 8, 3), np.float32), np.zeros((8, 8, 3), np.float32))


def test_the_matrix_filter_equals_the_convolution(monkeypatch):
    """Blocks up to MATRIX_SIDE are filtered by banded matrices, wider ones by conv2d: one
    filter either way (replicated edges included), on a non-square block."""
    import noisefeat.perceptual as P

    x = torch.as_tensor(RNG.normal(size=(3, 40, 24)), dtype=torch.float32)
    by_matrix = {c: P._blur(x, c, 67.0) for c in "Lab"}
    monkeypatch.setattr(P, "MATRIX_SIDE", 0)
    for c in "Lab":
        torch.testing.assert_close(by_matrix[c], P._blur(x, c, 67.0), atol=1e-5, rtol=0)
