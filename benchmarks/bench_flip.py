"""`noisestop bench flip`: the batched LDR-FLIP (noisefeat.flip) against flip-evaluator, its
speed and its agreement on every stored (level, block).
"""
from __future__ import annotations

import logging
from typing import Any
import numpy as np
import torch
from .timing import interleaved_medians
from noisefeat.extras import require

log = logging.getLogger(__name__)


def _flip_evaluator_threads(n: int) -> bool:
    """Set flip-evaluator's OpenMP threads (its own bundled libgomp, which torch's
    set_num_threads does not reach); False if that library cannot be found."""
    import ctypes
    import glob
    import os

    flip_evaluator = require("flip_evaluator")
    libs = glob.glob(os.path.join(os.path.dirname(flip_evaluator.__file__), os.pardir,
                                  "flip_evaluator.libs", "libgomp*"))
    try:
        ctypes.CDLL(libs[0]).omp_set_num_threads(int(n))
    except (IndexError, OSError, AttributeError):
        return False
    return True


def flip_bench_halves(n: int, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n pairs of half buffers [size, size, 3]: smooth coloured shading with an edge, and
    two independent noisy estimates of it (what a render's half buffers look like)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    base = rng.random((n, 1, 1, 3)) * 0.6 * (0.3 + x + 0.5 * (y > 0.6))[None, ..., None]
    a, b = (base * (1 + 0.1 * rng.standard_normal(base.shape[:3] + (3,))) for _ in range(2))
    return np.clip(a, 0, None).astype(np.float32), np.clip(b, 0, None).astype(np.float32)


def flip_agreement(root: str) -> dict[str, Any]:
    """Both routes on every (level, block) of the labelled stacks under `root` whose
    calibration and bundled-model figures are on record: how far e differs, and whether any
    decision does, at every candidate c of the flip criterion and for the bundled model at
    its offset (only blocks flip would be asked about: not flat, level >= 1). Reads the
    stacks, writes nothing (no cache)."""
    from learning.data.dataset_dir import list_stacks
    from learning.data.stack import read_stack
    from learning.evaluation.calibrate import FLIP_CANDIDATES
    from learning.inputs.halves import halves_flip, halves_flip_evaluator
    from learning.inputs.halves import iter_stack_halves
    from learning.inputs.noise_input import compose
    from learning.models.bundle import load_model
    from learning.stoprule import flat_blocks

    old, new = [], []
    for path in list_stacks(root):
        stack = read_stack(path)
        for k, even, odd in iter_stack_halves(stack):
            ask = np.flatnonzero(~flat_blocks(stack.blocks(k)))
            if ask.size:
                old.append(halves_flip_evaluator(even[ask], odd[ask]))
                new.append(halves_flip(even[ask], odd[ask]))
    if not old:
        raise ValueError(f"{root}: no blocks to compare (no stacks, or every block flat)")
    e_old, e_new = np.concatenate(old), np.concatenate(new)
    model = load_model(None)
    s_old, s_new = (model.decision_function(compose(None, e, model.composition or "f")) for e in (e_old, e_new))
    resolved = e_old >= 1e-3
    rel = np.abs(e_new - e_old) / np.maximum(e_old, 1e-300)
    return {"root": root, "values": int(e_old.size), "below_1e-3": int((~resolved).sum()),
            "max_rel_diff": float(rel[resolved].max()) if resolved.any() else None,
            "median_rel_diff": float(np.median(rel)), "max_abs_diff": float(np.abs(e_new - e_old).max()),
            "flip_candidates": len(FLIP_CANDIDATES),
            "flip_verdict_changes": int(sum(((e_old <= c) != (e_new <= c)).sum() for c in FLIP_CANDIDATES)),
            "model": model.name, "model_composition": model.composition, "model_offset": model.offset,
            "model_max_score_diff": float(np.abs(s_new - s_old).max()),
            "model_max_score_diff_resolved": float(np.abs(s_new - s_old)[resolved].max()) if resolved.any() else None,
            "model_verdict_changes": int(((s_old > model.offset) != (s_new > model.offset)).sum())}


def bench_flip(repeats: int = 30, shapes: tuple[tuple[int, int], ...] = ((16, 64), (16, 128)),
               threads: tuple[int, ...] = (1, 2), datasets: tuple[str, ...] = ()) -> dict[str, Any]:
    """FLIP between the half buffers (the flip criterion's score, the bundled model's input
    `f`), warm, median of repeats: flip-evaluator one block per call (the reference) against
    noisefeat.flip, all blocks at once, at each thread count; how closely they agree, here
    and on every block of the labelled `datasets` (`flip_agreement`)."""
    import os

    from learning.inputs.halves import halves_flip, halves_flip_evaluator

    load = [os.getloadavg()[0]]
    before = torch.get_num_threads()
    rows = []
    try:
        for t in threads:
            torch.set_num_threads(t)
            set_old = _flip_evaluator_threads(t)
            for n, size in shapes:
                a, b = flip_bench_halves(n, size)
                new, old = halves_flip(a, b), halves_flip_evaluator(a, b)
                t_new, t_old = interleaved_medians(lambda: halves_flip(a, b), lambda: halves_flip_evaluator(a, b),
                                                    repeats, max(3, repeats // 6))
                rows.append({"threads": t, "evaluator_threads_set": set_old, "blocks": n, "size": size,
                             "evaluator_ms": t_old * 1e3, "torch_ms": t_new * 1e3, "speedup": t_old / t_new,
                             "max_rel_diff": float(np.max(np.abs(new - old) / old)), "mean_e": float(old.mean())})
    finally:
        torch.set_num_threads(before)
        _flip_evaluator_threads(os.cpu_count() or 1)
    load.append(os.getloadavg()[0])
    return {"rows": rows, "cpus": os.cpu_count(), "load_avg": load, "repeats": repeats,
            "pooling": pooling_cost(repeats), "datasets": [flip_agreement(d) for d in datasets]}


def pooling_cost(repeats: int = 30, shapes: tuple[tuple[int, int], ...] = ((1, 64), (16, 64), (16, 128))
                 ) -> list[dict[str, Any]]:
    """What the criterion's tile pooling (`CRITERION_POOLING`: the largest 8x8 tile mean)
    adds to the flip criterion's cost against the block mean: the whole score (FLIP and
    pooling) both ways, on one torch thread as the render loop decides, interleaved medians."""
    from learning.inputs.halves import halves_flip
    from noisefeat.pooling import CRITERION_POOLING
    from noisefeat.runtime import torch_threads

    rows = []
    with torch_threads(1):
        for n, size in shapes:
            a, b = flip_bench_halves(n, size, seed=1)
            t_tile, t_mean = interleaved_medians(lambda: halves_flip(a, b, pooling=CRITERION_POOLING),
                                                 lambda: halves_flip(a, b, pooling="mean"), repeats, repeats)
            rows.append({"blocks": n, "size": size, "pooling": CRITERION_POOLING, "tile_ms": t_tile * 1e3,
                         "mean_ms": t_mean * 1e3, "added": t_tile / t_mean - 1.0})
    return rows


def md_flip(r: dict[str, Any]) -> str:
    lines = [f"Median of {r['repeats']} warm calls (flip-evaluator: of {max(3, r['repeats'] // 6)}, interleaved), "
             f"{r['cpus']} CPUs, load average {r['load_avg'][0]:.1f} before and {r['load_avg'][1]:.1f} after "
             "(above the thread count means other work shared the CPUs).", "",
             "| threads | blocks per call | flip-evaluator, per call (ms) | per block (ms) | noisefeat.flip, "
             "per call (ms) | per block (ms) | speed-up | max relative difference of e |",
             "|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(f"| {x['threads']} | {x['blocks']} of {x['size']}x{x['size']} | {x['evaluator_ms']:.1f} | "
                     f"{x['evaluator_ms'] / x['blocks']:.2f} | {x['torch_ms']:.1f} | {x['torch_ms'] / x['blocks']:.3f} | "
                     f"{x['speedup']:.1f}x | {x['max_rel_diff']:.1e} |")
    if r.get("pooling"):
        lines += ["", "What the tile pooling adds to the flip criterion's score (FLIP between the halves, then "
                  "the largest tile mean instead of the block mean), one torch thread, interleaved medians "
                  "(goal: under 5 %):", "",
                  "| blocks per call | tile pooling (ms) | block mean (ms) | added |", "|---|---|---|---|"]
        for x in r["pooling"]:
            lines.append(f"| {x['blocks']} of {x['size']}x{x['size']} | {x['tile_ms']:.3f} ({x['pooling']}) | "
                         f"{x['mean_ms']:.3f} | {x['added']:+.1%} |")
    if r.get("datasets"):
        lines += ["", "The two routes on every block the flip criterion is asked about (not flat, level >= 1) of "
                  "the labelled stacks, and the decisions taken from them:", "",
                  "| stacks | values of e | max relative difference (e >= 1e-3) | median relative difference "
                  "| max absolute difference | flip verdicts changed, over every candidate c "
                  "| bundled model: max score difference (e >= 1e-3 / all) | its verdicts changed |",
                  "|---|---|---|---|---|---|---|---|"]
        for d in r["datasets"]:
            def g(v: float | None) -> str:
                return "-" if v is None else f"{v:.1e}"
            lines.append(f"| {d['root']} | {d['values']} ({d['below_1e-3']} below 1e-3) | {g(d['max_rel_diff'])} | "
                         f"{g(d['median_rel_diff'])} | {g(d['max_abs_diff'])} | {d['flip_verdict_changes']} "
                         f"({d['flip_candidates']} values of c) | {g(d['model_max_score_diff_resolved'])} / "
                         f"{g(d['model_max_score_diff'])} | {d['model_verdict_changes']} (offset "
                         f"{d['model_offset']:g}) |")
    return "\n".join(lines)
