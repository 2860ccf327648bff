"""The learned stop: per-tile content terms, the error estimator, its bundle, its
out-of-fold calibration, and the `estimate` criterion deciding on what it was trained on."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from learning.inputs.tile_features import FEATURE_NAMES, target, tile_features
from learning.inputs.tile_stats import STAT_NAMES, tile_stats
from learning.models.tile_error import TileErrorEstimator
from noisefeat.pooling import tile_windows
from tests.learning.test_tile_truth import _noisy_stack

WINDOWS = tile_windows(32, 32, 16)
COL = {n: i for i, n in enumerate(STAT_NAMES)}
#: noise amplitudes of the synthetic stacks' tiles: most converge inside the stack, at different levels
AMPLITUDE = (0.003, 0.03)


def _halves(kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(1)
    base = rng.uniform(0.1, 0.6, (2, 32, 32, 3))
    a, b = base + 0.02 * rng.standard_normal(base.shape), base + 0.02 * rng.standard_normal(base.shape)
    if kind == "black":
        a, b = np.zeros_like(a), np.zeros_like(b)
    elif kind == "constant":
        a = b = np.full_like(a, 0.5)
    elif kind == "fireflies":
        a[:, 3, 5] = 1e6
    elif kind == "nonfinite":
        a[0, 0, 0], a[0, 1, 1], b[1, 2, 2] = np.nan, np.inf, -np.inf
    elif kind == "tiny":
        a, b = a * 1e-30, b * 1e-30
    elif kind == "huge":
        a, b = a * 1e30, b * 1e30
    return torch.as_tensor(a, dtype=torch.float32), torch.as_tensor(b, dtype=torch.float32)


@pytest.mark.parametrize("kind", ["plain", "black", "constant", "fireflies", "nonfinite", "tiny", "huge"])
def test_tile_stats_are_finite_at_the_extremes(kind: str) -> None:
    a, b = _halves(kind)
    s = tile_stats(a, b, WINDOWS)
    assert s.shape == (2, 4, len(STAT_NAMES)) and bool(torch.isfinite(s).all())
    shares = s[..., [COL[c] for c in ("dark_share", "clipped_share", "outlier_share", "black_both_share",
                                      "black_one_share", "relative_difference", "tile_balance")]]
    assert bool(((shares >= 0) & (shares <= 1)).all())
    x = tile_features(np.full((2, 4), np.nan), np.full((2, 4), np.inf), np.zeros((2, 4)), np.full((2, 4), -1.0),
                      np.full((2, 4, 4), np.nan), s.numpy())
    assert x.shape == (2, 4, len(FEATURE_NAMES)) and np.isfinite(x).all()


def test_tile_stats_see_dark_black_and_disagreeing_pixels() -> None:
    """Known values: a black tile is all dark and black in both halves; one pixel black in
    one half only and white in the other is an outlier and a missing path, 1 of 256; a
    tile of halves that differ only by a 10 % gain has that balance."""
    a, b = _halves("black")
    a[0, 20, 20] = 1.0                       # tile 3 of block 0 (x 16-31, y 16-31)
    s = tile_stats(a, b, WINDOWS)
    assert s[1, :, COL["dark_share"]].tolist() == [1.0] * 4 and s[1, :, COL["black_both_share"]].tolist() == [1.0] * 4
    assert s[0, 3, COL["black_one_share"]] == pytest.approx(1 / 256)
    assert s[0, 3, COL["outlier_share"]] == pytest.approx(1 / 256)
    assert s[0, 0, COL["outlier_share"]] == 0.0
    c = torch.full((1, 32, 32, 3), 0.2)
    s = tile_stats(c * 1.1, c * 0.9, WINDOWS)
    assert s[0, :, COL["tile_balance"]].numpy() == pytest.approx([0.1] * 4)
    assert s[0, :, COL["relative_difference"]].numpy() == pytest.approx([0.1] * 4)
    assert s[0, :, COL["log_texture"]].numpy() == pytest.approx([-6.0] * 4)     # flat: at the floor


def test_the_target_is_the_log_ratio_and_nan_where_undefined() -> None:
    np.testing.assert_allclose(target(np.array([0.04, 0.0, np.nan, 0.02]), np.array([0.02, 0.1, 0.1, np.inf])),
                               [np.log(2), np.nan, np.nan, np.nan])


@pytest.mark.parametrize("kind", ["gbm", "linear"])
def test_the_estimator_learns_a_content_dependent_correction(kind: str) -> None:
    """y depends on the dark share: a constant correction leaves its spread, the estimator
    removes most of it (control: the spread of y itself)."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((3000, len(FEATURE_NAMES)))
    dark = len(FEATURE_NAMES) - len(STAT_NAMES) + COL["dark_share"]
    y = 0.6 * X[:, dark] + 0.03 * rng.standard_normal(3000)
    est = TileErrorEstimator(kind=kind, max_iter=200).fit(X[:2000], y[:2000])
    resid = y[2000:] - est.predict(X[2000:])
    assert np.std(y[2000:]) > 0.5 and np.std(resid) < 0.15
    np.testing.assert_allclose(est.estimate(X[2000:]), np.exp(X[2000:, 0] + est.predict(X[2000:])))


