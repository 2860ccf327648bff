"""Which composition of the half-buffer input generalises (`noisestop bench inputs`).

Each composition of `learning.inputs.noise_input.COMPOSITIONS` (and the paper's quick-image
inputs for reference) goes through the production pipeline: DSVM with C and gamma by
grouped cross-validation and the decision offset calibrated out of fold on the training
scenes (`train_model`), then judged on the held-out scenes through the stop rule. Rows
report the training scenes' out-of-fold figures next to the held-out ones, per scene the
worst number of early-stopped blocks, and the decision cost per block (features + SVM, one
thread): the speed knob next to its accuracy cost.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from noisefeat.runtime import median_s, torch_threads

from ..evaluation.evaluate import evaluate_model
from ..evaluation.generalisation import split_tables
from ..inputs.noise_input import COMPOSITIONS, halves_input
from ..inputs.table import SubImageTable, stack_halves_input
from ..models.bundle import Model
from .train import train_model

log = logging.getLogger(__name__)


def with_composition(table: SubImageTable, composition: str) -> SubImageTable:
    """`table` (a `halves` table) with its inputs rebuilt for another composition."""
    X = np.concatenate([stack_halves_input(table.stacks[s], composition=composition).reshape(
        table.stacks[s].n_levels * table.stacks[s].n_blocks, -1) for s in dict.fromkeys(table.scene)])
    return dataclasses.replace(table, X=X)


def per_block_ms(fn: Callable[[np.ndarray, np.ndarray], Any], block: tuple[int, int] = (64, 64),
                 n: int = 16, repeats: int = 5) -> float:
    """Median milliseconds per block of `fn(a, b)` on n half-buffer pairs, on one thread
    after a warm-up call: what a render pays per active block and decision."""
    rng = np.random.default_rng(0)
    a = rng.random((n, *block, 3)).astype(np.float32)
    b = (a + rng.normal(0, 0.02, a.shape)).astype(np.float32)
    with torch_threads(1):
        return 1000.0 * median_s(lambda: fn(a, b), repeats) / n


def decision_ms(model: Model, block: tuple[int, int] = (64, 64), n: int = 16, repeats: int = 5) -> float:
    """Milliseconds per block to turn half buffers (or a block and its quick image) into a score."""
    return per_block_ms(lambda a, b: model.score_halves(a, b) if model.needs_halves else model.score_blocks(a, b),
                        block, n, repeats)


def flip_ms() -> float:
    """The flip criterion's score (FLIP between the half buffers) per 64x64 block, timed alike."""
    return per_block_ms(lambda a, b: halves_input(a, b, composition="f"))


def _row(name: str, quick: str, train: SubImageTable, test: SubImageTable, data: str,
         composition: str | None = None) -> dict[str, Any]:
    t0 = time.perf_counter()
    est, summary = train_model("dsvm", data, table=train, test_scenes=[], quick=quick, progress=False,
                               max_early_stop=0.05)
    model = Model(est, {"kind": "dsvm", "input": "features", "quick": quick,
                        **({"composition": composition} if composition else {})})
    m = evaluate_model(model, test)
    conv = m.get("groups", {}).get("converging", m)
    cal = summary["calibration"]["chosen"]
    early_blocks = {s: int(ps["counts"]["early"]) for s, ps in m["per_scene"].items()}
    return {"input": name, "quick": quick, "composition": composition, "n_inputs": int(est.n_features_in_),
            "C": summary["C"], "gamma": summary["gamma"], "offset": summary["offset"],
            "train_oof_early": cal["out_of_fold"]["early_stop_rate"] if cal.get("out_of_fold") else None,
            "train_early": cal["early_stop_rate"], "train_ratio": cal["spp_ratio_vs_oracle"],
            "early_stop_rate": conv["early_stop_rate"], "spp_ratio_vs_oracle": conv["spp_ratio_vs_oracle"],
            "all_early_stop_rate": m["early_stop_rate"], "worst_scene_early_blocks": max(early_blocks.values()),
            "early_blocks": early_blocks, "support_vectors": est.n_support_,
            "decision_ms_per_block": decision_ms(model), "seconds": time.perf_counter() - t0}


def compare_inputs(data: str, heldout: str, compositions: tuple[str, ...] = COMPOSITIONS,
                   quick: tuple[str, ...] = ("albedo", "none")) -> dict[str, Any]:
    """One row per input: every composition of the half buffers, and the paper's quick inputs."""
    rows = []
    train, test = split_tables(data, heldout, quick="halves")
    for comp in compositions:
        log.info("inputs: halves %s", comp)
        rows.append(_row(f"halves {comp}", "halves", with_composition(train, comp),
                         with_composition(test, comp), data, comp))
    for q in quick:
        log.info("inputs: quick %s", q)
        rows.append(_row(f"quick {q}", q, *split_tables(data, heldout, quick=q), data))
    # the flip criterion's cost on the same blocks, for the cost column's scale
    return {"rows": rows, "flip_ms_per_block": flip_ms(), "train_scenes": train.scenes(),
            "heldout_scenes": test.scenes()}


def md_inputs(r: dict[str, Any]) -> str:
    lines = [f"Trained on {len(r['train_scenes'])} training scenes (DSVM, C and gamma by grouped CV, offset "
             "calibrated out of fold for <= 5 % early stops); judged on the held-out scenes that converge "
             "(early stops, samples) and per scene (worst count of early-stopped blocks out of 16).", "",
             "| input | columns | C | gamma | offset | training: early stops (out of fold) | training: "
             "samples / oracle | held-out: early_stop_rate | held-out: samples / oracle | worst held-out "
             "scene (early blocks) | decision ms / block |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        gamma = x["gamma"] if isinstance(x["gamma"], str) else f"{x['gamma']:.3g}"
        oof = "-" if x["train_oof_early"] is None else f"{x['train_oof_early']:.3f}"
        lines.append(f"| {x['input']} | {x['n_inputs']} | {x['C']:g} | {gamma} | {x['offset']:.1f} | {oof} | "
                     f"{x['train_ratio']:.2f} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} | "
                     f"{x['worst_scene_early_blocks']} | {x['decision_ms_per_block']:.2f} |")
    lines += ["", f"The FLIP value alone (part `f`, the flip criterion's score) costs "
                  f"{r['flip_ms_per_block']:.2f} ms per 64x64 block on one thread."]
    return "\n".join(lines)
