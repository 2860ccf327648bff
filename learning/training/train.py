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

from ..evaluation.generalisation import default_test_scenes
from ..inputs.table import SubImageTable, load_table
from ..models.active import ActiveSemiSupervised, SimulatedExpert
from ..models.cv import select_hyperparameters
from ..models.estimators import DSVM, SVM, RBFSVM
from ..models.gram import GramRBF, SharedGram, index_column
from ..names import SVM_KINDS

log = logging.getLogger(__name__)

CV_MAX_SAMPLES = 4000
CV_MAX_SAMPLES_RAW = 1000   # 4096-dim raw blocks: each RBF fit costs ~100x a 26-feature one
AL_BATCH = 16               # labels queried per active-learning round


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


#: the initial labelled set holds at least this many sub-images (the paper's: one scene's
#: 505; a stack of one 64x64 block has only 64)
INITIAL_MIN_ROWS = 500


def initial_scenes(table: SubImageTable, scenes: list[str], min_rows: int = INITIAL_MIN_ROWS) -> list[str]:
    """The initial labelled set of the active kinds: the scenes whose labels are closest to
    half converged, as many as it takes to reach `min_rows` sub-images (one scene of a
    16-block stack; about eight of one-block stacks). Both classes are needed to fit."""
    fractions = {s: float((table.y[table.scene == s] > 0).mean()) for s in scenes}
    chosen, rows = [], 0
    for s in sorted(scenes, key=lambda s: (abs(fractions[s] - 0.5), s)):
        chosen.append(s)
        rows += int((table.scene == s).sum())
        if rows >= min_rows and len(np.unique(table.y[table.scene_mask(chosen)])) == 2:
            break
    return chosen


def cv_groups(table: SubImageTable, rows: np.ndarray, folds: int = 5) -> np.ndarray:
    """Groups for grouped cross-validation: the paper's (the sub-images of one image level)
    when the rows hold fewer than `folds` scenes; else whole scenes, since the levels of a
    one-block stack are one block's noise at several spp and would leak across folds."""
    scenes = table.scene[rows]
    if len(np.unique(scenes)) < folds:
        return table.groups[rows]
    return np.unique(scenes, return_inverse=True)[1]


def _cv_subset(n: int, groups: np.ndarray, seed: int, limit: int = CV_MAX_SAMPLES) -> np.ndarray:
    """Whole groups, at random, up to `limit` rows: CV cost stays bounded."""
    if n <= limit:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    ug = rng.permutation(np.unique(groups))
    sizes = {g: int((groups == g).sum()) for g in ug}
    keep, total = [], 0
    for g in ug:
        if total >= limit:
            break
        keep.append(g)
        total += sizes[g]
    return np.flatnonzero(np.isin(groups, keep))


def _raw_gram(kind: str, X: np.ndarray, X_val: np.ndarray | None, gamma) -> SharedGram | None:
    """The precomputed Gram matrix for a raw-pixel active run (rows: pool + monitor), or
    None where it does not apply (feature kinds, gamma not a number, too large)."""
    if not kind.startswith("svm_") or isinstance(gamma, str):
        return None
    rows = X if X_val is None else np.concatenate([X, X_val])
    if not SharedGram.fits(len(rows), len(X)):
        log.info("%s: %d x %d Gram matrix too large to precompute; libsvm computes kernels", kind,
                 len(rows), len(X))
        return None
    t0 = time.perf_counter()
    gram = SharedGram(rows, X, float(gamma))
    log.info("%s: %d x %d Gram matrix in %.1f s", kind, len(rows), len(X), time.perf_counter() - t0)
    return gram


def fit_kind(kind: str, table: SubImageTable, scenes: list[str], *, C: float, gamma,
             initial_scene: str | list[str] | None = None, max_label_fraction: float = 0.25,
             batch_size: int = AL_BATCH, monitor: SubImageTable | None = None,
             progress: bool = False) -> tuple[RBFSVM, dict[str, Any]]:
    """Fit `kind` with fixed (C, gamma) on the rows of `scenes`; returns (estimator, info)."""
    tr = table.scene_mask(scenes)
    X, y = table.X[tr], table.y[tr].astype(int)
    est: RBFSVM = (SVM if kind.startswith("svm") else DSVM)(C=C, gamma=gamma)
    if kind in ("svm", "dsvm"):
        return est.fit(X, y), {"n_labels": int(len(y)), "label_fraction": 1.0}
    first = _initial(initial_scene) or initial_scenes(table, scenes)
    unknown = sorted(set(first) - set(scenes))
    if unknown:
        raise ValueError(f"initial scene(s) {', '.join(unknown)} not among the training scenes ({scenes})")
    init = np.isin(table.scene[tr], first)
    X_val = None if monitor is None else monitor.X
    gram = _raw_gram(kind, X, X_val, gamma)
    learner = ActiveSemiSupervised(estimator=est if gram is None else GramRBF(gram, C=C),
                                   semi_supervised=kind.endswith("_as"), batch_size=batch_size,
                                   max_label_fraction=max_label_fraction, patience=None,
                                   progress=progress)
    if gram is not None:     # the learner works on row indices into the Gram matrix
        X_val = None if X_val is None else index_column(len(X) + np.arange(len(X_val)))
    learner.fit(X if gram is None else index_column(np.arange(len(X))),
                np.where(init, y, np.nan).astype(float), SimulatedExpert(y), X_val=X_val,
                y_val=None if monitor is None else monitor.y.astype(int))
    fitted = learner.estimator_
    if gram is not None:     # the same SVM on the same training set, as a plain estimator
        train = learner.labelled_mask_ | learner.pseudo_mask_
        fitted = est.fit(X[train], np.where(learner.labelled_mask_, y, learner.pseudo_labels_)[train].astype(int))
    return fitted, {
        "initial_scenes": first, "n_initial": int(init.sum()), "n_pool": learner.n_pool_,
        "n_queries": learner.n_queries_, "query_fraction": learner.n_queries_ / max(1, learner.n_pool_),
        "n_pseudo": int(learner.pseudo_mask_.sum()), "n_labels": int(init.sum()) + learner.n_queries_,
        "label_fraction": (int(init.sum()) + learner.n_queries_) / len(y), "history": learner.history_}