def test_the_estimator_refuses_bad_input() -> None:
    X, y = np.zeros((10, len(FEATURE_NAMES))), np.zeros(10)
    with pytest.raises(ValueError):
        TileErrorEstimator(kind="forest").fit(X, y)
    with pytest.raises(ValueError, match="NaN"):
        TileErrorEstimator().fit(np.where(np.eye(10, len(FEATURE_NAMES)) > 0, np.nan, X), y)
    with pytest.raises(ValueError, match="target"):
        TileErrorEstimator().fit(X, np.full(10, np.inf))
    with pytest.raises(ValueError, match="features"):
        TileErrorEstimator(kind="linear").fit(X, y).predict(np.zeros((2, 3)))


def _trained(tmp_path, n: int = 4):
    from learning.models.tile_error_bundle import load_tile_error_bundle, save_tile_error_bundle
    from learning.training.train_estimate import train_tile_error

    stacks = [_noisy_stack(tmp_path / f"s{i}", f"s{i}", i, AMPLITUDE) for i in range(n)]
    est, cal, rec = train_tile_error(stacks, params={"kind": "gbm", "max_iter": 30}, folds=None, taus=(0.015, 0.02),
                                     progress=False)
    save_tile_error_bundle(est, tmp_path / "bundle", tile=16, calibration=cal, training=rec)
    return stacks, est, cal, rec, load_tile_error_bundle(tmp_path / "bundle")


def test_training_calibrates_out_of_fold_and_the_bundle_round_trips(tmp_path) -> None:
    """Each scene's calibration estimates come from an estimator fit without it (bit for bit
    what a fit on the other scenes gives); the curve is checked and the bundle loads back
    the same estimator and c(tau)."""
    from learning.data.relabel import with_tile_truth
    from learning.inputs.tile_table import stack_tile_table
    from learning.training.train_estimate import estimates_of, out_of_fold_estimates, training_rows

    stacks, est, cal, rec, bundle = _trained(tmp_path)
    tables = {s.scene: stack_tile_table(with_tile_truth(s, 16), 16) for s in stacks}
    params = {"kind": "gbm", "max_iter": 30}
    oof = out_of_fold_estimates(tables, params, folds=None)
    alone = TileErrorEstimator(**params).fit(*training_rows([tables["s1"], tables["s2"], tables["s3"]]))
    np.testing.assert_array_equal(oof["s0"], estimates_of(alone, tables["s0"]))
    assert not np.allclose(np.nan_to_num(oof["s0"]), np.nan_to_num(estimates_of(est, tables["s0"])))
    assert [p["tau"] for p in cal["curve"]] == sorted(p["tau"] for p in cal["curve"]) and cal["unit"] == "tile16"
    assert rec["rows"] > 0 and np.isfinite(rec["out_of_fold_spread"]["estimate"])
    assert bundle.c(0.02) == pytest.approx(cal["c"]) and bundle.tile == 16
    X = tables["s0"].X.reshape(-1, len(FEATURE_NAMES))
    np.testing.assert_array_equal(bundle.estimator.predict(X), est.predict(X))


class Foreign:
    """A type no bundle may hold: skops must refuse to build it."""


def test_a_bundle_that_is_damaged_foreign_or_of_other_inputs_is_refused(tmp_path) -> None:
    import skops.io as sio
    from sklearn.linear_model import LinearRegression

    from learning.models.tile_error_bundle import load_tile_error_bundle, save_tile_error_bundle
    from noisefeat.errors import InputNotFound

    with pytest.raises(InputNotFound):
        load_tile_error_bundle(tmp_path / "none")
    est = TileErrorEstimator(kind="linear").fit(np.zeros((4, len(FEATURE_NAMES))), np.zeros(4))
    cal = {"curve": [{"tau": 0.01, "c": 0.01}, {"tau": 0.02, "c": 0.02}]}
    d = save_tile_error_bundle(est, tmp_path / "b", tile=16, calibration=cal, training={})
    first = load_tile_error_bundle(d)
    assert first.c(0.015) == pytest.approx(0.015)
    assert load_tile_error_bundle(d) is first               # read once per process while unchanged
    (d / "estimator.skops").write_bytes(sio.dumps(TileErrorEstimator(kind="linear", alpha=2.0).fit(
        np.zeros((4, len(FEATURE_NAMES))), np.zeros(4))))
    assert load_tile_error_bundle(d).estimator.alpha == 2.0  # a rewritten file is read again
    manifest = json.loads((d / "manifest.json").read_text())
    for broken, match in (({**manifest, "features": ["x"]}, "other inputs"), ({**manifest, "format": "x"}, "manifest"),
                          ({**manifest, "tile": 0}, "tile"),
                          ({**manifest, "calibration": {"curve": [{"tau": 0.02, "c": -1}]}}, "non-negative")):
        (d / "manifest.json").write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=match):
            load_tile_error_bundle(d)
    (d / "manifest.json").write_text(json.dumps(manifest))
    (d / "estimator.skops").write_bytes(sio.dumps(LinearRegression().fit(np.zeros((2, 1)), [0, 1])))
    with pytest.raises(ValueError, match="not a fitted TileErrorEstimator"):
        load_tile_error_bundle(d)
    (d / "estimator.skops").write_bytes(sio.dumps(Foreign()))
    with pytest.raises(ValueError, match="unknown types"):
        load_tile_error_bundle(d)
    (d / "estimator.skops").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(ValueError, match="unreadable"):
        load_tile_error_bundle(d)


