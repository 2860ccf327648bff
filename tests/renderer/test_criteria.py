"""Stopping criteria: the Cycles rule exactly, oracle/uniform, the model path, counters, NaN safety."""
from __future__ import annotations

import numpy as np
import pytest

from learning import make_synthetic_stack
from learning.models.bundle import load_model, save_model
from learning.models.estimators import DSVM
from learning.inputs.table import stack_features
from noisefeat.display import display_range
from renderer.criteria import (UnitView, ModelCriterion, OracleCriterion, UniformCriterion,
                               VarianceCriterion, make_criterion)
from renderer.spec import resolve


def train_model(tmp_path):
    """A real DSVM bundle trained on a labelled synthetic stack (there is no bundled model yet)."""
    st = make_synthetic_stack(tmp_path / "train", size=64, seed=3)
    x = stack_features(st)
    est = DSVM(C=10.0).fit(x.reshape(-1, x.shape[-1]), st.labels().reshape(-1))
    return load_model(save_model(est, tmp_path / "model", kind="dsvm", input="features")), st


@pytest.fixture(scope="module")
def model_and_stack(tmp_path_factory):
    return train_model(tmp_path_factory.mktemp("model"))


def view(mean, a=None, half_spp=(8, 8), spp=16, quick=None):
    mean = np.asarray(mean, np.float64)
    a = mean if a is None else np.asarray(a, np.float64)
    with np.errstate(invalid="ignore"):
        b = 2 * mean - a
    return UnitView(mean=mean, spp=spp, halves=(a, b), half_spp=half_spp, quick=quick)


def noisy_block(seed=0, level=0.3, shape=(8, 8)):
    rng = np.random.default_rng(seed)
    return level + 0.2 * rng.random((*shape, 3))


# ----------------------------------------------------------------------------- variance


def test_pixel_error_is_cycles_formula_both_branches():
    c = VarianceCriterion(0.01)
    i = np.array([[[0.1, 0.2, 0.3], [1.0, 2.0, 3.0]]])       # intensity 0.6 (< 1) and 6 (>= 1)
    a = i + np.array([[[0.01, -0.02, 0.0], [0.3, 0.0, -0.3]]])
    err = c.pixel_error(i, a)
    assert err.shape == (1, 2)
    assert err[0, 0] == pytest.approx(0.03 / (1e-4 + np.sqrt(0.6)), rel=1e-12)
    assert err[0, 1] == pytest.approx(0.6 / (1e-4 + 6.0), rel=1e-12)


def test_threshold_boundary_and_scale():
    i = np.full((4, 4, 3), 0.25)                              # intensity 0.75, norm sqrt(0.75)
    a = i.copy()
    a[..., 0] += 0.0087                                       # error ~ 0.0087/0.866 = 0.01004
    err = 0.0087 / (1e-4 + np.sqrt(0.75))
    assert VarianceCriterion(err * 1.001, flat_shortcut=False).decide([0], [view(i, a)]).verdict[0] == 1
    assert VarianceCriterion(err * 0.999, flat_shortcut=False).decide([0], [view(i, a)]).verdict[0] == -1
    # a scale of 5 (REFERENCES.md's reading) loosens the same test five-fold
    assert VarianceCriterion(err / 4.9, scale=5.0, flat_shortcut=False).decide([0], [view(i, a)]).verdict[0] == 1


def test_all_pixels_by_default_quantile_optional():
    i = np.full((10, 10, 3), 0.25)
    i[:, :5] = 0.3                                             # not flat: no shortcut
    a = i.copy()
    a[0, 0, 0] += 0.5                                          # one bad pixel of 100
    assert VarianceCriterion(0.01).decide([0], [view(i, a)]).verdict[0] == -1
    assert VarianceCriterion(0.01, quantile=0.99).decide([0], [view(i, a)]).verdict[0] == 1
    a[0, 1, 0] += 0.5                                          # two bad pixels: 98 % pass
    assert VarianceCriterion(0.01, quantile=0.99).decide([0], [view(i, a)]).verdict[0] == -1


def test_one_pass_has_no_noise_estimate():
    i = noisy_block()
    v = view(i, i, half_spp=(16, 0))                          # A == I after one pass
    assert VarianceCriterion(1.0).decide([0], [v]).verdict[0] == -1
    assert VarianceCriterion(1.0).decide([0], [view(i, i, half_spp=(8, 8))]).verdict[0] == 1


