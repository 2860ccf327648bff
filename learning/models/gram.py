"""One RBF Gram matrix for a whole active-learning run on raw pixels.

Algorithm 1 refits the SVM about a hundred times on growing subsets of one fixed set of
samples and scores the whole pool after every fit. On the raw L* blocks (4,096 numbers per
sample) libsvm recomputes each kernel value from the pixels every time, which made
SVM_AL / SVM_AS take ~7 minutes each. Here the squared distances between the samples are
computed once (one float64 BLAS product) and every fit and score slices the Gram matrix.

`GramRBF` is the same RBF SVC, addressed by row index: its `X` is a column of indices
into the rows of the Gram matrix, so the active learner and the stateless query strategy
run on it unchanged. The kernel values differ from libsvm's own only by float rounding;
tests/learning/test_gram.py checks that the queries and the decision values match.
"""
from __future__ import annotations

import logging

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.svm import SVC
from sklearn.utils.validation import check_is_fitted

from ..stoprule import OffsetClassifierMixin
from .estimators import LABELS, check_inputs, check_labels

log = logging.getLogger(__name__)

#: largest Gram matrix (bytes, float64) a run precomputes; beyond it the plain route is used
MAX_GRAM_BYTES = 2 * 1024 ** 3


class SharedGram:
    """K[i, j] = exp(-gamma |a_i - b_j|^2) for rows a (all samples) and columns b (the
    samples an SVM may be fit on). Shared, not copied, when sklearn clones an estimator
    holding it (clone deep-copies parameters; a Gram matrix is read-only here)."""

    def __init__(self, rows: np.ndarray, columns: np.ndarray, gamma: float) -> None:
        if not (np.isfinite(gamma) and gamma > 0):
            raise ValueError(f"gamma must be a positive finite number, got {gamma}")
        a = check_inputs(rows)
        b = check_inputs(columns, a.shape[1])
        sq = np.einsum("ij,ij->i", a, a)[:, None] + np.einsum("ij,ij->i", b, b)[None, :] - 2.0 * (a @ b.T)
        np.maximum(sq, 0.0, out=sq)               # rounding can leave tiny negatives
        np.multiply(sq, -gamma, out=sq)
        self.K = np.exp(sq, out=sq)
        self.K.setflags(write=False)
        self.gamma = float(gamma)

    @staticmethod
    def fits(n_rows: int, n_columns: int) -> bool:
        """Whether a Gram matrix of this shape stays within MAX_GRAM_BYTES."""
        return n_rows * n_columns * 8 <= MAX_GRAM_BYTES

    def __deepcopy__(self, memo: dict) -> "SharedGram":
        return self


def as_index(X: np.ndarray) -> np.ndarray:
    """Row indices from a [n, 1] index column (floats from check_inputs are accepted)."""
    X = np.asarray(X)
    if X.ndim != 2 or X.shape[1] != 1:
        raise ValueError(f"GramRBF takes a column of row indices [n, 1], got shape {X.shape}")
    idx = X[:, 0].astype(np.int64)
    if not np.array_equal(idx, X[:, 0]):
        raise ValueError("GramRBF row indices must be whole numbers")
    return idx


def index_column(indices: np.ndarray) -> np.ndarray:
    return np.asarray(indices, dtype=np.float64).reshape(-1, 1)


class GramRBF(OffsetClassifierMixin, ClassifierMixin, BaseEstimator):
    """RBF SVC on the rows of a `SharedGram`, addressed by index (fit columns only).

    Same contract as `estimators.RBFSVM` without standardisation: decision_function is the
    signed distance (positive = converged), predict is the stop rule's verdict at the
    fitted `offset_` (0 after fit), and a one-class training set answers that class
    everywhere.
    """

    def __init__(self, gram: SharedGram | None = None, C: float = 10.0,
                 class_weight: dict | str | None = None) -> None:
        self.gram = gram
        self.C = C
        self.class_weight = class_weight

    def fit(self, X: np.ndarray, y: np.ndarray) -> "GramRBF":
        if self.gram is None:
            raise ValueError("GramRBF needs a SharedGram")
        idx = as_index(X)
        y = check_labels(y)
        if len(idx) != len(y) or len(idx) == 0:
            raise ValueError(f"{len(idx)} samples but {len(y)} labels")
        if idx.min() < 0 or idx.max() >= self.gram.K.shape[1]:
            raise ValueError("GramRBF can only be fit on the Gram matrix's columns")
        self.classes_ = np.array(LABELS)
        self.n_features_in_ = 1
        self.offset_ = 0.0
        self.train_index_ = idx
        present = np.unique(y)
        self.constant_ = int(present[0]) if len(present) == 1 else None
        self.svc_ = None if self.constant_ is not None else SVC(
            C=self.C, kernel="precomputed", class_weight=self.class_weight
        ).fit(self.gram.K[np.ix_(idx, idx)], y)
        return self

    def decision_function(self, X: np.ndarray) -> np.ndarray:
        check_is_fitted(self, "classes_")
        idx = as_index(X)
        if self.svc_ is None:
            return np.full(len(idx), float(self.constant_))
        if len(idx) == 0:
            return np.zeros(0)
        if idx.min() < 0 or idx.max() >= self.gram.K.shape[0]:
            raise ValueError("row index outside the Gram matrix")
        return self.svc_.decision_function(self.gram.K[np.ix_(idx, self.train_index_)])