def _initial(initial_scene: str | list[str] | None) -> list[str]:
    """The initial scenes a caller named ('a,b' or a list), [] for none."""
    if initial_scene is None:
        return []
    names = initial_scene.split(",") if isinstance(initial_scene, str) else list(initial_scene)
    return [n.strip() for n in names if n.strip()]


def train_model(kind: str, data: str, *, test_scenes: list[str] | None = None,
                initial_scene: str | list[str] | None = None, cv: bool = True, seed: int = 0,
                max_label_fraction: float = 0.25, batch_size: int = AL_BATCH,
                max_early_stop: float | None = None, quick: str = "albedo",
                base: FeatureBase | None = None, progress: bool = True,
                table: SubImageTable | None = None,
                cv_max_samples: int | None = None,
                monitor: SubImageTable | None = None) -> tuple[RBFSVM, dict[str, Any]]:
    """Fit one model kind; returns (fitted estimator, training summary for the manifest).

    With `max_early_stop`, the decision offset is calibrated on leave-one-scene-out scores
    of the training scenes (learning.evaluation.calibrate) to keep early stops within that rate.
    `cv_max_samples` caps the rows the supervised kinds' cross-validation sees (default
    CV_MAX_SAMPLES, raw pixels CV_MAX_SAMPLES_RAW; 0 = no cap): a speed knob whose accuracy
    cost `noisestop bench knobs` measures. `monitor`: held-out rows whose precision the
    active kinds record along their queries (default: the test scenes of `table`); only
    recorded, never used to decide anything.
    """
    kind = kind.lower()
    if kind not in SVM_KINDS:
        raise ValueError(f"unknown model kind {kind!r}; SVM kinds: {', '.join(SVM_KINDS)}")
    raw = kind.startswith("svm")
    t0 = time.perf_counter()
    table = table or load_table(data, raw=raw, base=base, progress=progress, quick=quick)
    t_data = time.perf_counter() - t0
    train_scenes, test = split_scenes(table, test_scenes)
    tr = table.scene_mask(train_scenes)
    summary: dict[str, Any] = {"kind": kind, "input": "raw" if raw else "features",
                               "quick": quick if not raw or quick == "halves" else None,
                               "train_scenes": train_scenes, "test_scenes": test,
                               "n_train": int(tr.sum()), "data": str(data), "seed": seed,
                               "table_s": t_data}
    t1 = time.perf_counter()
    template = SVM() if raw else DSVM()
    C, gamma = template.C, template.gamma
    fit_table = table.trainable()        # rows whose input exists (halves: not the first level)
    tr_fit = fit_table.scene_mask(train_scenes)
    if cv:
        if kind in ("svm", "dsvm"):
            rows = np.flatnonzero(tr_fit)
            cap = (CV_MAX_SAMPLES_RAW if raw else CV_MAX_SAMPLES) if cv_max_samples is None else \
                (cv_max_samples or len(rows))
            sub = rows[_cv_subset(len(rows), cv_groups(fit_table, rows), seed, cap)]
            summary["cv_rows"] = int(len(sub))
        else:  # the paper: cross-validation on the initially labelled set
            first = _initial(initial_scene) or initial_scenes(fit_table, train_scenes)
            sub = np.flatnonzero(fit_table.scene_mask(first))
        best = select_hyperparameters(template, fit_table.X[sub], fit_table.y[sub].astype(int),
                                      cv_groups(fit_table, sub))
        C, gamma = best["C"], best["gamma"]
        summary["cv"] = best
    if monitor is None and test:
        monitor = fit_table.subset(fit_table.scene_mask(test))
    fitted, info = fit_kind(kind, fit_table, train_scenes, C=C, gamma=gamma, initial_scene=initial_scene,
                            max_label_fraction=max_label_fraction, batch_size=batch_size,
                            monitor=monitor, progress=progress)
    summary.update(info)
    summary["train_s"] = time.perf_counter() - t1
    if max_early_stop is not None:
        from ..evaluation.calibrate import calibrate_offset

        def fold_fit(sub_table: SubImageTable) -> RBFSVM:
            return fit_kind(kind, sub_table.trainable(), sub_table.scenes(), C=C, gamma=gamma,
                            max_label_fraction=max_label_fraction, batch_size=batch_size)[0]
        fitted.offset_, summary["calibration"] = calibrate_offset(fold_fit, table.subset(tr), train_scenes,
                                                                  max_early_stop, progress=progress)
    summary["C"], summary["gamma"] = float(fitted.C), fitted.gamma
    summary["offset"] = float(fitted.offset_)
    log.info("%s: trained on %d scenes in %.1f s (%s labels), offset %.2f", kind, len(train_scenes),
             summary["train_s"], summary.get("n_labels"), fitted.offset_)
    return fitted, summary
