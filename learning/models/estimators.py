"""SVM and DSVM: RBF support-vector classifiers with the scikit-learn estimator contract.

DSVM works on the 26 noise features (standardised), SVM on the raw L* block (flattened,
L*/100). Labels are -1 (noisy) and +1 (converged). `decision_function` is the signed
distance to the hyperplane (positive = converged). The fitted attribute `offset_` moves
the decision without refitting: predict is +1 iff f(x) > offset_ (the one stop rule,
`learning.stoprule`). `fit` sets it to 0 (the hyperplane itself); calibration
(`learning.evaluation.calibrate`) sets the value that keeps early stops within a target, the knob
the speed/accuracy trade-off sweeps (a larger offset stops later: fewer early stops,
more samples).
"""
from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC
from sklearn.utils.validation import check_is_fitted

from ..stoprule import OffsetClassifierMixin

LABELS = (-1, 1)


def check_inputs(X: np.ndarray, n_features: int | None = None) -> np.ndarray:
    """float64 2D, finite, with the expected width: clear errors instead of NaN verdicts."""
    X = np.asarray(X)
    if X.ndim != 2:
        raise ValueError(f"expected a 2D array [n_samples, n_features], got shape {X.shape}")
    if not np.issubdtype(X.dtype, np.number):
        raise ValueError(f"expected numbers, got dtype {X.dtype}")
    X = X.astype(np.float64, copy=False)
    if n_features is not None and X.shape[1] != n_features:
        raise ValueError(f"expected {n_features} features per sample, got {X.shape[1]}")
    if X.size and not np.isfinite(X).all():
        bad = int((~np.isfinite(X)).any(axis=1).sum())
        raise ValueError(f"{bad} sample(s) hold NaN or Inf features")
    return X


def check_labels(y: np.ndarray) -> np.ndarray:
    y = np.asarray(y)
    if y.ndim != 1:
        raise ValueError(f"labels must be 1D, got shape {y.shape}")
    bad = set(np.unique(y).tolist()) - set(LABELS)
    if bad:
        raise ValueError(f"labels must be -1 (noisy) or +1 (converged), got {sorted(bad)[:5]}")
    return y.astype(np.int64)


class RBFSVM(OffsetClassifierMixin, ClassifierMixin, BaseEstimator):
    """RBF SVC (optionally on standardised inputs) with a movable decision offset.

    A training set with one class only cannot define a hyperplane: the model then answers
    that class everywhere with decision value +-1 (`constant_`), instead of failing.

    `clip_to_range`: inputs are clipped to the range each feature spanned in training
    (`range_`). An RBF decision function falls back to its intercept far from every
    support vector, so a block less noisy than any training block would otherwise get
    the verdict of no data at all (measured: held-out blocks far below the training
    noise range never stopped); clipped, it gets the verdict of the edge of the data.
    """

    def __init__(self, C: float = 10.0, gamma: float | str = "scale", standardize: bool = True,
                 class_weight: dict | str | None = None, cache_size: float = 500.0,
                 clip_to_range: bool = False) -> None:
        self.C = C
        self.gamma = gamma
        self.standardize = standardize
        self.class_weight = class_weight
        self.cache_size = cache_size
        self.clip_to_range = clip_to_range

    def fit(self, X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None = None) -> "RBFSVM":
        X = check_inputs(X)
        y = check_labels(y)
        if len(X) != len(y):
            raise ValueError(f"{len(X)} samples but {len(y)} labels")
        if len(X) == 0:
            raise ValueError("cannot fit on an empty training set")
        if not (np.isfinite(self.C) and self.C > 0):
            raise ValueError(f"C must be a positive finite number, got {self.C}")
        if not isinstance(self.gamma, str) and not (np.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"gamma must be 'scale', 'auto' or a positive finite number, got {self.gamma}")
        self.n_features_in_ = X.shape[1]
        self.classes_ = np.array(LABELS)
        self.offset_ = 0.0
        self.scaler_ = StandardScaler().fit(X) if self.standardize else None
        self.range_ = np.stack([X.min(axis=0), X.max(axis=0)]) if self.clip_to_range else None
        present = np.unique(y)
        if len(present) == 1:
            self.constant_ = int(present[0])
            self.svc_ = None
            return self
        self.constant_ = None
        Z = self.scaler_.transform(X) if self.scaler_ is not None else X
        self.svc_ = SVC(C=self.C, gamma=self.gamma, kernel="rbf", class_weight=self.class_weight,
                        cache_size=self.cache_size).fit(Z, y, sample_weight=sample_weight)
        return self

    def decision_function(self, X: np.ndarray) -> np.ndarray:
        """Signed distance to the hyperplane, positive = converged; float64 [n]."""
        check_is_fitted(self, "classes_")
        X = check_inputs(X, self.n_features_in_)
        if self.svc_ is None:
            return np.full(len(X), float(self.constant_))
        if len(X) == 0:
            return np.zeros(0)
        rng = getattr(self, "range_", None)          # absent in bundles written before it existed
        if rng is not None:
            X = np.clip(X, rng[0], rng[1])
        Z = self.scaler_.transform(X) if self.scaler_ is not None else X
        return self.svc_.decision_function(Z)

    @property
    def n_support_(self) -> int:
        return 0 if getattr(self, "svc_", None) is None else int(self.svc_.n_support_.sum())

    def n_parameters(self) -> int:
        """Stored numbers: support vectors x features + dual coefficients + intercept (+ scaler)."""
        if getattr(self, "svc_", None) is None:
            return 1
        n_sv, d = self.svc_.support_vectors_.shape
        scaler = 2 * d if self.scaler_ is not None else 0
        bounds = 2 * d if getattr(self, "range_", None) is not None else 0
        return n_sv * d + n_sv + 1 + scaler + bounds


class DSVM(RBFSVM):
    """RBF SVM on noise features, standardised and clipped to the training range (the paper's DSVM)."""

    def __init__(self, C: float = 10.0, gamma: float | str = "scale", standardize: bool = True,
                 class_weight: dict | str | None = None, cache_size: float = 500.0,
                 clip_to_range: bool = True) -> None:
        super().__init__(C, gamma, standardize, class_weight, cache_size, clip_to_range)


class SVM(RBFSVM):
    """RBF SVM on the raw L* block (L*/100, flattened; not standardised)."""

    def __init__(self, C: float = 10.0, gamma: float | str = "scale", standardize: bool = False,
                 class_weight: dict | str | None = None, cache_size: float = 500.0,
                 clip_to_range: bool = False) -> None:
        super().__init__(C, gamma, standardize, class_weight, cache_size, clip_to_range)
