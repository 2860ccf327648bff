"""learning: estimators, query strategy, Algorithm 1, metrics, CV, bundles, training."""
from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
import skops.io as sio

from learning.evaluation.evaluate import by_scene
from learning.evaluation.generalisation import default_test_scenes
from learning.evaluation.metrics import evaluate_verdicts, stack_counts, stop_thresholds
from learning.inputs.table import load_table
from learning.models import bundle_check
from learning.models.active import (ActiveSemiSupervised, SimulatedExpert, class_centres,
                                    label_changing_rate)
from learning.models.bundle import load_model, save_model
from learning.models.cv import select_hyperparameters
from learning.models.estimators import DSVM, SVM
from learning.models.query import MarginQuery, RandomQuery
from learning.training.train import train_model
from tests.support import FIXTURE_DATASET as FIXTURE



def toy(n=600, d=26, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, d))
    y = np.where(X[:, 0] + 0.5 * X[:, 1] ** 2 - 0.5 > 0, 1, -1)
    return X, y


# --- estimators --------------------------------------------------------------------
def test_dsvm_contract_and_offset():
    X, y = toy()
    m = DSVM().fit(X[:400], y[:400])
    f = m.decision_function(X[400:])
    assert f.shape == (200,) and np.isfinite(f).all()
    assert set(np.unique(m.predict(X))) <= {-1, 1}
    majority = max((y[400:] > 0).mean(), (y[400:] < 0).mean())
    # 24 of the 26 dimensions are pure noise: well above the majority class is the test
    assert (m.predict(X[400:]) == y[400:]).mean() > majority + 0.15
    assert m.offset_ == 0.0 and "offset" not in m.get_params()     # fitted, not a parameter
    hi = DSVM().fit(X[:400], y[:400])
    hi.offset_ = 1.0                                                 # what calibration sets
    assert (hi.predict(X) > 0).sum() < (m.predict(X) > 0).sum()   # a larger offset stops later
    np.testing.assert_array_equal(hi.predict(X), np.where(hi.decision_function(X) > 1.0, 1, -1))
    assert m.n_support_ > 0 and m.n_parameters() > m.n_support_ * 26


def test_one_class_training_set_gives_constant_answers():
    X, _ = toy(50)
    m = DSVM().fit(X, np.ones(50, int))
    assert (m.predict(X) == 1).all() and (m.decision_function(X) == 1).all()


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_features_are_rejected(bad):
    X, y = toy(100)
    m = DSVM().fit(X, y)
    X2 = X.copy()
    X2[3, 5] = bad
    with pytest.raises(ValueError, match="NaN or Inf"):
        m.decision_function(X2)
    with pytest.raises(ValueError, match="NaN or Inf"):
        DSVM().fit(X2, y)


def test_bad_labels_shapes_and_params():
    X, y = toy(100)
    with pytest.raises(ValueError, match="-1 .* or \\+1"):
        DSVM().fit(X, np.where(y > 0, 1, 0))
    with pytest.raises(ValueError, match="expected 26 features"):
        DSVM().fit(X, y).decision_function(X[:, :5])
    with pytest.raises(ValueError, match="empty"):
        DSVM().fit(X[:0], y[:0])
    for C in (0.0, np.inf):
        with pytest.raises(ValueError, match="C must be"):
            DSVM(C=C).fit(X, y)


@pytest.mark.parametrize("C,gamma", [(1e-3, 1e-4), (1e-3, 1e3), (1e4, 1e-4), (1e4, 1e3)])
def test_extreme_c_and_gamma_stay_finite(C, gamma):
    X, y = toy(200)
    f = DSVM(C=C, gamma=gamma).fit(X, y).decision_function(X)
    assert np.isfinite(f).all()


def test_raw_svm_is_not_standardised():
    X, y = toy(100, d=64)
    assert SVM().fit(X, y).scaler_ is None and DSVM().fit(X, y).scaler_ is not None


# --- queries and Algorithm 1 --------------------------------------------------------
def test_margin_query_picks_the_smallest_margins_among_unlabelled():
    X, y = toy(300)
    y_part = np.full(300, np.nan)
    y_part[:100] = y[:100]
    clf = DSVM().fit(X[:100], y[:100])
    before = y_part.copy()
    idx = MarginQuery().query(X, y_part, clf, batch_size=10, fit_clf=False)
    np.testing.assert_array_equal(y_part, before)          # stateless
    assert len(idx) == 10 and (idx >= 100).all()
    margins = np.abs(clf.decision_function(X[100:]))
    assert np.abs(clf.decision_function(X[idx])).max() <= np.sort(margins)[9] + 1e-12
    assert len(RandomQuery().query(X, y_part, batch_size=10)) == 10


def test_label_changing_rate_and_class_centres():
    hist = np.array([[1, 1, -1], [1, -1, -1], [1, 1, -1]])
    np.testing.assert_allclose(label_changing_rate(hist), [0.0, 1.0, 0.0])
    f = np.array([-3.0, -2.0, -1.0, 0.5, 1.0, 4.0])
    stable = np.array([True, True, True, True, True, False])
    chosen = class_centres(f, stable, 1)
    assert set(chosen.tolist()) == {1, 3, 4} & set(chosen.tolist()) and len(chosen) == 2
    assert 1 in chosen                    # median |f| of the -1 class is 2.0


