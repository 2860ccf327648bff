"""The `halves` model input: content-free noise features, defined on every input a renderer
can produce (black, constant, fireflies, NaN/Inf, tiny and huge values), one composition."""
from __future__ import annotations

import numpy as np
import pytest

from tests.support.extremes import CASES, extreme_halves
from learning.inputs.noise_input import (COMPOSITIONS, FEATURE_FLOOR, FLIP_FLOOR, HALVES, compose, halves_input,
                                         halves_mean, halves_raw, layout, n_inputs, parts_of)
from noisefeat.base import N_FEATURES

RNG = np.random.default_rng(3)
H = W = 32


def noisy_pair(content: np.ndarray, sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return tuple(np.clip(content + rng.normal(0, sigma, content.shape), 0, None).astype(np.float32)
                 for _ in range(2))


@pytest.mark.parametrize("composition", COMPOSITIONS)
def test_layout_and_shapes(composition):
    a, b = noisy_pair(np.full((3, H, W, 3), 0.2), 0.02)
    x = halves_input(a, b, composition=composition)
    assert x.shape == (3, n_inputs(composition)) == (3, len(layout(composition))) and x.dtype == np.float32
    empty = np.zeros((0, H, W, 3), np.float32)
    assert halves_input(empty, empty, composition=composition).shape == (0, n_inputs(composition))
    assert halves_raw(a, b).shape == (3, 2 * N_FEATURES + 2)
    assert n_inputs(HALVES) >= 1


def test_noise_features_ignore_content_and_follow_noise():
    """The same noise on a flat grey and on a high-contrast checker gives nearly the same
    noise features, while the current-image features tell the two contents apart; more
    noise gives larger noise features, and a larger FLIP value."""
    yy, xx = np.mgrid[0:H, 0:W]
    checker = np.where(((yy // 4) + (xx // 4)) % 2, 0.3, 0.1)[None, ..., None] * np.ones((1, 1, 1, 3))
    grey = np.full((1, H, W, 3), 0.2)
    noise = [halves_input(*noisy_pair(c, 0.01, seed=5), composition="n+c")[0] for c in (grey, checker)]
    half = n_inputs("n")
    content_gap = np.abs(noise[0][half:] - noise[1][half:]).mean()
    noise_gap = np.abs(noise[0][:half] - noise[1][:half]).mean()
    assert noise_gap < 0.25 * content_gap
    louder = halves_input(*noisy_pair(grey, 0.04, seed=5), composition="n+f")[0]
    quieter = halves_input(*noisy_pair(grey, 0.01, seed=5), composition="n+f")[0]
    assert (louder > quieter).all()


def test_identical_halves_have_no_noise():
    content = RNG.random((2, H, W, 3)).astype(np.float32)
    x = halves_input(content, content, composition="f+n+c")
    np.testing.assert_array_equal(x[:, 0], np.log10(FLIP_FLOOR))
    np.testing.assert_array_equal(x[:, 1:1 + n_inputs("n")], np.log10(FEATURE_FLOOR))
    assert (x[:, 1 + n_inputs("n"):] > np.log10(FEATURE_FLOOR)).all()       # the content is still seen


@pytest.mark.parametrize("case", [c for c in CASES if c != "empty"])
def test_extreme_inputs_give_finite_bounded_features(case):
    base = RNG.random((2, H, W, 3)).astype(np.float32) * 0.3
    a, b = extreme_halves(case, base, base * 0.9)
    x = halves_input(a, b, composition="f+n+c")
    assert np.isfinite(x).all()
    # log10 of FLIP (<= 1) and of an L* std (<= 100): from the floors up to 0 and 2
    assert x[:, 0].min() >= np.log10(FLIP_FLOOR) and x[:, 0].max() <= 0.0
    assert (x[:, 1:] >= np.log10(FEATURE_FLOOR)).all() and (x[:, 1:] <= 2.0 + 1e-6).all()
    m = halves_mean(a, b)
    assert np.isfinite(m).all() and m.shape == a.shape


def test_halves_mean_drops_non_finite_pixels_per_half():
    a = np.full((1, 8, 8, 3), 0.4, np.float32)
    b = np.full((1, 8, 8, 3), 0.2, np.float32)
    a[0, 0, 0, 1] = np.nan
    m = halves_mean(a, b)
    assert m[0, 0, 0].tolist() == pytest.approx([0.1] * 3)        # the NaN pixel of A reads as 0
    assert m[0, 1, 1].tolist() == pytest.approx([0.3] * 3)


@pytest.mark.parametrize("even, odd, match", [
    (np.zeros((1, 16, 16, 3), np.float32), np.zeros((1, 16, 8, 3), np.float32), "one shape"),
    (np.zeros((1, 16, 16), np.float32), np.zeros((1, 16, 16), np.float32), r"\[N, h, w, 3\]"),
    (np.zeros((1, 16, 16, 3), np.int32), np.zeros((1, 16, 16, 3), np.int32), "floating point"),
])
def test_bad_input_is_refused_clearly(even, odd, match):
    with pytest.raises(ValueError, match=match):
        halves_input(even, odd)


def test_non_finite_exposure_is_refused():
    a = np.zeros((1, 16, 16, 3), np.float32)
    with pytest.raises(ValueError, match="exposure"):
        halves_input(a, a, exposure=float("nan"))


def test_compose_checks_its_inputs():
    with pytest.raises(ValueError, match="halves features"):
        compose(np.zeros((2, 26)), None, "n")
    with pytest.raises(ValueError, match="FLIP"):
        compose(np.zeros((2, 52)), None, "f+n")
    for bad in ("", "f+f", "x", "n+q"):
        with pytest.raises(ValueError, match="composition"):
            parts_of(bad)
    # FLIP not measured (NaN: a flat block) reads as the floor, never as NaN
    x = compose(None, np.array([np.nan, 0.5]), "f")
    np.testing.assert_allclose(x[:, 0], [np.log10(FLIP_FLOOR), np.log10(0.5)], rtol=1e-6)
