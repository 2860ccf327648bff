"""Training the paper's models on a dataset, with scenes held out for evaluation.

Supervised kinds (svm, dsvm) see every label of the training scenes. Active kinds
(*_al, *_as) start from the labelled sub-images of one training scene (the paper starts
from one scene's 505) and query the others' labels through a simulated expert, up to
`max_label_fraction` of the pool; held-out scenes are only recorded for the
precision-vs-queries curve, never used to decide anything.
"""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from noisefeat import FeatureBase

from .active import ActiveSemiSupervised, SimulatedExpert
from .cv import select_hyperparameters
from .estimators import DSVM, SVM, RBFSVM
from .table import SubImageTable, load_table

log = logging.getLogger(__name__)

SVM_KINDS = ("svm", "dsvm", "svm_al", "dsvm_al", "svm_as", "dsvm_as")
CV_MAX_SAMPLES = 4000


def default_test_scenes(scenes: list[str]) -> list[str]:
    """Every fourth scene by name, starting with the second: about a quarter held out."""
    return sorted(scenes)[1::4]


def split_scenes(table: SubImageTable, test_scenes: list[str] | None) -> tuple[list[str], list[str]]:
    scenes = table.scenes()
    test = default_test_scenes(scenes) if test_scenes is None else list(test_scenes)
    unknown = sorted(set(test) - set(scenes))
    if unknown:
        raise ValueError(f"test scenes not in the dataset: {unknown}; it has {scenes}")
    train = [s for s in scenes if s not in test]
    if not train:
        raise ValueError("no scene left for training once the test scenes are held out")
    return train, test


def balanced_scene(table: SubImageTable, scenes: list[str]) -> str:
    """The training scene whose labels are closest to half converged: the initial set."""
    fractions = {s: float((table.y[table.scene == s] > 0).mean()) for s in scenes}
    return min(scenes, key=lambda s: (abs(fractions[s] - 0.5), s))


def _cv_subset(n: int, groups: np.ndarray, seed: int) -> np.ndarray:
    """Whole groups, at random, up to CV_MAX_SAMPLES rows: CV cost stays bounded."""
    if n <= CV_MAX_SAMPLES:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    ug = rng.permutation(np.unique(groups))
    sizes = {g: int((groups == g).sum()) for g in ug}
    keep, total = [], 0
    for g in ug:
        if total >= CV_MAX_SAMPLES:
            break
        keep.append(g)
        total += sizes[g]
    return np.flatnonzero(np.isin(groups, keep))


def train_model(kind: str, data: str, *, test_scenes: list[str] | None = None,
                initial_scene: str | None = None, cv: bool = True, seed: int = 0,
                max_label_fraction: float = 0.25, batch_size: int = 16,
                base: FeatureBase | None = None, progress: bool = True,
                table: SubImageTable | None = None) -> tuple[RBFSVM, dict[str, Any]]:
    """Fit one model kind; returns (fitted estimator, training summary for the manifest)."""
    kind = kind.lower()
    if kind not in SVM_KINDS:
        raise ValueError(f"unknown model kind {kind!r}; SVM kinds: {', '.join(SVM_KINDS)}")
    raw = kind.startswith("svm")
    t0 = time.perf_counter()
    table = table or load_table(data, raw=raw, base=base, progress=progress)
    t_data = time.perf_counter() - t0
    train_scenes, test = split_scenes(table, test_scenes)
    tr = np.isin(table.scene, train_scenes)
    te = np.isin(table.scene, test)
    X, y, groups = table.X[tr], table.y[tr].astype(int), table.groups[tr]
    est: RBFSVM = SVM() if raw else DSVM()
    summary: dict[str, Any] = {"kind": kind, "input": "raw" if raw else "features",
                               "train_scenes": train_scenes, "test_scenes": test,
                               "n_train": int(tr.sum()), "data": str(data), "seed": seed,
                               "table_s": t_data}
    t1 = time.perf_counter()
    if kind in ("svm", "dsvm"):
        if cv:
            sub = _cv_subset(len(y), groups, seed)
            best = select_hyperparameters(est, X[sub], y[sub], groups[sub])
            est.set_params(C=best["C"], gamma=best["gamma"])
            summary["cv"] = best
        est.fit(X, y)
        summary.update(n_labels=int(len(y)), label_fraction=1.0)
        fitted = est
    else:
        first = initial_scene or balanced_scene(table, train_scenes)
        if first not in train_scenes:
            raise ValueError(f"initial scene {first!r} is not a training scene ({train_scenes})")
        init = table.scene[tr] == first
        if cv:
            best = select_hyperparameters(est, X[init], y[init], groups[init])
            est.set_params(C=best["C"], gamma=best["gamma"])
            summary["cv"] = best
        y_known = np.where(init, y, np.nan).astype(float)
        learner = ActiveSemiSupervised(estimator=est, semi_supervised=kind.endswith("_as"),
                                       batch_size=batch_size, max_label_fraction=max_label_fraction,
                                       patience=None, progress=progress)
        learner.fit(X, y_known, SimulatedExpert(y), X_val=table.X[te] if te.any() else None,
                    y_val=table.y[te].astype(int) if te.any() else None)
        fitted = learner.estimator_
        summary.update(initial_scene=first, n_initial=int(init.sum()), n_pool=learner.n_pool_,
                       n_queries=learner.n_queries_,
                       query_fraction=learner.n_queries_ / max(1, learner.n_pool_),
                       n_pseudo=int(learner.pseudo_mask_.sum()),
                       n_labels=int(init.sum()) + learner.n_queries_,
                       label_fraction=(int(init.sum()) + learner.n_queries_) / len(y),
                       history=learner.history_)
    summary["train_s"] = time.perf_counter() - t1
    summary["C"], summary["gamma"] = float(fitted.C), fitted.gamma
    log.info("%s: trained on %d scenes in %.1f s (%s labels)", kind, len(train_scenes),
             summary["train_s"], summary.get("n_labels"))
    return fitted, summary
