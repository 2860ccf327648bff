"""C and gamma by grouped V-fold cross-validation (the paper's protocol).

Groups are the 16 sub-images of one image level: sub-images of one level share their
noise and must never sit on both sides of a split. gamma is searched as multiples of
scikit-learn's 'scale' value (1 / (n_features * var(X))), so one grid serves the
26-feature DSVM and the raw-pixel SVM alike.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np
from sklearn.base import clone
from sklearn.model_selection import GridSearchCV, GroupKFold
from sklearn.preprocessing import StandardScaler

log = logging.getLogger(__name__)

C_GRID = (1.0, 10.0, 100.0, 1000.0)
GAMMA_FACTORS = (1 / 9, 1 / 3, 1.0, 3.0)


def scale_gamma(X: np.ndarray, standardize: bool) -> float:
    Z = StandardScaler().fit_transform(X) if standardize else X
    var = float(np.var(Z))
    return 1.0 / (X.shape[1] * var) if var > 0 else 1.0


def select_hyperparameters(estimator, X: np.ndarray, y: np.ndarray, groups: np.ndarray,
                           folds: int = 5, c_grid=C_GRID, gamma_factors=GAMMA_FACTORS,
                           n_jobs: int = 1) -> dict[str, Any]:
    """Best (C, gamma) by grouped V-fold CV; returns {"C", "gamma", "cv_precision", "table"}."""
    n_groups = len(np.unique(groups))
    if n_groups < 2 or len(np.unique(y)) < 2:
        log.warning("cross-validation needs 2+ groups and both classes; keeping C=%s gamma=%s",
                    estimator.C, estimator.gamma)
        return {"C": estimator.C, "gamma": estimator.gamma, "cv_precision": None, "table": []}
    g0 = scale_gamma(X, getattr(estimator, "standardize", True))
    grid = {"C": list(c_grid), "gamma": [g0 * f for f in gamma_factors]}
    search = GridSearchCV(clone(estimator), grid, cv=GroupKFold(n_splits=min(folds, n_groups)),
                          scoring="accuracy", n_jobs=n_jobs, refit=False)
    search.fit(X, y, groups=groups)
    res = search.cv_results_
    table = [{"C": p["C"], "gamma": p["gamma"], "precision": float(m)}
             for p, m in zip(res["params"], res["mean_test_score"])]
    best = search.best_params_
    log.info("grouped %d-fold CV: C=%g gamma=%.4g precision %.3f", min(folds, n_groups),
             best["C"], best["gamma"], search.best_score_)
    return {"C": best["C"], "gamma": best["gamma"], "cv_precision": float(search.best_score_),
            "table": table}