def test_flat_blocks_are_converged_without_halves():
    c = VarianceCriterion(0.01)
    black = np.zeros((8, 8, 3))
    sky = np.full((8, 8, 3), 0.5)
    d = c.decide([0, 1], [view(black, half_spp=(16, 0)), view(sky, half_spp=(16, 0))])
    assert d.verdict.tolist() == [1, 1] and d.ratio.tolist() == [0.0, 0.0]
    assert d.counts["flat_units"] == 2
    assert display_range(sky[None])[0] == 0.0 and display_range(noisy_block()[None])[0] > 0.1
    off = VarianceCriterion(0.01, flat_shortcut=False)
    assert off.decide([0], [view(black, half_spp=(16, 0))]).verdict[0] == -1


def test_nonfinite_pixels_never_give_nan_decisions():
    i = noisy_block()
    i[0, 0] = [np.nan, np.inf, -np.inf]
    a = i.copy()
    a[1, 1, 0] = np.nan
    c = VarianceCriterion(0.05)
    err = c.pixel_error(i, a)
    assert np.isfinite(err).all()
    d = c.decide([3], [view(i, a)])
    # a pixel with no finite estimate holds the block noisy, its ratio "no estimate"
    assert d.verdict.dtype == np.int8 and d.verdict.tolist() == [-1] and np.isnan(d.ratio).all()
    assert d.counts["nonfinite_units"] == 1


# ----------------------------------------------------------------------------- oracle, uniform


def test_oracle_and_uniform():
    o = OracleCriterion([32, None, 16])
    views = [view(noisy_block(), spp=32)] * 3
    assert o.decide([0, 1, 2], views).verdict.tolist() == [1, -1, 1]
    assert o.decide([0, 2], [view(noisy_block(), spp=16)] * 2).verdict.tolist() == [-1, 1]
    with pytest.raises(ValueError, match="out of range"):
        o.decide([5], views[:1]).verdict
    with pytest.raises(ValueError, match="positive integer"):
        OracleCriterion([0])
    u = UniformCriterion()
    d = u.decide([0, 1], views[:2])
    assert d.verdict.tolist() == [-1, -1]
    assert d.counts["units_asked"] == 2 and d.counts["decide_calls"] == 1


def test_bad_input_is_a_clear_error():
    c = VarianceCriterion()
    with pytest.raises(ValueError, match="2 block ids but 1 views"):
        c.decide([0, 1], [view(noisy_block())]).verdict
    with pytest.raises(ValueError, match="half buffers"):
        c.decide([0], [UnitView(mean=noisy_block(), spp=4)]).verdict
    with pytest.raises(ValueError, match="oracle criterion needs true thresholds"):
        resolve({"criterion": "oracle"})                  # the render spec's check, by the declaration
    with pytest.raises(ValueError, match="thresholds must be a sequence"):
        make_criterion(resolve({"criterion": "oracle"}, thresholds_known=True))   # a caller that said so wrongly
    with pytest.raises(ValueError, match="criterion must be one of .* got 'magic'"):
        resolve({"criterion": "magic"})
    with pytest.raises(ValueError, match="threshold"):
        VarianceCriterion(-1.0)
    assert c.decide([], []).verdict.shape == (0,)


# ----------------------------------------------------------------------------- model


def test_model_criterion_matches_score_blocks(model_and_stack):
    model, st = model_and_stack
    crit = ModelCriterion(model)
    assert crit.needs_quick
    quick = st.split(st.quick())
    ids = list(range(st.n_blocks))
    for k in (0, st.n_levels - 1):
        blocks = st.blocks(k)
        expected, _ = model.score_blocks(blocks, quick)
        d = crit.decide(ids, [UnitView(mean=blocks[b], spp=st.spp[k], quick=quick[b]) for b in ids])
        assert d.verdict.tolist() == expected.tolist()
        # 16 current rows + 16 quick rows (views carry raw quick blocks; the loop prepares them once)
        assert d.counts["units_featured"] == 16 and d.counts["feature_rows"] == 32
        assert d.counts["units_asked"] == 16
        assert d.timers["features_s"] > 0 and d.timers["decisions_s"] > 0
    assert set(expected.tolist()) <= {-1, 1}


