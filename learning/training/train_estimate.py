"""Training the learned stop: the per-tile error estimate and its c(tau).

1. Every training stack's tiles at every level become rows (`learning.inputs.tile_table`);
   the estimator learns log(true / e_hist) on the rows whose true error lies in `BAND`,
   where a stop at any tau of the curve is decided (far above it no stop is near, far
   below it the estimate cannot be early).
2. Out of fold (scenes in `learning.evaluation.calibrate.scene_folds`), each scene's
   estimates come from an estimator fit without it; c(tau) is chosen on them as flip's is
   (`calibrate_flip_curve` with `estimates`: the final frame's early blocks at most the
   target on scenes it was not chosen on). So the margin between the estimate and tau is
   the estimate's own out-of-fold error, the conformal step. (On a seeded subset of at most
   `CALIBRATION_SCENES` scenes: the cost is a final frame judged per scene and c tried.)
3. The shipped estimator is then fit on every training scene.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from ..data.relabel import with_tile_truth
from ..data.stack import Stack
from ..evaluation.calibrate import CALIBRATION_FOLDS, calibrate_flip_curve, scene_folds
from ..evaluation.spread import needed_spread
from ..inputs.tile_table import TileTable, stack_tile_table
from ..models.tile_error import TileErrorEstimator

#: true errors of the rows trained on: around every tau of the curve (0.01-0.05)
BAND = (0.003, 0.2)
#: the taus c(tau) is calibrated at (between them it is interpolated in log)
ESTIMATE_TAUS = (0.01, 0.015, 0.02, 0.03, 0.04, 0.05)
#: c tried, as multiples of tau, 3 % apart: the estimate is of the error itself, so c lies near tau
RELATIVE_CANDIDATES = np.geomspace(0.25, 2.0, 71)


#: c(tau) is chosen on at most this many training scenes: each c tried judges every scene's
#: final frame (a FLIP of the frame per distinct set of stops), and a hundred one-block scenes
#: already resolve a 5 % target to 1 %
CALIBRATION_SCENES = 120


def calibration_subset(scenes: Sequence[str], n: int | None) -> set[str]:
    """A seeded subset of `n` of `scenes` (all of them when n is None or they are fewer)."""
    if n is None or len(scenes) <= n:
        return set(scenes)
    order = np.random.default_rng(0).permutation(sorted(scenes))
    return set(order[:n].tolist())


def candidates(tau: float) -> tuple[float, ...]:
    """The c tried at `tau` (`RELATIVE_CANDIDATES` times tau)."""
    return tuple(float(f"{c:.5g}") for c in RELATIVE_CANDIDATES * float(tau))


def training_rows(tables: Sequence[TileTable], band: tuple[float, float] = BAND) -> tuple[np.ndarray, np.ndarray]:
    """(X [m, F], y [m]) of the tables' rows with an estimate, a truth in `band` and not flat."""
    xs, ys = [], []
    for t in tables:
        ok = np.isfinite(t.y) & np.isfinite(t.e_hist) & ~t.flat & (t.true_error > band[0]) & (t.true_error < band[1])
        xs.append(t.X[ok])
        ys.append(t.y[ok])
    if not xs or not sum(len(y) for y in ys):
        raise ValueError("no training rows: the stacks have no tile whose true error is near any tau")
    return np.concatenate(xs), np.concatenate(ys)


def estimates_of(estimator: TileErrorEstimator, table: TileTable) -> np.ndarray:
    """float64 [K, n]: the estimator's error estimate of every tile at every level (NaN
    where the halves' history has none)."""
    k, n, f = table.X.shape
    est = estimator.estimate(table.X.reshape(-1, f)).reshape(k, n)
    return np.where(np.isfinite(table.e_hist), est, np.nan)


def out_of_fold_estimates(tables: Mapping[str, TileTable], params: Mapping[str, Any],
                          folds: int | None = CALIBRATION_FOLDS, progress: bool = False) -> dict[str, np.ndarray]:
    """scene -> [K, n]: each scene estimated by an estimator fit without its fold."""
    out: dict[str, np.ndarray] = {}
    for fold in tqdm(scene_folds(list(tables), folds), desc="folds", disable=not progress, leave=False):
        others = [t for s, t in tables.items() if s not in fold]
        est = TileErrorEstimator(**params).fit(*training_rows(others))
        out.update({s: estimates_of(est, tables[s]) for s in fold})
    return out


def train_tile_error(stacks: Sequence[Stack], *, tile: int = 16, params: Mapping[str, Any] | None = None,
                     max_early_stop: float = 0.05, folds: int | None = CALIBRATION_FOLDS,
                     taus: Sequence[float] = ESTIMATE_TAUS, calibration_scenes: int | None = CALIBRATION_SCENES,
                     progress: bool = True) -> tuple[TileErrorEstimator, dict[str, Any], dict[str, Any]]:
    """(estimator fit on every stack, its c(tau) calibration, the training record) from
    labelled training stacks (never held-out ones); c(tau) chosen on `calibration_scenes` of
    them (`calibration_subset`)."""
    params = dict(params or {})
    t0 = time.perf_counter()
    stacks = [with_tile_truth(s, tile) for s in stacks]
    tables = {s.scene: stack_tile_table(s, tile, progress=progress)
              for s in tqdm(stacks, desc="tile rows", disable=not progress, leave=False)}
    oof = out_of_fold_estimates(tables, params, folds, progress)
    chosen_on = calibration_subset([s.scene for s in stacks], calibration_scenes)
    cal = calibrate_flip_curve([s for s in stacks if s.scene in chosen_on], max_early_stop, taus=taus,
                               candidates=candidates, tile=tile, estimates=oof, progress=progress)
    X, y = training_rows(list(tables.values()))
    estimator = TileErrorEstimator(**params).fit(X, y)
    calibration = {k: cal[k] for k in ("unit", "curve", "c", "target_early_stop_rate", "tile_truth", "rate")}
    record = {"scenes": sorted(tables), "calibration_scenes": sorted(chosen_on), "rows": int(len(y)),
              "params": estimator.get_params(),
              "band": list(BAND), "folds": folds, "seconds": round(time.perf_counter() - t0, 1),
              "out_of_fold_spread": {"estimate": needed_spread(stacks, oof), "halves_history": needed_spread(
                  stacks, {k: t.e_hist for k, t in tables.items()})}}
    return estimator, calibration, record
