"""Active and active + semi-supervised learning: the paper's Algorithm 1 (DSVM_AS).

    L: labelled set, U: unlabelled pool.
    for s in 1..S:                       (n_outer)
        for p in 1..P:                   (n_inner)
            fit f on L (+ pseudo-labelled samples)
            record sign f(x) for x in U
            query the batch of U closest to the hyperplane; the expert labels it -> L
        semi-supervised step: w(x) = fraction of the P iterations in which x's predicted
        label changed; among x with w = 0, per predicted class, add the samples at the
        median distance |f(x)| (the class centres) with their predicted labels
    then plain active learning until the stopping criterion.

`*_AL` is the same loop without the semi-supervised step. The expert is any callable
indices -> labels (a human, or `SimulatedExpert` revealing a dataset's labels).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin, clone
from tqdm import tqdm

from .estimators import DSVM, check_inputs
from .query import MISSING_LABEL, MarginQuery, is_labelled

log = logging.getLogger(__name__)

Expert = Callable[[np.ndarray], np.ndarray]


class SimulatedExpert:
    """Reveals the true labels of queried samples and counts what it was asked."""

    def __init__(self, y_true: np.ndarray) -> None:
        self.y_true = np.asarray(y_true)
        self.asked = 0

    def __call__(self, idx: np.ndarray) -> np.ndarray:
        self.asked += len(idx)
        return self.y_true[idx]


def label_changing_rate(history: np.ndarray) -> np.ndarray:
    """w(x) over P recorded predictions [P, n]: fraction of the P-1 transitions that flip."""
    history = np.asarray(history)
    if len(history) < 2:
        return np.zeros(history.shape[1] if history.ndim == 2 else 0)
    return (np.diff(history, axis=0) != 0).mean(axis=0)


def class_centres(decision: np.ndarray, stable: np.ndarray, n_per_class: int) -> np.ndarray:
    """Indices of stable samples closest to the median |f| of their predicted class."""
    chosen = []
    pred = np.where(decision > 0, 1, -1)
    for c in (-1, 1):
        idx = np.flatnonzero(stable & (pred == c))
        if len(idx) == 0 or n_per_class == 0:
            continue
        dist = np.abs(decision[idx])
        order = np.argsort(np.abs(dist - np.median(dist)), kind="stable")[:n_per_class]
        chosen.append(idx[order])
    return np.concatenate(chosen) if chosen else np.zeros(0, int)


class ActiveSemiSupervised(ClassifierMixin, BaseEstimator):
    """DSVM_AS / SVM_AS (semi_supervised=True) and DSVM_AL / SVM_AL (False).

    Stopping after the S x P phase: the label budget (`max_label_fraction` of the pool,
    and `max_queries`) or, when `patience` is set and a validation set is given, a
    precision plateau (no gain above `min_delta` for `patience` iterations). With
    `patience=None` the validation set is only recorded in `history_` (for plots), never
    used to decide anything: pass held-out data that way without leaking it.
    """

    def __init__(self, estimator=None, semi_supervised: bool = True, n_outer: int = 10,
                 n_inner: int = 5, batch_size: int = 16, n_centres: int = 20,
                 max_label_fraction: float = 0.25, max_queries: int | None = None,
                 patience: int | None = 10, min_delta: float = 0.002, query_strategy=None,
                 progress: bool = False) -> None:
        self.estimator = estimator
        self.semi_supervised = semi_supervised
        self.n_outer = n_outer
        self.n_inner = n_inner
        self.batch_size = batch_size
        self.n_centres = n_centres
        self.max_label_fraction = max_label_fraction
        self.max_queries = max_queries
        self.patience = patience
        self.min_delta = min_delta
        self.query_strategy = query_strategy
        self.progress = progress

    # -- helpers ---------------------------------------------------------------------
    def _fit_on(self, X, y_lab, pseudo):
        train = is_labelled(y_lab) | pseudo
        y_train = np.where(is_labelled(y_lab), y_lab, self.pseudo_labels_)[train].astype(int)
        return clone(self.estimator if self.estimator is not None else DSVM()).fit(X[train], y_train)

    def _budget(self, n_pool: int) -> int:
        budget = int(np.floor(self.max_label_fraction * n_pool))
        return min(budget, self.max_queries) if self.max_queries is not None else budget

    def fit(self, X: np.ndarray, y: np.ndarray, expert: Expert | None = None,
            X_val: np.ndarray | None = None, y_val: np.ndarray | None = None) -> "ActiveSemiSupervised":
        """`y`: known labels, NaN for the unlabelled pool; `expert(indices) -> labels`."""
        t0 = time.perf_counter()
        X = check_inputs(X)
        y = np.asarray(y, dtype=np.float64).copy()
        if len(y) != len(X):
            raise ValueError(f"{len(X)} samples but {len(y)} labels")
        if not is_labelled(y).any():
            raise ValueError("Algorithm 1 needs an initial labelled set (y with some labels)")
        if expert is None:
            raise ValueError("an expert (callable indices -> labels) is needed to answer queries")
        query = self.query_strategy or MarginQuery()
        n_pool = int((~is_labelled(y)).sum())
        budget = self._budget(n_pool)
        self.pseudo_labels_ = np.zeros(len(y))
        pseudo = np.zeros(len(y), bool)
        self.history_: list[dict] = []
        queried = 0
        clf = self._fit_on(X, y, pseudo)
        bar = tqdm(total=budget, desc="labels queried", disable=not self.progress, leave=False)

        def step() -> bool:
            """One active iteration; False when the pool or the budget is exhausted."""
            nonlocal clf, queried
            room = budget - queried
            if room <= 0:
                return False
            cand = ~pseudo
            y_q = np.where(pseudo, 0.0, y)       # pseudo-labelled samples count as labelled here
            idx = query.query(X, y_q, clf, batch_size=min(self.batch_size, room), fit_clf=False,
                              candidates=cand)
            if len(idx) == 0:
                return False
            labels = np.asarray(expert(idx), dtype=np.float64)
            if labels.shape != (len(idx),) or not np.isin(labels, (-1, 1)).all():
                raise ValueError("the expert must answer -1 or +1 for every queried sample")
            y[idx] = labels
            queried += len(idx)
            bar.update(len(idx))
            clf = self._fit_on(X, y, pseudo)
            self._record(clf, queried, pseudo, X_val, y_val)
            return True

        for _ in range(self.n_outer):
            preds, track = [], ~is_labelled(y) & ~pseudo
            for _ in range(self.n_inner):
                preds.append(np.where(clf.decision_function(X) > 0, 1, -1))
                if not step():
                    break
            if self.semi_supervised and len(preds) >= 2:
                still = track & ~is_labelled(y) & ~pseudo
                w = label_changing_rate(np.stack(preds))
                f = clf.decision_function(X)
                stable = still & (w == 0)
                add = class_centres(np.where(stable, f, 0.0), stable, self.n_centres // 2)
                self.pseudo_labels_[add] = np.where(f[add] > 0, 1, -1)
                pseudo[add] = True
                clf = self._fit_on(X, y, pseudo)
        # then plain active learning until the stopping criterion
        best, since = -np.inf, 0
        while step():
            if self.patience is not None and X_val is not None and self.history_:
                p = self.history_[-1]["val_precision"]
                if p > best + self.min_delta:
                    best, since = p, 0
                else:
                    since += 1
                    if since >= self.patience:
                        break
        bar.close()
        self.estimator_ = clf
        self.classes_ = clf.classes_
        self.n_features_in_ = X.shape[1]
        self.labelled_mask_ = is_labelled(y)
        self.pseudo_mask_ = pseudo
        self.n_queries_ = queried
        self.n_pool_ = n_pool
        self.fit_time_ = time.perf_counter() - t0
        return self

    def _record(self, clf, queried, pseudo, X_val, y_val) -> None:
        entry = {"queries": queried, "pseudo": int(pseudo.sum())}
        if X_val is not None and y_val is not None and len(y_val):
            entry["val_precision"] = float((clf.predict(X_val) == np.asarray(y_val)).mean())
        self.history_.append(entry)

    # -- the estimator contract --------------------------------------------------------
    def decision_function(self, X: np.ndarray) -> np.ndarray:
        return self.estimator_.decision_function(X)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.estimator_.predict(X)

    @property
    def n_support_(self) -> int:
        return self.estimator_.n_support_

    def n_parameters(self) -> int:
        return self.estimator_.n_parameters()
