"""The model comparison: every model kind, trained on the training scenes and judged on
held-out ones (learning.evaluation.generalisation), on one table.

Columns: precision, f1, threshold_mse, early_stop_rate, labels queried (and % of the
pool), support vectors, parameters, training time, test time for 101 sub-images (features
included). Every verdict goes through the one stop rule (offset 0: the hyperplane; each
row also keeps its held-out offset curve). Written as JSON and as the markdown table
BENCHMARKS.md quotes.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from ..evaluation.calibrate import DEFAULT_OFFSETS, sweep
from ..evaluation.evaluate import evaluate_model, evaluate_scores, time_101_sub_images
from ..evaluation.generalisation import scene_groups, split_tables
from ..evaluation.plots import plot_learning_curves
from ..inputs.table import rgb_blocks
from ..inputs.table import SubImageTable
from ..models.bundle import Model
from ..stoprule import StopRule
from ..names import SVM_KINDS, TRANSFER_KINDS
from .train import train_model

log = logging.getLogger(__name__)
TRANSFER_ARCHES = TRANSFER_KINDS
PAPER = {"dsvm_as": "91 % / 93.4 %, 0.008 s per 101, 2095 s training", "svm_as": "99 %"}


def _svm_row(kind: str, data: str, train: SubImageTable, test: SubImageTable,
             quick: str = "albedo") -> tuple[dict, Any, dict]:
    est, summary = train_model(kind, data, table=train, test_scenes=[], monitor=test, progress=False,
                               quick=quick)
    model = Model(est, {"kind": kind, "input": summary["input"], "quick": quick})
    m = evaluate_model(model, test)
    block = next(iter(test.stacks.values())).block
    row = {"model": kind, **{k: m[k] for k in ROW_METRICS}, "groups": m.get("groups", {}),
           "labels": summary.get("n_labels"), "label_fraction": summary.get("label_fraction"),
           "queries": summary.get("n_queries"), "pool": summary.get("n_pool"),
           "query_fraction": summary.get("query_fraction"),
           "support_vectors": est.n_support_, "parameters": est.n_parameters(),
           "train_s": summary["train_s"], "test_101_s": time_101_sub_images(model, tuple(block)),
           "C": summary["C"], "gamma": summary["gamma"],
           # the speed/accuracy knob: held-out metrics at each decision offset (the stop rule)
           "offset_curve": _curve(sweep(est.decision_function(test.X), test, DEFAULT_OFFSETS))}
    return row, est, summary


def _curve(rows: list[dict]) -> list[dict]:
    """An offset curve as saved: overall metrics and the converging group, not every scene."""
    return [{k: v for k, v in r.items() if k != "per_scene"} for r in rows]


ROW_METRICS = ("precision", "f1", "threshold_mse", "early_stop_rate", "spp_ratio_vs_oracle")


def _transfer_row(arch: str, train: SubImageTable, test: SubImageTable, halves: bool = False) -> dict:
    from ..models.transfer import TransferClassifier
    train = train.trainable()
    Xtr = rgb_blocks(train, halves)
    clf = TransferClassifier(arch=arch).prepare_base(Xtr[:1024])
    t0 = time.perf_counter()
    Ftr = clf.transform(Xtr)
    del Xtr
    clf.fit(Ftr, train.y.astype(int))
    train_s = time.perf_counter() - t0
    Xte = rgb_blocks(test, halves)
    scores = clf.decision_function(clf.transform(Xte))
    m = evaluate_scores(test, scores, StopRule(float(clf.offset_)))
    sample = Xte[:101]
    clf.decision_function(sample)
    t1 = time.perf_counter()
    clf.decision_function(sample)
    return {"model": clf.report_label() + (" on the noise image" if halves else ""),
            **{k: m[k] for k in ROW_METRICS}, "groups": m.get("groups", {}),
            "labels": int(len(train)), "label_fraction": 1.0, "queries": None, "pool": None,
            "query_fraction": None, "support_vectors": None, "parameters": clf.n_parameters(),
            "train_s": train_s, "test_101_s": time.perf_counter() - t1}


def compare_models(data: str, out_dir: str | Path, kinds=SVM_KINDS, arches=TRANSFER_ARCHES,
                   heldout: str | None = None, quick: str = "albedo") -> dict[str, Any]:
    """Every kind trained on the training scenes of `data`, judged on `heldout`'s scenes
    (learning.evaluation.generalisation: without `heldout`, a quarter of `data` is held out)."""
    out_dir = Path(out_dir)
    feats = split_tables(data, heldout, quick=quick)
    # raw-pixel kinds read the block itself (the paper's) or, with halves, the noise image
    raw = split_tables(data, heldout, raw=True, quick="halves" if quick == "halves" else "none") \
        if any(k.startswith("svm") for k in kinds) else None
    rows, histories, fitted = [], {}, {}
    for kind in kinds:
        log.info("comparison: training %s", kind)
        train, test = raw if kind.startswith("svm") else feats
        row, est, summary = _svm_row(kind, data, train, test, quick)
        rows.append(row)
        fitted[kind] = (est, summary)
        if "history" in summary:
            histories[kind] = summary["history"]
    for arch in arches:
        log.info("comparison: transfer baseline %s", arch)
        try:
            rows.append(_transfer_row(arch, *feats, halves=quick == "halves"))
        except (ImportError, RuntimeError, ValueError) as exc:
            log.error("transfer baseline %s unavailable: %s", arch, exc)
            rows.append({"model": f"{arch} (unavailable: {exc})"})
    curves = None
    if histories:
        pool = next(iter(fitted[k][1].get("n_pool") for k in histories))
        curves = str(plot_learning_curves(histories, out_dir / f"precision-vs-queries-{quick}.png", pool))
    return {"rows": rows, "train_scenes": feats[0].scenes(), "test_scenes": feats[1].scenes(),
            "groups": scene_groups(feats[1].stacks.values()), "heldout": heldout,
            "curves": curves, "fitted": fitted}


def markdown_table(rows: list[dict]) -> str:
    head = ("| model | precision | f1 | threshold_mse | early_stop_rate | converging scenes: early stops, "
            "samples / oracle | labels queried (% pool) | support vectors | parameters | training (s) "
            "| test, 101 sub-images (s) |")
    lines = [head, "|" + "---|" * 11]

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)
    for r in rows:
        if "precision" not in r:
            lines.append(f"| {r['model']} |" + " - |" * 10)
            continue
        q = "all (supervised)" if r.get("queries") is None else \
            f"{r['queries']} ({100 * r['query_fraction']:.1f} %)"
        g = (r.get("groups") or {}).get("converging")
        conv = f"{g['early_stop_rate']:.3f}, {g['spp_ratio_vs_oracle']:.3f}" if g else "-"
        lines.append(f"| {r['model']} | {r['precision']:.3f} | {r['f1']:.3f} | {r['threshold_mse']:.4f} "
                     f"| {r['early_stop_rate']:.3f} | {conv} | {q} | {num(r['support_vectors'], 'd')} "
                     f"| {num(r['parameters'], ',d')} | {r['train_s']:.1f} | {r['test_101_s']:.4f} |")
    return "\n".join(lines)
