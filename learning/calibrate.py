"""Choosing the decision offset: the speed/accuracy knob of a model criterion.

A block stops at its first level with f(x) > offset, so raising the offset trades samples
for fewer early stops. The offset is calibrated without touching held-out scenes: each
training scene is scored by a model trained on the other training scenes (leave one scene
out), and the smallest offset whose out-of-fold early-stop rate meets the target is kept.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from .evaluate import verdicts_by_scene
from .metrics import evaluate_verdicts
from .table import SubImageTable

log = logging.getLogger(__name__)

DEFAULT_OFFSETS = tuple(np.round(np.arange(-1.0, 3.01, 0.1), 2))


def out_of_fold_scores(fit: Callable[[SubImageTable], Any], table: SubImageTable,
                       scenes: Sequence[str], progress: bool = False) -> np.ndarray:
    """f(x) for every row of `scenes`, each scene scored by a model fit without it."""
    scores = np.full(len(table), np.nan)
    for s in tqdm(scenes, desc="leave-one-scene-out", disable=not progress, leave=False):
        rest = [t for t in scenes if t != s]
        model = fit(table.subset(table.scene_mask(rest)))
        m = table.scene == s
        scores[m] = model.decision_function(table.X[m])
    return scores


def sweep(scores: np.ndarray, table: SubImageTable, offsets: Sequence[float] = DEFAULT_OFFSETS) -> list[dict]:
    """Metrics at each offset, for the rows of `table` that have a finite score."""
    rows = []
    keep = np.isfinite(scores)
    sub = table.subset(keep)
    for off in offsets:
        v = np.where(scores[keep] > off, 1, -1)
        m = evaluate_verdicts(verdicts_by_scene(sub, v))
        rows.append({"offset": float(off), **{k: m[k] for k in m if k != "per_scene"}})
    return rows


def choose_offset(curve: list[dict], max_early_stop: float = 0.05) -> dict:
    """The smallest offset (fewest samples) whose early-stop rate is within the target."""
    ok = [r for r in curve if r["early_stop_rate"] <= max_early_stop]
    if not ok:
        best = min(curve, key=lambda r: (r["early_stop_rate"], r["spp_ratio_vs_oracle"]))
        log.warning("no offset reaches early_stop_rate <= %.3f; the safest (%.3f at %.2f) is used",
                    max_early_stop, best["early_stop_rate"], best["offset"])
        return best
    return min(ok, key=lambda r: r["offset"])
