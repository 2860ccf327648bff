"""The precomputed Gram route of raw-pixel active learning gives the plain route's model."""
from __future__ import annotations

import copy

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.metrics.pairwise import rbf_kernel

import learning.models.gram as gram_mod
from learning.models.active import ActiveSemiSupervised, SimulatedExpert
from learning.models.estimators import SVM
from learning.models.gram import GramRBF, SharedGram, index_column
from learning.inputs.table import load_table
from learning.training.train import fit_kind
from tests.support import FIXTURE_DATASET as FIXTURE



def blobs(n=240, d=64, seed=0):
    rng = np.random.default_rng(seed)
    y = np.where(rng.random(n) < 0.5, -1, 1)
    X = rng.random((n, d)) * 0.6 + (y[:, None] > 0) * 0.25 + rng.normal(0, 0.05, (n, d))
    return X, y


def test_gram_matches_sklearn_rbf_and_is_shared_not_copied():
    X, _ = blobs(50, 4096)
    g = SharedGram(X, X[:30], gamma=1 / 4096)
    np.testing.assert_allclose(g.K, rbf_kernel(X, X[:30], gamma=1 / 4096), rtol=0, atol=1e-12)
    assert g.K.shape == (50, 30) and not g.K.flags.writeable
    assert copy.deepcopy(g) is g and clone(GramRBF(g)).gram is g


def test_decisions_match_the_plain_svm():
    X, y = blobs()
    gamma = 1.0 / X.shape[1]
    plain = SVM(C=10, gamma=gamma).fit(X[:160], y[:160])
    g = GramRBF(SharedGram(X, X[:160], gamma), C=10).fit(index_column(np.arange(160)), y[:160])
    np.testing.assert_allclose(g.decision_function(index_column(np.arange(240))),
                               plain.decision_function(X), atol=1e-6)
    one = GramRBF(g.gram).fit(index_column([0, 1]), np.array([1, 1]))
    assert (one.predict(index_column([5, 6])) == 1).all()


def test_active_learning_queries_the_same_samples_on_both_routes():
    X, y = blobs()
    gamma = 1.0 / X.shape[1]
    start = np.where(np.arange(len(y)) < 40, y, np.nan).astype(float)
    kw = dict(semi_supervised=True, n_outer=3, n_inner=3, batch_size=8, n_centres=4,
              max_label_fraction=0.4, patience=None)
    a = ActiveSemiSupervised(SVM(C=10, gamma=gamma), **kw).fit(X, start, SimulatedExpert(y))
    b = ActiveSemiSupervised(GramRBF(SharedGram(X, X, gamma), C=10), **kw).fit(
        index_column(np.arange(len(X))), start, SimulatedExpert(y))
    assert a.n_queries_ == b.n_queries_ > 0
    np.testing.assert_array_equal(a.labelled_mask_, b.labelled_mask_)
    np.testing.assert_array_equal(a.pseudo_mask_, b.pseudo_mask_)
    assert b.pseudo_mask_.any()


def test_fit_kind_raw_active_gives_the_plain_routes_model(monkeypatch):
    table = load_table(FIXTURE, raw=True, progress=False)
    scenes = ["cornell", "cornell_dark", "checker"]
    gamma = 1.0 / table.X.shape[1]
    fast, info = fit_kind("svm_as", table, scenes, C=10, gamma=gamma)
    monkeypatch.setattr(gram_mod, "MAX_GRAM_BYTES", 0)          # forces the plain route
    slow, info_slow = fit_kind("svm_as", table, scenes, C=10, gamma=gamma)
    assert type(fast) is SVM and info["n_queries"] == info_slow["n_queries"] > 0
    X = table.X[table.scene_mask(["sky"])]
    np.testing.assert_allclose(fast.decision_function(X), slow.decision_function(X), atol=1e-6)


@pytest.mark.parametrize("X, match", [
    (np.zeros((3, 2)), "column of row indices"),
    (np.array([[0.5]]), "whole numbers"),
    (np.array([[99.0]]), "outside"),
])
def test_bad_indices_are_rejected(X, match):
    Xs, y = blobs(20, 8)
    g = GramRBF(SharedGram(Xs, Xs[:10], 0.1)).fit(index_column(np.arange(10)), y[:10])
    with pytest.raises(ValueError, match=match):
        g.decision_function(X)


@pytest.mark.parametrize("rows", [np.full((3, 4), np.nan), np.full((3, 4), np.inf)])
def test_non_finite_samples_and_bad_gamma_are_rejected(rows):
    with pytest.raises(ValueError, match="NaN or Inf"):
        SharedGram(rows, rows, 0.1)
    with pytest.raises(ValueError, match="gamma"):
        SharedGram(np.zeros((2, 2)), np.zeros((2, 2)), float("nan"))


def test_huge_and_tiny_inputs_stay_finite():
    X, y = blobs(60, 16)
    for scale in (1e-150, 1e150):
        g = SharedGram(X * scale, X[:40] * scale, gamma=1.0 / (16 * np.var(X * scale)))
        assert np.isfinite(g.K).all() and (g.K >= 0).all() and (g.K <= 1 + 1e-12).all()
        clf = GramRBF(g).fit(index_column(np.arange(40)), y[:40])
        assert np.isfinite(clf.decision_function(index_column(np.arange(60)))).all()
