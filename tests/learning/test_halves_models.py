"""Models on the `halves` input: tables of every kind, bundles that read half buffers, the
initial labelled set and cross-validation groups of one-block stacks, and the train
command's input options."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learning.models.bundle import Model, load_model, save_model
from learning.models.estimators import DSVM, SVM
from learning.inputs.noise_input import HALVES, n_inputs, noise_lightness
from learning.inputs.table import load_table
from learning.training.train import cv_groups, initial_scenes, train_model
from tests.support import FIXTURE_DATASET as FIXTURE



@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """A private copy of the fixture dataset: half-buffer caches are written next to it."""
    root = tmp_path_factory.mktemp("halves-data") / "dataset"
    shutil.copytree(FIXTURE, root, ignore=shutil.ignore_patterns(".cache"))
    return root


def test_feature_and_raw_tables_read_the_half_buffers(data):
    feats = load_table(data, progress=False, quick="halves", composition="n+c+l")
    raw = load_table(data, progress=False, raw=True, quick="halves")
    plain = load_table(data, progress=False, raw=True)
    assert feats.X.shape == (len(plain), n_inputs("n+c+l"))
    assert raw.X.shape == plain.X.shape                 # one noise pixel per block pixel
    # the first level has one pass only: no odd half, so no input there, in both tables
    for t in (feats, raw):
        np.testing.assert_array_equal(t.decidable, t.level > 0)
        assert len(t.trainable()) == int((t.level > 0).sum())
    assert not np.allclose(raw.X[raw.level > 0], plain.X[raw.level > 0])
    # the noise image is centred on zero, the block is not
    assert abs(raw.X[raw.level > 0].mean()) < 0.05 < plain.X.mean()
    # another composition of the same cached features: its columns are a re-arrangement
    n_only = load_table(data, progress=False, quick="halves", composition="n")
    np.testing.assert_array_equal(n_only.X, feats.X[:, :n_inputs("n")])


def test_a_raw_halves_bundle_scores_half_buffers(data, tmp_path):
    table = load_table(data, progress=False, raw=True, quick="halves").trainable()
    est = SVM(C=10.0).fit(table.X, table.y.astype(int))
    path = save_model(est, tmp_path / "raw", kind="svm", input="raw", extra={"quick": "halves"})
    model = load_model(path)
    assert model.needs_halves and not model.needs_quick and model.composition is None
    assert "composition" not in model.manifest
    rng = np.random.default_rng(0)
    a = rng.random((3, 16, 16, 3)).astype(np.float32)
    b = (a * 0.8).astype(np.float32)
    verdict, score = model.score_halves(a, b)
    np.testing.assert_allclose(score, est.decision_function(noise_lightness(a, b)))
    assert verdict.dtype == np.int8 and set(verdict.tolist()) <= {-1, 1}
    with pytest.raises(ValueError, match="16x16 blocks"):
        model.score_halves(a[:, :8, :8], b[:, :8, :8])
    with pytest.raises(ValueError, match="half buffers"):
        model.score_blocks(a)
    assert model.table_options() == {"raw": True, "quick": "halves"}


def test_a_feature_bundle_keeps_its_composition(data, tmp_path):
    table = load_table(data, progress=False, quick="halves", composition="n+l").trainable()
    est = DSVM().fit(table.X, table.y.astype(int))
    model = load_model(save_model(est, tmp_path / "m", kind="dsvm", input="features",
                                  extra={"quick": "halves", "composition": "n+l"}))
    assert model.composition == "n+l" and model.table_options() == {
        "raw": False, "quick": "halves", "composition": "n+l"}
    again = load_table(data, progress=False, **model.table_options())
    np.testing.assert_allclose(model.decision_function(again.X), est.decision_function(again.X))
    # a bundle whose composition does not match its fitted width is refused
    bad = load_model(save_model(est, tmp_path / "bad", kind="dsvm", input="features",
                                extra={"quick": "halves", "composition": "n+l"}))
    manifest = (bad.path / "manifest.json")
    manifest.write_text(manifest.read_text().replace('"n+l"', '"n+c+l"'))
    with pytest.raises(ValueError, match="columns"):
        load_model(bad.path)
    # a plain Model without a composition reads the default one
    assert Model(est, {"kind": "dsvm", "input": "features", "quick": "halves"}).composition == HALVES


def test_initial_set_and_cv_groups_of_one_block_stacks(data):
    table = load_table(data, progress=False, quick="none")
    scenes = table.scenes()
    one = initial_scenes(table, scenes, min_rows=1)
    assert len(one) == 1
    many = initial_scenes(table, scenes, min_rows=int(table.scene_mask(scenes).sum()))
    assert sorted(many) == sorted(scenes)                 # as many scenes as the rows need
    mid = initial_scenes(table, scenes, min_rows=300)
    rows = table.scene_mask(mid)
    assert rows.sum() >= 300 and len(np.unique(table.y[rows])) == 2
    # under 5 scenes: the paper's groups (one image level); else one group per scene
    idx = np.arange(len(table))
    np.testing.assert_array_equal(cv_groups(table, idx, folds=5), table.groups)
    g = cv_groups(table, idx, folds=2)
    assert len(np.unique(g)) == len(scenes)
    for s in scenes:
        assert len(np.unique(g[table.scene == s])) == 1


def test_active_training_on_halves_names_its_initial_scenes(data):
    table = load_table(data, progress=False, quick="halves")
    est, summary = train_model("dsvm_al", str(data), table=table, test_scenes=["sky"], cv=False,
                               quick="halves", progress=False, initial_scene="cornell,checker")
    assert summary["initial_scenes"] == ["cornell", "checker"] and summary["quick"] == "halves"
    assert est.n_features_in_ == n_inputs(HALVES)
    with pytest.raises(ValueError, match="initial scene"):
        train_model("dsvm_al", str(data), table=table, test_scenes=["sky"], cv=False, quick="halves",
                    progress=False, initial_scene="sky")


@pytest.mark.parametrize("args, message", [
    (["--input", "albedo", "--composition", "n"], "--composition applies"),
    (["--input", "halves", "--composition", "n+x"], "unknown input composition"),
])
def test_train_refuses_bad_input_options_in_one_line(data, tmp_path, args, message):
    out = subprocess.run([sys.executable, "-m", "service.cli", "train", "--data", str(data), "--model", "dsvm",
                          "--out", str(tmp_path / "m"), "--no-cv", *args], capture_output=True, text=True)
    assert out.returncode == 2
    assert message in out.stderr and "Traceback" not in out.stderr