def test_the_criterion_decides_on_the_rows_it_was_trained_on(tmp_path) -> None:
    """Simulated on a stack it was not trained on, every row the live criterion hands the
    estimator is a row of that stack's training table (same level, same numbers): what the
    estimate learns from is what the loop decides on. Its stops are those of its estimate
    against c, and a tile of another size is refused."""
    from learning.data.relabel import with_tile_truth
    from learning.inputs.tile_table import stack_tile_table
    from renderer.criteria.estimate import EstimateCriterion
    from renderer.simulation.simulate import simulate_loop

    stacks, _, _, _, bundle = _trained(tmp_path)
    held = _noisy_stack(tmp_path / "held", "held", 99, AMPLITUDE)
    table = stack_tile_table(with_tile_truth(held, 16), 16)
    seen: list[np.ndarray] = []
    real = bundle.estimator.estimate

    class Recording:
        kind = bundle.estimator.kind

        def estimate(self, X: np.ndarray) -> np.ndarray:
            seen.append(np.asarray(X).copy())
            return real(X)

    crit = EstimateCriterion(tau=0.02, tile=16, bundle=type(bundle)(Recording(), 16, bundle.calibration, "test"))
    verdicts, loop = simulate_loop(held, crit, tile=16, decide_skip=0.0, decide_growth=0.0)
    rows = np.concatenate(seen)
    # until a tile stops, every tile's block holds the stack's samples (after, a stopped
    # neighbour is context as it stopped, in the live loop as in the render)
    first_stop = int(np.argmax((verdicts == 1).any(axis=1)))
    level = np.array([int(np.argmin(np.abs(np.log(held.spp) - r[2]))) for r in rows])
    early = rows[level <= first_stop]
    assert first_stop >= 1 and len(early) >= 16
    for r, k in zip(early, level[level <= first_stop]):
        assert np.abs(table.X[k] - r).max(axis=1).min() < 1e-9
    assert (verdicts[-1] == 1).any() and loop.ledger.counters["feature_rows"] == len(rows)
    with pytest.raises(ValueError, match="16-px tile"):
        EstimateCriterion(tau=0.02, tile=8, bundle=bundle)


@pytest.mark.slow
def test_a_live_render_stops_tiles_on_the_learned_estimate(tmp_path) -> None:
    """The criterion in the live loop: a 64x64 render of 32-px blocks cut into 16-px tiles
    decides on the estimate, its report names it, and at a loose c tiles stop apart and before
    max spp; at c = 1e-6 nothing stops (control). A soft-lit scene, so that the dot guard (flip's)
    lets some tiles be judged by 48 spp."""
    from renderer.criteria.estimate import EstimateCriterion
    from renderer.live.adaptive import adaptive_render

    bundle = _trained(tmp_path)[-1]
    kw = {"resolution": 64, "block": 32, "tile": 16, "step": 4, "min_spp": 8, "max_spp": 48, "progress": False,
          "grow": False}
    loose = adaptive_render("large_light", tmp_path / "a", EstimateCriterion(c=0.2, tau=0.05, tile=16, bundle=bundle),
                            **kw)
    assert loose["criterion"]["name"] == "estimate" and loose["criterion"]["estimator"]["tile"] == 16
    spp = [t["spp"] for t in loose["tiles"]]
    assert len(spp) == 16 and min(spp) < 48
    strict = adaptive_render("large_light", tmp_path / "b", EstimateCriterion(c=1e-6, tau=0.05, tile=16, bundle=bundle),
                             **kw)
    assert all(t["spp"] == 48 for t in strict["tiles"])


def test_the_criterion_refuses_units_of_another_size_before_any_render() -> None:
    """From a render spec, whole 64-px blocks are refused when the criterion is built (not at
    its first decision, after a pass was paid for); 16-px tiles of them, or 16-px blocks, are
    its grain."""
    from renderer.criteria.estimate import EstimateCriterion
    from renderer.spec import resolve

    with pytest.raises(ValueError, match="got 64-px units"):
        EstimateCriterion.from_spec(resolve({"criterion": "estimate", "resolution": 128, "block": 64, "tile": 64}))
    for block in (64, 16):
        crit = EstimateCriterion.from_spec(resolve({"criterion": "estimate", "resolution": 128, "block": block,
                                                    "tile": 16}))
        assert crit.unit == "tile16"
