"""Evaluation of a model on held-out scenes through the one stop rule: DESIGN metrics,
overall and per scene."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from noisefeat.runtime import median_s

from ..data.observer import label_tau
from ..inputs.halves import guard_dots
from ..inputs.table import SubImageTable
from ..models.bundle import Model
from ..stoprule import StopRule
from .generalisation import scene_groups
from .metrics import evaluate_verdicts


def by_scene(table: SubImageTable, values: np.ndarray) -> dict[str, np.ndarray]:
    """Per scene: a per-row column of `table` (scores, verdicts, flags) as [K, B]."""
    out = {}
    for scene, stack in table.stacks.items():
        m = table.scene == scene
        order = np.lexsort((table.block[m], table.level[m]))
        out[scene] = np.asarray(values)[m][order].reshape(stack.n_levels, stack.n_blocks)
    return out


def scores_by_scene(table: SubImageTable, scores: np.ndarray) -> dict[str, np.ndarray]:
    """Per scene [K, B]: per-row `scores` as the stop rule reads them in the live loop: -inf
    where there is no input yet, NaN (no stop) where a `halves` table's dot guard holds the
    row at its stack's tau (`learning.inputs.halves.guard_dots`)."""
    s = by_scene(table, np.where(table.decidable, scores, -np.inf))   # no input yet: never stops (unless flat)
    if table.dots is None:
        return s
    dots = by_scene(table, table.dots)
    return {scene: guard_dots(s[scene], dots[scene], label_tau(st)) for scene, st in table.stacks.items()}


def stops_by_scene(table: SubImageTable, scores: np.ndarray, rule: StopRule) -> dict[str, tuple]:
    """Per scene: (held verdicts V [K, B], labels, thresholds, spp) for learning.evaluation.metrics,
    the stops `rule` makes from per-row `scores` (flat sub-images stop at once)."""
    s, flat, labels = scores_by_scene(table, scores), by_scene(table, table.flat), by_scene(table, table.y)
    return {scene: (rule.stops(s[scene], st.spp, flat[scene]), labels[scene], st.thresholds, st.spp)
            for scene, st in table.stacks.items()}


def evaluate_scores(table: SubImageTable, scores: np.ndarray, rule: StopRule) -> dict[str, Any]:
    """DESIGN metrics of the stops `rule` makes from `scores`: overall, per scene, and per
    group (scenes that converge inside their stacks apart from those that do not)."""
    return evaluate_verdicts(stops_by_scene(table, scores, rule), scene_groups(table.stacks.values()))


def evaluate_model(model: Model, table: SubImageTable, offset: float | None = None,
                   min_spp: int | None = None) -> dict[str, Any]:
    """Metrics of `model` on every scene of `table` (restrict the table to held-out scenes),
    at its own offset or `offset`; no decision below `min_spp` (None: from the first level)."""
    t0 = time.perf_counter()
    rule = model.rule(offset, min_spp)
    result = evaluate_scores(table, model.decision_function(table.X), rule)
    result["offset"] = rule.offset
    result["n_sub_images"] = int(len(table))
    result["scenes"] = table.scenes()
    result["predict_s"] = time.perf_counter() - t0
    return result


def time_101_sub_images(model: Model, block: tuple[int, int], repeats: int = 20) -> float:
    """Seconds to classify 101 sub-images from linear RGB, features included (paper: 0.008 s);
    a `halves` model reads two half buffers per sub-image."""
    rng = np.random.default_rng(0)
    blocks = rng.random((101, *block, 3)).astype(np.float32)
    other = rng.random((101, *block, 3)).astype(np.float32)     # the quick image, or the odd half

    def score() -> None:
        model.score_halves(blocks, other) if model.needs_halves else model.score_blocks(blocks, other)
    return median_s(score, repeats)
