"""The dot term (noisefeat.dots): the observer's version-3 rule and the criteria's guard,
at the extremes (black, constant, fireflies, NaN/Inf, tiny and huge values) and on the
dots-on-black case (a few dozen light pixels on black)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from noisefeat.display import display
from noisefeat.dots import (DOT_LEVEL, count_outliers, dot_rank, halves_dots, rank_pool, reference_dots)
from renderer.criteria import UnitView, FlipCriterion, ModelCriterion


def dots_on_black(n: int, value: float = 0.01, size: int = 64, seed: int = 0) -> np.ndarray:
    """Linear RGB [size, size, 3]: black with `n` single light pixels, none adjacent."""
    img = np.zeros((size, size, 3))
    half = size // 2
    ys, xs = np.unravel_index(np.random.default_rng(seed).choice(half * half, n, replace=False), (half, half))
    img[2 * ys, 2 * xs] = value
    return img


def test_rank_is_one_allowed_pixel_per_256_plus_one():
    assert dot_rank(64, 64) == 17 and dot_rank(128, 128) == 65 and dot_rank(16, 16) == 2
    assert dot_rank(8, 8) == 2 and dot_rank(1, 1) == 2          # at least one pixel allowed


@pytest.mark.parametrize("case", ["black", "constant", "huge", "tiny", "one_pixel", "empty"])
def test_rank_pool_at_the_extremes(case):
    maps = {"black": torch.zeros(3, 64, 64), "constant": torch.full((3, 64, 64), 0.3),
            "huge": torch.full((2, 64, 64), 3e38), "tiny": torch.full((2, 64, 64), 1e-38),
            "one_pixel": torch.ones(2, 1, 1), "empty": torch.zeros(0, 64, 64)}[case]
    out = rank_pool(maps)
    assert out.dtype == torch.float64 and out.shape == (maps.shape[0],)
    want = {"black": 0.0, "constant": 0.3 / DOT_LEVEL, "huge": 3e38 / DOT_LEVEL, "tiny": 1e-38 / DOT_LEVEL,
            "one_pixel": 0.0, "empty": None}[case]
    if want is not None:
        np.testing.assert_allclose(out.numpy(), want, rtol=1e-6)


def test_rank_pool_nan_is_never_converged_and_shape_is_checked():
    m = torch.zeros(2, 16, 16)
    m[1, 3, 3] = float("nan")
    out = rank_pool(m).numpy()
    assert out[0] == 0.0 and np.isnan(out[1])
    with pytest.raises(ValueError, match=r"\[N, h, w\]"):
        rank_pool(torch.zeros(16, 16))


@pytest.mark.parametrize("n", [0, 5, 16, 17, 40])
def test_reference_dots_counts_isolated_pixels(n):
    """On black, light pixels of display value ~0.1 (> 0.05): up to 16 pass at tau 0.02."""
    img = dots_on_black(n)
    d = reference_dots(np.zeros_like(img), img[None])[0]
    assert (d <= 0.02) == (n <= 16)
    assert count_outliers(img, np.zeros_like(img), 0.02) == n


@pytest.mark.parametrize("case", ["nan", "posinf", "neginf", "huge", "tiny"])
def test_reference_dots_follow_the_display_rule_on_bad_values(case):
    """NaN/-Inf show black, +Inf and huge values white, tiny values black: the term stays
    finite and counts exactly the pixels that show."""
    img = np.zeros((64, 64, 3))
    value = {"nan": np.nan, "posinf": np.inf, "neginf": -np.inf, "huge": 1e300, "tiny": 1e-300}[case]
    img[::8, ::8] = value                       # 64 pixels
    d = reference_dots(np.zeros((64, 64, 3)), img[None])[0]
    shows = case in ("posinf", "huge")
    assert np.isfinite(d) and (d > 0.02) == shows
    assert count_outliers(img, np.zeros((64, 64, 3)), 0.02) == (64 if shows else 0)


def test_halves_estimate_a_firefly_in_one_half_as_its_own_display_error():
    """A dot that landed in A alone: B is still the truth (black), so the halves see M's
    display error exactly, without the reference."""
    a = dots_on_black(30, value=0.02)
    b = np.zeros_like(a)
    m = (a + b) / 2
    t = [torch.as_tensor(x[None]) for x in (m, a, b)]
    np.testing.assert_allclose(halves_dots(*t[1:]).numpy(), reference_dots(np.zeros_like(m), m[None]), rtol=1e-6)


def test_halves_dots_of_gaussian_noise_track_the_error_against_the_truth():
    """With Gaussian noise |d(M) - d(A)| has the spread of M's own error: the halves'
    term lands within 25 % of the reference's on a grey field."""
    rng = np.random.default_rng(3)
    truth = np.full((64, 64, 3), 0.18)
    a = truth + 0.02 * rng.standard_normal((64, 64, 3))
    b = truth + 0.02 * rng.standard_normal((64, 64, 3))
    m = (a + b) / 2
    h = halves_dots(*[torch.as_tensor(x[None]) for x in (a, b)]).numpy()[0]
    r = reference_dots(truth, m[None])[0]
    assert 0.75 < h / r < 1.25


