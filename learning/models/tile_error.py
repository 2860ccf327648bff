"""The learned per-tile error estimate: how far a tile's halves history is from
the observer's error, learned from the training corpus, as a scikit-learn regressor.

`TileErrorEstimator.fit(X, y)` learns y = log(true error) - log(e_hist) from rows of
`learning.inputs.tile_features.tile_features` (their column 0 is log e_hist);
`predict(X)` is that correction and `estimate(X)` the error it implies, e_hist exp(predict).
The stop compares `estimate` with c(tau), a curve calibrated out of fold on the training
scenes' final frames (`learning.evaluation.tile_error_calibration`), so the margin that
keeps early stops rare is the estimate's own out-of-fold error, not a guess.

Two kinds: "gbm" (gradient-boosted trees, `HistGradientBoostingRegressor`) and "linear"
(ridge on standardised inputs), compared in docs/benchmarks/learning.md.
"""
from __future__ import annotations

from numbers import Integral, Real

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.linear_model import Ridge
from sklearn.pipeline import Pipeline, make_pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.validation import check_is_fitted

from ..inputs.tile_features import FEATURE_NAMES
from .estimators import check_inputs

KINDS = ("gbm", "linear")


class TileErrorEstimator(RegressorMixin, BaseEstimator):
    """log(true / halves-history error) of a tile from its decision's inputs.

    `kind`: "gbm" or "linear"; `max_iter`, `learning_rate`, `max_leaf_nodes`,
    `min_samples_leaf`: the boosted trees' (ignored by "linear"); `alpha`: the ridge's
    penalty (ignored by "gbm"); `random_state`: the trees' seed; `quantile`: None to learn
    the mean correction, or q in (0, 1) to learn its q-quantile (the trees' pinball loss:
    a tile whose correction is uncertain gets a larger one, its own margin).
    Fitted: `model_` (the scikit-learn regressor), `n_features_in_`.
    """

    _parameter_constraints: dict = {
        "kind": [StrOptions(set(KINDS))],
        "max_iter": [Interval(Integral, 1, 10_000, closed="both")],
        "learning_rate": [Interval(Real, 0.0, 1.0, closed="right")],
        "max_leaf_nodes": [Interval(Integral, 2, 1024, closed="both")],
        "min_samples_leaf": [Interval(Integral, 1, None, closed="left")],
        "alpha": [Interval(Real, 0.0, None, closed="left")],
        "random_state": [Interval(Integral, 0, None, closed="left")],
        "quantile": [Interval(Real, 0.0, 1.0, closed="neither"), None],
    }

    def __init__(self, kind: str = "gbm", max_iter: int = 300, learning_rate: float = 0.05,
                 max_leaf_nodes: int = 15, min_samples_leaf: int = 40, alpha: float = 1.0,
                 random_state: int = 0, quantile: float | None = None) -> None:
        self.kind, self.max_iter, self.learning_rate = kind, max_iter, learning_rate
        self.max_leaf_nodes, self.min_samples_leaf, self.alpha = max_leaf_nodes, min_samples_leaf, alpha
        self.random_state, self.quantile = random_state, quantile

    def fit(self, X: np.ndarray, y: np.ndarray) -> TileErrorEstimator:
        self._validate_params()
        X = check_inputs(X, len(FEATURE_NAMES))
        y = np.asarray(y, np.float64).reshape(-1)
        if len(y) != len(X) or not len(y):
            raise ValueError(f"need one finite target per row, got {len(y)} targets for {len(X)} rows")
        if not np.isfinite(y).all():
            raise ValueError(f"{int((~np.isfinite(y)).sum())} target(s) are NaN or Inf")
        if self.quantile is not None and self.kind != "gbm":
            raise ValueError("a quantile is learned by kind='gbm' only")
        if self.kind == "gbm":
            model: HistGradientBoostingRegressor | Pipeline = HistGradientBoostingRegressor(
                max_iter=self.max_iter, learning_rate=self.learning_rate, max_leaf_nodes=self.max_leaf_nodes,
                min_samples_leaf=self.min_samples_leaf, random_state=self.random_state,
                **({} if self.quantile is None else {"loss": "quantile", "quantile": self.quantile}))
        else:
            model = make_pipeline(StandardScaler(), Ridge(alpha=self.alpha))
        self.model_ = model.fit(X, y)
        self.n_features_in_ = X.shape[1]
        return self

    def predict(self, X: np.ndarray) -> np.ndarray:
        """float64 [n]: the learned log(true / e_hist) of each row."""
        check_is_fitted(self, "model_")
        X = check_inputs(X, self.n_features_in_)
        return np.asarray(self.model_.predict(X), np.float64) if len(X) else np.zeros(0)

    def estimate(self, X: np.ndarray) -> np.ndarray:
        """float64 [n]: the tile's estimated observer error, e_hist exp(predict(X))."""
        X = check_inputs(X, len(FEATURE_NAMES))
        return np.exp(X[:, 0] + self.predict(X))