@pytest.mark.parametrize("semi", [True, False])
def test_algorithm_1_respects_the_label_budget(semi):
    X, y = toy(800)
    y0 = np.full(800, np.nan)
    y0[:80] = y[:80]
    expert = SimulatedExpert(y)
    m = ActiveSemiSupervised(semi_supervised=semi, batch_size=8, n_outer=3, n_inner=3,
                             max_label_fraction=0.1, patience=None).fit(X, y0, expert)
    assert m.n_queries_ == expert.asked <= int(0.1 * 720)
    assert (m.pseudo_mask_.sum() > 0) == semi
    assert (m.predict(X) == y).mean() > 0.8


def test_algorithm_1_rejects_a_bad_expert_and_no_initial_set():
    X, y = toy(200)
    y0 = np.full(200, np.nan)
    with pytest.raises(ValueError, match="initial labelled set"):
        ActiveSemiSupervised().fit(X, y0, SimulatedExpert(y))
    y0[:40] = y[:40]
    with pytest.raises(ValueError, match="-1 or \\+1"):
        ActiveSemiSupervised(n_outer=1).fit(X, y0, lambda idx: np.zeros(len(idx)))


# --- metrics -----------------------------------------------------------------------
def test_metrics_by_hand():
    spp = [10, 20, 30, 40]
    V = np.array([[-1, -1, 1], [1, -1, 1], [1, 1, 1], [1, 1, 1]])
    labels = np.array([[-1, -1, 1], [-1, -1, 1], [1, 1, 1], [1, 1, 1]])
    th = [30, None, 10]
    np.testing.assert_array_equal(stop_thresholds(V, spp), [20, 30, 10])
    c = stack_counts(V, labels, th, spp)
    assert (c["early"], c["spent"], c["oracle"], c["uniform"]) == (2, 60, 80, 120)
    m = evaluate_verdicts({"a": (V, labels, th, spp)})
    assert m["precision"] == pytest.approx(11 / 12)
    assert m["threshold_mse"] == pytest.approx(((20 - 30) ** 2 + (30 - 50) ** 2) / 40 ** 2 / 3)
    assert m["spp_ratio_vs_oracle"] == pytest.approx(0.75)
    assert m["saved_vs_uniform"] == pytest.approx(0.5)
    assert m["per_scene"]["a"]["early_stop_rate"] == pytest.approx(2 / 3)
    assert "early_block_rate" not in m
    # the same units as tiles, 3 a block, and again with one block of one tile each: blocks holding an early tile
    assert evaluate_verdicts({"a": (V, labels, th, spp)}, per_block=3)["early_block_rate"] == 1.0
    assert evaluate_verdicts({"a": (V, labels, th, spp)}, per_block={"a": 1})["early_block_rate"] == pytest.approx(2 / 3)


def test_never_converging_blocks_spend_spp_max():
    spp = [16, 32]
    V = -np.ones((2, 2), int)
    m = evaluate_verdicts({"s": (V, -np.ones((2, 2), int), [None, None], spp)})
    assert m["early_stop_rate"] == 0 and m["saved_vs_uniform"] == 0 and m["f1"] == 1.0


# --- cross-validation --------------------------------------------------------------
def test_grouped_cv_picks_from_the_grid():
    X, y = toy(300)
    groups = np.repeat(np.arange(30), 10)
    best = select_hyperparameters(DSVM(), X, y, groups, folds=3, c_grid=(1.0, 10.0),
                                  gamma_factors=(1.0,))
    assert best["C"] in (1.0, 10.0) and len(best["table"]) == 2 and best["cv_precision"] > 0.7
    same = select_hyperparameters(DSVM(C=3.0), X, y, np.zeros(300))
    assert same["C"] == 3.0 and same["cv_precision"] is None


# --- bundles -----------------------------------------------------------------------
def test_bundle_roundtrip(tmp_path):
    X, y = toy(200)
    est = DSVM().fit(X, y)
    est.offset_ = 0.25
    save_model(est, tmp_path / "m", kind="dsvm", input="features", training={"n": 200})
    model = load_model(tmp_path / "m")
    np.testing.assert_allclose(model.decision_function(X), est.decision_function(X))
    assert model.offset == 0.25 and model.manifest["training"]["n"] == 200
    assert model.manifest["feature_base"]["hash"]


def test_bundle_refuses_foreign_types_and_other_feature_bases(tmp_path):
    X, y = toy(100)
    save_model(DSVM().fit(X, y), tmp_path / "m", kind="dsvm", input="features")
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    manifest["feature_base"]["hash"] = "0000"
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="feature base"):
        load_model(tmp_path / "m")
    save_model(DSVM().fit(X, y), tmp_path / "evil", kind="dsvm", input="features")
    sio.dump({"payload": json.loads}, tmp_path / "evil" / "model.skops")   # a function inside
    with pytest.raises(ValueError, match="model_sha256"):                  # the file changed
        load_model(tmp_path / "evil")
    manifest = json.loads((tmp_path / "evil" / "manifest.json").read_text())
    del manifest["model_sha256"]                                            # the attacker edits both
    (tmp_path / "evil" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="unknown types"):
        load_model(tmp_path / "evil")
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "nothing")


