"""The metrics of DESIGN.md ("Metrics"), from per-(level, block) verdicts of one stack.

A criterion's verdicts for a stack form V [K, B] (+1 converged / -1 noisy) over its K
levels. A block stops at its first +1 level: T_pred = spp of that level, or
spp_max + step if never (it is then rendered to spp_max: samples *spent* are spp_max).
Censored true thresholds (None) count as spp_max + step.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

METRIC_NAMES = ("precision", "f1", "threshold_mse", "early_stop_rate", "spp_ratio_vs_oracle",
                "saved_vs_uniform")


def never_spp(spp: Sequence[int]) -> int:
    """The stand-in threshold for 'never converged': spp_max + step."""
    spp = list(spp)
    step = spp[-1] - spp[-2] if len(spp) > 1 else spp[-1]
    return int(spp[-1] + step)


def stop_thresholds(verdicts: np.ndarray, spp: Sequence[int]) -> np.ndarray:
    """T_pred per block from V [K, B]: spp of the first +1 level, never_spp if none."""
    v = np.asarray(verdicts) > 0
    spp_arr = np.asarray(spp)
    first = np.where(v.any(axis=0), v.argmax(axis=0), len(spp_arr))
    return np.where(first < len(spp_arr), spp_arr[np.minimum(first, len(spp_arr) - 1)], never_spp(spp))


def true_thresholds(thresholds: Sequence[int | None], spp: Sequence[int]) -> np.ndarray:
    return np.array([never_spp(spp) if t is None else int(t) for t in thresholds])


def stack_counts(verdicts: np.ndarray, labels: np.ndarray, thresholds: Sequence[int | None],
                 spp: Sequence[int], per_block: int | None = None) -> dict[str, float]:
    """Additive counts for one stack (summed over stacks, then turned into metrics).

    `per_block`: the units are tiles, this many a block (block-major): the counts then
    also hold how many blocks have an early tile, what a user sees as a block above tau
    at the end (`early_block_rate`)."""
    v = np.asarray(verdicts) > 0
    truth = np.asarray(labels) > 0
    t_pred = stop_thresholds(verdicts, spp)
    t_true = true_thresholds(thresholds, spp)
    spp_max = int(spp[-1])
    whole = {} if per_block is None else {
        "whole_blocks": len(t_true) // per_block,
        "blocks_with_early": int((t_pred < t_true).reshape(-1, per_block).any(axis=1).sum())}
    return {**whole,
        "n": v.size, "correct": int((v == truth).sum()),
        "tp": int((v & truth).sum()), "fp": int((v & ~truth).sum()), "fn": int((~v & truth).sum()),
        "blocks": len(t_true),
        "sq_err": float((((t_pred - t_true) / spp_max) ** 2).sum()),
        "early": int((t_pred < t_true).sum()),
        "spent": int(np.minimum(t_pred, spp_max).sum()),
        "oracle": int(np.minimum(t_true, spp_max).sum()),
        "uniform": spp_max * len(t_true),
    }


def metrics_from_counts(c: Mapping[str, float]) -> dict[str, float]:
    """precision, f1, threshold_mse, early_stop_rate, spp_ratio_vs_oracle, saved_vs_uniform."""
    denom = 2 * c["tp"] + c["fp"] + c["fn"]
    return {
        "precision": c["correct"] / c["n"] if c["n"] else float("nan"),
        # no converged sub-image anywhere and none predicted: F1 is perfect, not undefined
        "f1": 2 * c["tp"] / denom if denom else 1.0,
        "threshold_mse": c["sq_err"] / c["blocks"] if c["blocks"] else float("nan"),
        "early_stop_rate": c["early"] / c["blocks"] if c["blocks"] else float("nan"),
        "spp_ratio_vs_oracle": c["spent"] / c["oracle"] if c["oracle"] else float("nan"),
        "saved_vs_uniform": 1.0 - c["spent"] / c["uniform"] if c["uniform"] else float("nan"),
        **({"early_block_rate": c["blocks_with_early"] / c["whole_blocks"] if c["whole_blocks"] else float("nan")}
           if "whole_blocks" in c else {}),
        # the final frame's blocks above tau whose own truth converges (`add_end_counts`)
        **({"end_early_rate": c["end_early"] / c["end_blocks"] if c["end_blocks"] else 0.0}
           if "end_blocks" in c else {}),
    }


def add_end_counts(result: dict[str, Any], ends: Mapping[str, Mapping[str, float]]) -> dict[str, Any]:
    """`evaluate_verdicts`' result with what each scene's final frame shows (`ends`: scene ->
    `learning.data.tile_truth.FinalFrame.judge`) in its counts: ``end_blocks`` (blocks
    whose truth converges in the stack) and ``end_early`` (those the frame leaves above tau),
    and their rate ``end_early_rate``, per scene and pooled: the rate a tile-grain c is
    calibrated to (what the user judges, not early tiles)."""
    for scene, end in ends.items():
        entry = result["per_scene"][scene]
        entry["counts"].update(end_blocks=int(end["converging"]), end_early=int(end["early"]))
        entry.update(metrics_from_counts(entry["counts"]))
    result.update(metrics_from_counts(pool_counts(e["counts"] for e in result["per_scene"].values())))
    return result


def evaluate_verdicts(per_scene: Mapping[str, tuple[np.ndarray, np.ndarray, Sequence[int | None],
                                                     Sequence[int]]],
                      groups: Mapping[str, Sequence[str]] | None = None,
                      per_block: int | Mapping[str, int] | None = None) -> dict[str, Any]:
    """{scene: (V [K, B], labels [K, B], thresholds, spp)} -> metrics overall and per scene
    (each scene's entry also holds its additive `counts`, so that any subset of scenes can
    be pooled later: `pool_counts`).

    `groups` ({name: scenes}) adds ``groups`` (name -> metrics pooled over those scenes,
    absent when none of them was evaluated), e.g. scenes that converge inside their
    stacks apart from those that never do (`learning.evaluation.generalisation`).
    `per_block`: the units are tiles, this many a block (`stack_counts`), one number or
    one per scene."""
    counts: dict[str, dict[str, float]] = {}
    out: dict[str, Any] = {"per_scene": {}}
    for scene, (v, labels, th, spp) in sorted(per_scene.items()):
        counts[scene] = stack_counts(v, labels, th, spp,
                                     per_block.get(scene) if isinstance(per_block, Mapping) else per_block)
        out["per_scene"][scene] = {**metrics_from_counts(counts[scene]), "counts": counts[scene]}
    if not counts:
        raise ValueError("nothing to evaluate: no scenes")
    out.update(metrics_from_counts(pool_counts(counts.values())))
    if groups is not None:
        out["groups"] = {name: {**metrics_from_counts(pool_counts(counts[s] for s in scenes if s in counts)),
                                "scenes": [s for s in scenes if s in counts]}
                         for name, scenes in groups.items() if any(s in counts for s in scenes)}
    return out


def pool_counts(counts: Iterable[Mapping[str, float]]) -> dict[str, float]:
    """The sum of `stack_counts` dicts: metrics over several stacks pool their counts."""
    total: dict[str, float] = {}
    for c in counts:
        for k, val in c.items():
            total[k] = total.get(k, 0) + val
    return total