def test_model_criterion_skips_flat_blocks(model_and_stack):
    model, st = model_and_stack
    crit = ModelCriterion(model)
    quick = st.split(st.quick())
    flat = np.zeros_like(quick[0])
    d = crit.decide([0, 1], [UnitView(mean=flat, spp=4, quick=quick[0]),
                             UnitView(mean=st.blocks(0)[1], spp=4, quick=quick[1])])
    assert d.verdict[0] == 1
    assert d.counts["flat_units"] == 1 and d.counts["units_featured"] == 1
    with pytest.raises(ValueError, match="needs the quick image"):
        crit.decide([0], [UnitView(mean=st.blocks(0)[0], spp=4)]).verdict


def test_model_criterion_uses_any_scorer():
    class Fake:
        input = "features"

        def __init__(self):
            self.calls = []

        def score_blocks(self, blocks, quick=None, exposure=0.0, offset=None):
            self.calls.append((blocks.shape, None if quick is None else quick.shape, exposure, offset))
            v = np.where(blocks.mean(axis=(1, 2, 3)) > 0.35, 1, -1).astype(np.int8)
            return v, v.astype(float)

    fake = Fake()
    crit = ModelCriterion(fake)
    views = [UnitView(mean=noisy_block(level=lv), spp=8, quick=np.ones((8, 8, 3))) for lv in (0.1, 0.5)]
    assert crit.decide([4, 7], views).verdict.tolist() == [-1, 1]
    assert fake.calls == [((2, 8, 8, 3), (2, 8, 8, 3), 0.0, None)]
    assert crit.describe()["model"] == {"type": "Fake"}
    # a remote scorer gets the display exposure and the user's offset with every call
    ModelCriterion(fake, exposure=1.5, offset=0.7).decide([4], views[:1]).verdict
    assert fake.calls[-1] == ((1, 8, 8, 3), (1, 8, 8, 3), 1.5, 0.7)


def test_model_criterion_without_quick_image(tmp_path):
    """A model trained with quick 'none' decides from the current blocks alone."""
    from learning.models.bundle import load_model, save_model
    from learning.models.estimators import DSVM
    from renderer.criteria import UnitView, ModelCriterion
    rng = np.random.default_rng(0)
    X = rng.normal(size=(120, 26))
    y = np.where(X[:, 0] > 0, 1, -1)
    save_model(DSVM().fit(X, y), tmp_path / "m", kind="dsvm", input="features", extra={"quick": "none"})
    crit = ModelCriterion(load_model(tmp_path / "m"))
    assert not crit.needs_quick
    views = [UnitView(mean=rng.random((16, 16, 3)).astype(np.float32), spp=16) for _ in range(3)]
    out = crit.decide([0, 1, 2], views).verdict
    assert out.shape == (3,) and set(out.tolist()) <= {-1, 1}


# ----------------------------------------------------------------------------- configuration only


def test_a_criterion_is_configuration_only_and_the_loop_keeps_the_render(model_and_stack):
    """A render changes nothing in its criterion (no counters, ratios or caches
    there), so one object judges any number of renders alike; the loop counts, and prepares
    the quick image's features once per render (16 quick rows, then one row per block asked)."""
    from renderer.criteria import FlipCriterion
    from renderer.simulation.simulate import simulate_loop

    model, st = model_and_stack
    for crit in (ModelCriterion(model), VarianceCriterion(0.08), FlipCriterion(0.05), OracleCriterion(st.thresholds)):
        before = repr(sorted(vars(crit).items()))
        first, loop = simulate_loop(st, crit, min_spp=8)
        second, again = simulate_loop(st, crit, min_spp=8)
        assert repr(sorted(vars(crit).items())) == before, crit.name
        np.testing.assert_array_equal(first, second)
        assert loop.ledger.counters == again.ledger.counters and loop.ledger.counters["units_asked"] > 0
        assert not hasattr(crit, "counters") and not hasattr(crit, "ratios")
        if crit.name == "model":
            assert loop.ledger.counters["feature_rows"] == st.n_blocks + loop.ledger.counters["units_featured"]
        asked, ratio = loop.ratios.take(np.arange(st.n_blocks))
        assert asked.all() and not np.isnan(ratio[asked & np.isfinite(ratio)]).any()