@pytest.mark.parametrize("case", ["black", "constant", "nan", "inf", "huge", "tiny"])
def test_halves_dots_at_the_extremes(case):
    x = {"black": 0.0, "constant": 0.4, "nan": np.nan, "inf": np.inf, "huge": 1e300, "tiny": 1e-300}[case]
    a = np.full((2, 32, 32, 3), x)
    b = np.full((2, 32, 32, 3), x)
    out = halves_dots(torch.as_tensor(a), torch.as_tensor(b)).numpy()
    assert out.shape == (2,) and np.isfinite(out).all() and (out == 0).all()    # the halves agree


def view(a: np.ndarray, b: np.ndarray, spp: tuple[int, int] = (16, 16)) -> UnitView:
    return UnitView(mean=(a + b) / 2, spp=sum(spp), halves=(a, b), half_spp=spp)


def test_flip_criterion_holds_a_block_whose_halves_disagree_on_dots():
    """40 dots on black in one half. FLIP between the halves at 67 ppd (tile 8x8)
    stays under a lenient c, so without the guard (tau 1: a dot level above any display
    error) the block stops; at tau 0.02 it does not, and its ratio says why."""
    a, b = dots_on_black(40, value=0.01, seed=1), np.zeros((64, 64, 3))
    quiet = (np.full((64, 64, 3), 0.3), np.full((64, 64, 3), 0.3) + 1e-4)
    unguarded = FlipCriterion(0.05, tau=1.0)
    assert unguarded.decide([0, 1], [view(a, b), view(*quiet)]).verdict.tolist() == [1, 1]
    crit = FlipCriterion(0.05, tau=0.02)
    d = crit.decide([0, 1], [view(a, b), view(*quiet)])
    assert d.verdict.tolist() == [-1, 1]
    assert d.counts["dotted_units"] == 1
    assert d.ratio[0] > 1 >= d.ratio[1]


class _Accepting:
    """A local halves model that calls every block converged (score 1 over offset 0)."""
    needs_halves = True
    input = "features"

    def score_blocks(self, *a, **k):     # pragma: no cover - the halves route is taken
        raise AssertionError

    def rule(self, offset=None, min_spp=None):
        from learning.stoprule import StopRule
        return StopRule(0.0 if offset is None else offset)

    def inputs_from_halves(self, even, odd, exposure=0.0):
        return np.zeros((len(even), 1))

    def decision_function(self, x):
        return np.ones(len(x))


def test_model_criterion_holds_dotted_blocks_too():
    a, b = dots_on_black(40, value=0.01, seed=2), np.zeros((64, 64, 3))
    quiet = (np.full((64, 64, 3), 0.3), np.full((64, 64, 3), 0.3) + 1e-4)
    crit = ModelCriterion(_Accepting(), tau=0.02)
    assert crit.decide([0, 1], [view(a, b), view(*quiet)]).verdict.tolist() == [-1, 1]
    assert ModelCriterion(_Accepting(), tau=1.0).decide([0], [view(a, b)]).verdict.tolist() == [1]


def test_the_served_halves_route_holds_dotted_blocks():
    """`Model.assess_halves` (the service's route) applies the same guard at its tau."""
    from learning.models.bundle import load_model

    m = load_model()
    a = np.stack([dots_on_black(40, value=0.01, seed=3), np.full((64, 64, 3), 0.3)]).astype(np.float32)
    b = np.stack([np.zeros((64, 64, 3)), np.full((64, 64, 3), 0.3)]).astype(np.float32)
    loose = m.assess_halves(a, b, offset=-1e6, tau=1.0)[0]           # every score passes this offset
    strict = m.assess_halves(a, b, offset=-1e6, tau=0.02)[0]
    assert loose.tolist() == [1, 1] and strict.tolist() == [-1, 1]
