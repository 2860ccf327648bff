"""A unit's noise estimate from its decision history: one formula in two forms
(the calibration's matrix, the live loop's running sums), stable at the extremes."""
from __future__ import annotations

import numpy as np
import pytest

from learning.inputs.history import ALPHA, Evidence, combine, running

SPP = np.array([32, 64, 96, 128, 160, 192], np.float64)


def _incremental(e: np.ndarray) -> np.ndarray:
    """What the live loop computes, a decision at a time."""
    ev, out = Evidence(e.shape[1]), []
    ids = np.arange(e.shape[1])
    for k in range(len(e)):
        spp = np.full(e.shape[1], SPP[k])
        hist, x = combine(ev.rows(ids), e[k], spp)
        ev.add(ids, x, spp)
        out.append(hist)
    return np.array(out)


def test_the_live_form_is_the_calibration_form() -> None:
    rng = np.random.default_rng(0)
    e = rng.uniform(0.005, 0.2, (len(SPP), 9))
    e[rng.random(e.shape) < 0.2] = np.nan          # levels without a decision
    assert np.allclose(_incremental(e), running(e, SPP), equal_nan=True)
    assert np.array_equal(np.isnan(running(e, SPP)), np.isnan(e))


def test_with_a_constant_step_the_history_is_the_plain_mean_bit_for_bit() -> None:
    """Decided after every pass, every weight is the step: the statistic the tile curve of
    c(tau) was calibrated on, to the last bit for a power-of-two step."""
    rng = np.random.default_rng(2)
    e = rng.uniform(0.005, 0.2, (len(SPP), 7))
    x = e * SPP[:, None] ** ALPHA
    plain = np.cumsum(x, axis=0) / np.arange(1, len(SPP) + 1)[:, None] / SPP[:, None] ** ALPHA
    assert np.array_equal(running(e, SPP), plain)


def test_sparse_decisions_weigh_each_estimate_by_the_samples_it_stands_for() -> None:
    """Decided at some levels only (a geometric decision schedule), each estimate
    weighs the spp since the unit's decision before it, so the history is the step
    schedule's mean sampled more sparsely, not one tilted towards the early levels."""
    rng = np.random.default_rng(3)
    e = rng.uniform(0.005, 0.2, (len(SPP), 5))
    at = [0, 1, 3, 5]                                   # the levels decided
    ev, ids = Evidence(5), np.arange(5)
    for k in at:
        spp = np.full(5, SPP[k])
        hist, x = combine(ev.rows(ids), e[k], spp)
        ev.add(ids, x, spp)
    w = np.diff(SPP[at], prepend=0.0)
    expect = (w[:, None] * e[at] * SPP[at, None] ** ALPHA).sum(axis=0) / w.sum() / SPP[-1] ** ALPHA
    assert np.allclose(hist, expect, rtol=1e-12)
    assert np.array_equal(ev.sums[:, 1], np.full(5, SPP[-1]))


def test_an_exact_monte_carlo_decay_is_its_own_estimate_and_noise_averages_out() -> None:
    exact = 0.3 / SPP[:, None] ** ALPHA * np.ones((1, 4))
    assert np.allclose(running(exact, SPP), exact)
    # one level's score scatters about the decay; the history's much less
    rng = np.random.default_rng(1)
    noisy = exact[:, :1] * rng.lognormal(0.0, 0.3, (len(SPP), 2000))
    spread = lambda m: np.std(np.log(m[-1] / exact[-1, 0]))   # noqa: E731
    assert spread(running(noisy, SPP)) < 0.6 * spread(noisy)


@pytest.mark.parametrize("value", [0.0, 1e-30, 1e-6, 0.5, 1e30])
def test_black_tiny_constant_and_huge_scores_stay_finite(value: float) -> None:
    e = np.full((len(SPP), 3), value)
    out = running(e, SPP)
    assert np.isfinite(out).all()
    assert (out >= 0).all() and np.allclose(out[0], value)


def test_non_finite_scores_are_no_decision_and_add_nothing() -> None:
    e = np.array([[np.nan, 0.1, np.inf, -np.inf]] * 2)
    out = running(e, SPP[:2])
    assert np.isnan(out[:, [0, 2, 3]]).all() and np.isfinite(out[:, 1]).all()
    ev = Evidence(4)
    _, x = combine(None, e[0], SPP[:4])
    ev.add(np.arange(4), x, SPP[:4])
    assert np.array_equal(ev.sums[:, 1], [0, 64, 0, 0]) and np.isfinite(ev.sums).all()
    assert np.array_equal(ev.last, SPP[:4])            # a decision without a score is still the last one


def test_flip_at_tile_grain_stops_on_the_history_and_at_block_grain_on_one_level() -> None:
    """A unit whose first estimate was loud and whose current level looks quiet stays noisy
    when its history says so; the same level alone (block grain) stops it. The evidence it
    returns is what the loop adds (`renderer.live.passloop.PassLoop`)."""
    from renderer.criteria import UnitBatch, UnitView, FlipCriterion

    def batch_of(noise: float, seed: int, spp: int, sums=None) -> UnitBatch:
        rng = np.random.default_rng(seed)
        a, b = (0.3 + noise * rng.standard_normal((16, 16, 3)) for _ in range(2))
        batch = UnitBatch.from_views([UnitView(mean=(a + b) / 2, spp=spp, halves=(a, b), half_spp=(spp // 2,) * 2)])
        batch.evidence = sums
        return batch
    tile, block = FlipCriterion(0.02, tile=16), FlipCriterion(0.02)
    assert (tile.statistic, block.statistic) == ("history-mean", "last")
    first = tile.decide([0], batch_of(0.2, 0, 16))
    assert first.verdict.tolist() == [-1] and np.isfinite(first.evidence).all()
    sums = np.array([[16 * first.evidence[0], 16.0, 16.0]])
    quiet = batch_of(0.002, 1, 64)
    assert block.decide([0], quiet).verdict.tolist() == [1] and block.decide([0], quiet).evidence is None
    quiet.evidence = sums
    later = tile.decide([0], quiet)
    assert later.verdict.tolist() == [-1] and later.ratio[0] > 1          # the history remembers
    assert tile.decide([0], batch_of(0.002, 1, 64)).verdict.tolist() == [1]   # a unit without history: its level


def test_each_units_last_decided_spp_comes_from_the_verdict_history() -> None:
    """What a resumed loop's next weight counts from and what a checkpoint's weights may sum
    to: the unit's spp at its last nonzero verdict, 0 without one (an empty history too)."""
    from learning.inputs.history import last_decided_spp

    verdicts = np.array([[-1, 0, 0], [0, -1, 0], [1, 0, 0]], np.int8)
    spp = np.array([[16, 16, 16], [32, 32, 16], [48, 32, 16]])
    assert last_decided_spp(verdicts, spp).tolist() == [48, 32, 0]
    assert last_decided_spp(np.zeros((0, 3), np.int8), np.zeros((0, 3), np.int64)).tolist() == [0, 0, 0]
