"""Query strategies in scikit-activeml's stateless form: query(X, y, clf, batch_size).

Unlabelled samples are marked in `y` with MISSING_LABEL (NaN), as scikit-activeml does.
"""
from __future__ import annotations

import numpy as np
from sklearn.base import clone

MISSING_LABEL = np.nan


def is_labelled(y: np.ndarray) -> np.ndarray:
    return ~np.isnan(np.asarray(y, dtype=np.float64))


class MarginQuery:
    """Batch-mode uncertainty sampling for SVMs: the unlabelled samples closest to the
    hyperplane (smallest |f(x)|), the paper's query."""

    def query(self, X: np.ndarray, y: np.ndarray, clf, batch_size: int = 1, fit_clf: bool = True,
              candidates: np.ndarray | None = None, return_utilities: bool = False):
        """Indices (into X) of the `batch_size` most uncertain unlabelled candidates."""
        y = np.asarray(y, dtype=np.float64)
        labelled = is_labelled(y)
        pool = ~labelled if candidates is None else (~labelled & np.asarray(candidates, bool))
        idx = np.flatnonzero(pool)
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if len(idx) == 0:
            return (np.zeros(0, int), np.zeros(0)) if return_utilities else np.zeros(0, int)
        if fit_clf:
            if not labelled.any():
                raise ValueError("no labelled sample to fit the classifier on")
            clf = clone(clf).fit(X[labelled], y[labelled].astype(int))
        margin = np.abs(clf.decision_function(X[idx]))
        # stable order: equal margins keep index order, so queries are reproducible
        order = np.argsort(margin, kind="stable")[:batch_size]
        chosen = idx[order]
        return (chosen, -margin[order]) if return_utilities else chosen


class RandomQuery:
    """Random sampling: the baseline active learning must beat."""

    def __init__(self, random_state: int = 0) -> None:
        self.random_state = random_state

    def query(self, X: np.ndarray, y: np.ndarray, clf=None, batch_size: int = 1, fit_clf: bool = True,
              candidates: np.ndarray | None = None):
        y = np.asarray(y, dtype=np.float64)
        pool = ~is_labelled(y) if candidates is None else (~is_labelled(y) & np.asarray(candidates, bool))
        idx = np.flatnonzero(pool)
        rng = np.random.default_rng(self.random_state + int(is_labelled(y).sum()))
        return rng.choice(idx, size=min(batch_size, len(idx)), replace=False) if len(idx) else idx