def test_a_bundle_written_before_the_move_to_sub_packages_still_loads(tmp_path, monkeypatch):
    """The estimators live in learning.models; a bundle saved before that names
    learning.estimators in its skops schema and must load with the same decisions."""
    X, y = toy(200)
    save_model(DSVM().fit(X, y), tmp_path / "m", kind="dsvm", input="features")
    model_file = tmp_path / "m" / "model.skops"
    schema = zipfile.ZipFile(model_file).read("schema.json")
    assert b'"learning.models.estimators"' in schema
    old = tmp_path / "old.skops"
    with zipfile.ZipFile(model_file) as src, zipfile.ZipFile(old, "w") as dst:
        for info in src.infolist():
            raw = src.read(info)
            dst.writestr(info, raw.replace(b'"learning.models.estimators"', b'"learning.estimators"')
                         if info.filename == "schema.json" else raw)
    want = load_model(tmp_path / "m").decision_function(X)
    old.replace(model_file)
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    manifest["model_sha256"] = bundle_check.file_sha256(model_file)
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(manifest))
    np.testing.assert_array_equal(load_model(tmp_path / "m").decision_function(X), want)
    monkeypatch.setattr(bundle_check, "MOVED_MODULES", {})       # control: without the map it cannot load
    with pytest.raises(ValueError, match="skops"):
        load_model(tmp_path / "m")


# --- training on the fixture dataset -----------------------------------------------
@pytest.fixture(scope="module")
def table():
    return load_table(FIXTURE, progress=False)


def test_table_rows_and_groups(table):
    assert len(table) == 4 * 16 * 16 and table.X.shape[1] == 26
    assert len(np.unique(table.groups)) == 4 * 16
    v, labels = by_scene(table, table.y)["cornell"], table.stacks["cornell"].labels()
    assert v.shape == (16, 16) and (v == labels).all()
    flat = by_scene(table, table.flat)
    assert flat["sky"].all() and not flat["cornell"].any()   # the stop rule's flat blocks


@pytest.mark.parametrize("kind", ["dsvm", "dsvm_as", "svm_al"])
def test_training_holds_scenes_out(kind, table):
    est, summary = train_model(kind, str(FIXTURE), cv=kind == "dsvm", progress=False,
                               table=table if not kind.startswith("svm") else None)
    assert summary["test_scenes"] == default_test_scenes(table.scenes()) == ["cornell"]
    assert "cornell" not in summary["train_scenes"]
    if kind != "dsvm":
        assert summary["n_queries"] <= 0.25 * summary["n_pool"] + 1e-9
        assert set(summary["initial_scenes"]) <= set(summary["train_scenes"])
    assert np.isfinite(est.decision_function(
        np.zeros((1, est.n_features_in_)))).all()


# --- models trained without a quick image ('none': a flat quick image) ---------------------
def test_quick_none_model_uses_minus_the_current_features(tmp_path):
    from noisefeat import extract_features
    X, y = toy(200)
    save_model(DSVM().fit(X, y), tmp_path / "m", kind="dsvm", input="features", extra={"quick": "none"})
    model = load_model(tmp_path / "m")
    assert model.quick == "none" and not model.needs_quick
    rng = np.random.default_rng(1)
    blocks = rng.random((3, 16, 16, 3)).astype(np.float32)
    np.testing.assert_allclose(model.inputs_from_blocks(blocks), -extract_features(blocks))
    flat = np.full((2, 16, 16, 3), 0.4, np.float32)     # what 'none' stands for
    np.testing.assert_array_equal(extract_features(flat), np.zeros((2, 26), np.float32))
    verdict, score = model.score_blocks(blocks)          # no quick image needed
    assert verdict.shape == (3,) and np.isfinite(score).all()
    albedo = load_model(tmp_path / "m")
    albedo.manifest["quick"] = "albedo"
    with pytest.raises(ValueError, match="quick image"):
        albedo.score_blocks(blocks)


def test_table_quick_modes_differ_by_the_quick_features(table):
    none = load_table(FIXTURE, progress=False, quick="none")
    st = table.stacks["cornell"]
    from noisefeat import extract_features
    q = extract_features(st.split(st.quick()))
    m = table.scene == "cornell"
    np.testing.assert_allclose(table.X[m] - none.X[m], np.tile(q, (st.n_levels, 1)), atol=1e-4)
    direct = load_table(FIXTURE, progress=False, quick="direct")
    qd = extract_features(st.split(st.quick("direct")))
    np.testing.assert_allclose(direct.X[m] - none.X[m], np.tile(qd, (st.n_levels, 1)), atol=1e-4)
    assert not np.allclose(qd, q, atol=1e-2)     # a different picture: shading and shadows
    with pytest.raises(ValueError, match="quick must be"):
        load_table(FIXTURE, progress=False, quick="normals")
