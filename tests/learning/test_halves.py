"""The training-free flip criterion: FLIP between the half buffers, its calibration, extremes."""
from __future__ import annotations

import json

import numpy as np
import pytest

from noisefeat.dots import OBSERVER_DOTS

from learning import make_synthetic_stack
from learning.evaluation.calibrate import calibrate_flip, calibrate_flip_curve, flip_sweep
from learning.inputs.halves import (flip_c, flip_offset, flip_tau_range, halves_flip, load_flip_calibration,
                                    stack_flip_errors)
from learning.stoprule import StopRule
from renderer.criteria import UnitView, FlipCriterion, make_criterion
from renderer.spec import resolve

SPP = [8 * (k + 1) for k in range(12)]


def halves(level=0.3, noise=0.0, seed=0, size=16):
    rng = np.random.default_rng(seed)
    a = level + noise * rng.standard_normal((size, size, 3))
    b = level + noise * rng.standard_normal((size, size, 3))
    return a, b


def view(a, b, spp=(8, 8)):
    return UnitView(mean=(a + b) / 2, spp=sum(spp), halves=(a, b), half_spp=spp)


def test_flip_between_halves_grows_with_the_noise():
    e = [halves_flip(*[x[None] for x in halves(noise=s)])[0] for s in (0.0, 0.005, 0.02, 0.08)]
    assert e[0] == 0.0 and e == sorted(e) and e[-1] > 0.05


def test_flip_at_the_extremes_is_finite():
    a, b = halves(noise=0.05)
    fire = b.copy()
    fire[2, 2] = 1e6
    nan = b.copy()
    nan[1, 1] = [np.nan, np.inf, -np.inf]
    cases = {"black": (np.zeros_like(a), np.zeros_like(a)), "constant": (np.full_like(a, 0.4), np.full_like(a, 0.4)),
             "fireflies": (a, fire), "nan/inf": (a, nan), "tiny": (a * 1e-30, b * 1e-30),
             "huge": (a * 1e30, b * 1e30)}
    e = halves_flip(np.stack([x for x, _ in cases.values()]), np.stack([y for _, y in cases.values()]))
    got = dict(zip(cases, e.tolist()))
    assert all(np.isfinite(v) and 0 <= v <= 1 for v in got.values())
    assert got["black"] == got["constant"] == got["tiny"] == got["huge"] == 0.0   # nothing to see
    assert got["fireflies"] > got["black"]
    with pytest.raises(ValueError, match="one shape"):
        halves_flip(np.zeros((1, 8, 8, 3)), np.zeros((2, 8, 8, 3)))
    with pytest.raises(ValueError, match="exposure"):
        halves_flip(np.zeros((1, 8, 8, 3)), np.zeros((1, 8, 8, 3)), exposure=np.inf)


def test_c_means_at_most_c_exactly():
    for c in (0.0, 0.02, 0.0300001):
        rule = StopRule(flip_offset(c))
        assert rule.verdict(np.array([-c, -np.nextafter(c, 1.0), -np.nextafter(c, 0.0)])).tolist() == [1, -1, 1]
    for bad in (-0.01, np.nan, np.inf):
        with pytest.raises(ValueError, match="non-negative"):
            flip_offset(bad)


def test_flip_criterion_decisions():
    crit = FlipCriterion(0.02)
    quiet, loud = halves(noise=0.002), halves(noise=0.1, seed=1)       # e 0.014 and ~0.3
    flat = (np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.5))
    one_pass = halves(noise=0.01, seed=2)
    d = crit.decide([0, 1, 2, 3], [view(*quiet), view(*loud), view(*flat, spp=(8, 0)),
                                    view(*one_pass, spp=(8, 0))])
    assert d.verdict.tolist() == [1, -1, 1, -1]          # one pass: no noise estimate yet, unless flat
    assert d.counts["flat_units"] == 1 and d.counts["units_featured"] == 2
    assert crit.describe() == {"name": "flip", "threshold": 0.02, "tau": 0.02, "pooling": "tile8-max",
                               "source": "argument", "unit": "block", "statistic": "last"}
    with pytest.raises(ValueError, match="half buffers"):
        crit.decide([0], [UnitView(mean=quiet[0], spp=8)]).verdict
    def flip(**given):
        return make_criterion(resolve({"criterion": "flip", "tile": 64, **given}))      # whole 64-px blocks

    shipped = flip()
    assert isinstance(shipped, FlipCriterion) and shipped.c == flip_c(load_flip_calibration(), 0.02)
    # per 16-px tile (the render's default): the curve calibrated against the tile truth
    from learning.inputs.halves import unit_calibration

    per_tile = make_criterion(resolve({"criterion": "flip"}))
    assert per_tile.unit == "tile16" and per_tile.c == flip_c(unit_calibration(load_flip_calibration(), 16), 0.02)
    assert per_tile.c < shipped.c
    assert flip(threshold=0.05).c == 0.05
    assert flip(tau=0.01).c < shipped.c < flip(tau=0.04).c


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    root = tmp_path_factory.mktemp("halves")
    return [make_synthetic_stack(root / f"s{i}", size=64, spp=SPP, seed=i) for i in range(2)]


