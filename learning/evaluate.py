"""Evaluation of a model on held-out scenes: DESIGN metrics, overall and per scene."""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from .bundle import Model
from .metrics import evaluate_verdicts
from .table import SubImageTable


def verdicts_by_scene(table: SubImageTable, verdict: np.ndarray) -> dict[str, tuple]:
    """Per scene: (V [K, B], labels [K, B], thresholds, spp) for learning.metrics."""
    out = {}
    for scene, stack in table.stacks.items():
        m = table.scene == scene
        k, b = stack.n_levels, stack.n_blocks
        order = np.lexsort((table.block[m], table.level[m]))
        v = verdict[m][order].reshape(k, b)
        labels = table.y[m][order].reshape(k, b)
        out[scene] = (v, labels, stack.thresholds, stack.spp)
    return out


def evaluate_model(model: Model, table: SubImageTable) -> dict[str, Any]:
    """Metrics of `model` on every scene of `table` (restrict the table to held-out scenes)."""
    t0 = time.perf_counter()
    verdict = model.predict(table.X)
    result = evaluate_verdicts(verdicts_by_scene(table, verdict))
    result["n_sub_images"] = int(len(table))
    result["scenes"] = table.scenes()
    result["predict_s"] = time.perf_counter() - t0
    return result


def time_101_sub_images(model: Model, block: tuple[int, int], repeats: int = 20) -> float:
    """Seconds to classify 101 sub-images from linear RGB, features included (paper: 0.008 s)."""
    rng = np.random.default_rng(0)
    blocks = rng.random((101, *block, 3)).astype(np.float32)
    quick = rng.random((101, *block, 3)).astype(np.float32)
    model.score_blocks(blocks, quick)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        model.score_blocks(blocks, quick)
        times.append(time.perf_counter() - t)
    return float(np.median(times))