def test_stack_errors_are_cached_and_calibration_meets_its_target(stacks):
    st = stacks[0]
    e = stack_flip_errors(st)
    assert e.shape == (len(SPP), 16) and np.isnan(e[0]).all() and np.isfinite(e[1:]).all()
    assert list((st.path / ".cache").glob("flip-halves-*.npz"))
    np.testing.assert_array_equal(stack_flip_errors(st), e)
    # a block's noise falls with its samples: its halves' FLIP falls too, on the whole
    assert (np.nanmean(e[-1]) < np.nanmean(e[1]))
    curve = flip_sweep(stacks, (0.005, 0.02, 0.05, 0.2))
    early = [r["early_stop_rate"] for r in curve]
    assert early == sorted(early)                     # a larger c never stops later
    for target in (0.0, 0.1, 0.3):
        cal = calibrate_flip(stacks, target, candidates=(0.005, 0.02, 0.05, 0.2), progress=False)
        ok = [r for r in curve if r["early_stop_rate"] <= target]
        if ok:
            assert cal["c"] == max(r["threshold"] for r in ok) and cal["chosen"]["early_stop_rate"] <= target
        assert set(cal["per_scene"]) == {"synthetic"} or len(cal["per_scene"]) == 1
    with pytest.raises(ValueError, match="no stacks"):
        calibrate_flip([])


def _curve(points, pooling="tile8-max", observer="tile16-max+dots"):
    return {"format": "noisestop-flip-curve", "pooling": pooling, "observer_pooling": observer,
            "observer_dots": OBSERVER_DOTS,
            "curve": [{"tau": t, "c": c} for t, c in points]}


def test_a_calibration_file_is_read_and_checked(tmp_path):
    p = tmp_path / "flip.json"
    p.write_text(json.dumps(_curve([(0.01, 0.02), (0.04, 0.08)])))
    cal = load_flip_calibration(p)
    assert flip_c(cal, 0.01) == pytest.approx(0.02) and flip_c(cal, 0.04) == pytest.approx(0.08)
    assert flip_c(cal, 0.02) == pytest.approx(0.04)              # a power law between points
    assert flip_tau_range(cal) == (0.01, 0.04)
    for bad in (0.009, 0.05, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"outside the calibrated range \[0.01, 0.04\]"):
            flip_c(cal, bad)
    p.write_text(json.dumps({"c": 0.03}))                       # a block-mean calibration (observer v1)
    with pytest.raises(ValueError, match="recalibrate"):
        load_flip_calibration(p)
    p.write_text(json.dumps(_curve([(0.01, 0.02)], pooling="mean")))
    with pytest.raises(ValueError, match="recalibrate"):
        load_flip_calibration(p)
    p.write_text(json.dumps(_curve([(0.01, 0.02)], observer="tile16-max")))    # observer version 2
    with pytest.raises(ValueError, match="observer pooling 'tile16-max'.*recalibrate"):
        load_flip_calibration(p)
    p.write_text(json.dumps(_curve([(0.01, -1)])))
    with pytest.raises(ValueError, match="non-negative"):
        load_flip_calibration(p)
    p.write_text(json.dumps(_curve([(0.02, 0.03), (0.01, 0.02)])))
    with pytest.raises(ValueError, match="increasing"):
        load_flip_calibration(p)
    p.write_text("{")
    with pytest.raises(ValueError, match="unreadable"):
        load_flip_calibration(p)
    with pytest.raises(FileNotFoundError):
        load_flip_calibration(tmp_path / "none.json")


def test_the_shipped_curve_covers_the_documented_noise_targets():
    cal = load_flip_calibration()
    lo, hi = flip_tau_range(cal)
    assert lo <= 0.01 and hi >= 0.05
    cs = [flip_c(cal, t) for t in (0.01, 0.015, 0.02, 0.03, 0.04, 0.05)]
    assert cs == sorted(cs) and cs[0] > 0                        # a stricter target never a larger c
    for point in cal["curve"]:                                   # each met its target out of fold
        assert point["chosen"]["out_of_fold"]["early_stop_rate"] <= cal["target_early_stop_rate"] + 1e-9


def test_c_of_tau_calibration_relabels_and_keeps_a_monotone_curve(stacks):
    cal = calibrate_flip_curve(stacks, 0.1, taus=(0.01, 0.02, 0.04), candidates=(0.005, 0.02, 0.05, 0.2),
                               progress=False)
    cs = [p["c"] for p in cal["curve"]]
    assert [p["tau"] for p in cal["curve"]] == [0.01, 0.02, 0.04] and cs == sorted(cs)
    assert all(p["c"] >= p["c_raw"] for p in cal["curve"]) and cal["c"] == cs[1]
    assert cal["pooling"] == "tile8-max" and cal["observer_pooling"] == "tile16-max+dots"
