"""The issue-4 comparison: every model kind, trained with scenes held out, on one table.

Columns: precision, f1, threshold_mse, early_stop_rate, labels queried (and % of the
pool), support vectors, parameters, training time, test time for 101 sub-images (features
included). Written as JSON and as the markdown table BENCHMARKS.md quotes.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from .bundle import Model
from .calibrate import DEFAULT_OFFSETS, sweep
from .evaluate import evaluate_model, time_101_sub_images
from .metrics import evaluate_verdicts
from .plots import plot_learning_curves
from .table import SubImageTable, load_table
from .train import SVM_KINDS, split_scenes, train_model

log = logging.getLogger(__name__)
TRANSFER_ARCHES = ("vgg19", "mobilenet_v2", "inception_v3", "resnet50", "densenet201")
PAPER = {"dsvm_as": "91 % / 93.4 %, 0.008 s per 101, 2095 s training", "svm_as": "99 %"}


def _svm_row(kind: str, data: str, table: SubImageTable, test_scenes,
             quick: str = "albedo") -> tuple[dict, Any, dict]:
    est, summary = train_model(kind, data, table=table, test_scenes=test_scenes, progress=False,
                               quick=quick)
    model = Model(est, {"kind": kind, "input": summary["input"], "quick": quick})
    mask = table.scene_mask(summary["test_scenes"])
    test = table.subset(mask)
    m = evaluate_model(model, test)
    scores = np.full(len(table), np.nan)
    scores[mask] = est.decision_function(table.X[mask])
    block = next(iter(table.stacks.values())).block
    row = {"model": kind, **{k: m[k] for k in ("precision", "f1", "threshold_mse", "early_stop_rate",
                                                "spp_ratio_vs_oracle")},
           "labels": summary.get("n_labels"), "label_fraction": summary.get("label_fraction"),
           "queries": summary.get("n_queries"), "pool": summary.get("n_pool"),
           "query_fraction": summary.get("query_fraction"),
           "support_vectors": est.n_support_, "parameters": est.n_parameters(),
           "train_s": summary["train_s"], "test_101_s": time_101_sub_images(model, tuple(block)),
           "C": summary["C"], "gamma": summary["gamma"],
           # the speed/accuracy knob: held-out metrics at each decision offset
           "offset_curve": sweep(scores, table, DEFAULT_OFFSETS)}
    return row, est, summary


def rgb_blocks(table: SubImageTable, scenes: list[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Linear RGB sub-images [n, h, w, 3] of the given scenes, in table row order."""
    xs, ys, index = [], [], {}
    for s in scenes:
        st = table.stacks[s]
        xs.append(np.concatenate([st.blocks(k) for k in range(st.n_levels)]))
        ys.append(st.labels().reshape(-1))
        index[s] = st
    return np.concatenate(xs), np.concatenate(ys).astype(int), index


def _transfer_row(arch: str, table: SubImageTable, train_scenes, test_scenes) -> dict:
    from .transfer import TransferClassifier
    Xtr, ytr, _ = rgb_blocks(table, train_scenes)
    Xte, yte, stacks = rgb_blocks(table, test_scenes)
    clf = TransferClassifier(arch=arch).prepare_base(Xtr[:1024])
    t0 = time.perf_counter()
    Ftr = clf.transform(Xtr)
    clf.fit(Ftr, ytr)
    train_s = time.perf_counter() - t0
    Fte = clf.transform(Xte)
    verdict = clf.predict(Fte)
    per, off = {}, 0
    for s in test_scenes:
        st = stacks[s]
        n = st.n_levels * st.n_blocks
        per[s] = (verdict[off:off + n].reshape(st.n_levels, st.n_blocks),
                  yte[off:off + n].reshape(st.n_levels, st.n_blocks), st.thresholds, st.spp)
        off += n
    m = evaluate_verdicts(per)
    sample = Xte[:101]
    clf.decision_function(sample)
    t1 = time.perf_counter()
    clf.decision_function(sample)
    return {"model": clf.report_label(), **{k: m[k] for k in ("precision", "f1", "threshold_mse",
                                                               "early_stop_rate", "spp_ratio_vs_oracle")},
            "labels": int(len(ytr)), "label_fraction": 1.0, "queries": None, "pool": None,
            "query_fraction": None, "support_vectors": None, "parameters": clf.n_parameters(),
            "train_s": train_s, "test_101_s": time.perf_counter() - t1}


def compare_models(data: str, out_dir: str | Path, kinds=SVM_KINDS, arches=TRANSFER_ARCHES,
                   test_scenes: list[str] | None = None, quick: str = "albedo") -> dict[str, Any]:
    out_dir = Path(out_dir)
    feats = load_table(data, progress=False, quick=quick)
    raw = load_table(data, raw=True, progress=False) if any(k.startswith("svm") for k in kinds) else None
    train_scenes, test = split_scenes(feats, test_scenes)
    rows, histories, fitted = [], {}, {}
    for kind in kinds:
        log.info("comparison: training %s", kind)
        row, est, summary = _svm_row(kind, data, raw if kind.startswith("svm") else feats, test, quick)
        rows.append(row)
        fitted[kind] = (est, summary)
        if "history" in summary:
            histories[kind] = summary["history"]
    for arch in arches:
        log.info("comparison: transfer baseline %s", arch)
        try:
            rows.append(_transfer_row(arch, feats, train_scenes, test))
        except (ImportError, RuntimeError, ValueError) as exc:
            log.error("transfer baseline %s unavailable: %s", arch, exc)
            rows.append({"model": f"{arch} (unavailable: {exc})"})
    curves = None
    if histories:
        pool = next(iter(fitted[k][1].get("n_pool") for k in histories))
        curves = str(plot_learning_curves(histories, out_dir / f"precision-vs-queries-{quick}.png", pool))
    return {"rows": rows, "train_scenes": train_scenes, "test_scenes": test,
            "curves": curves, "fitted": fitted}


def markdown_table(rows: list[dict]) -> str:
    head = ("| model | precision | f1 | threshold_mse | early_stop_rate | labels queried (% pool) "
            "| support vectors | parameters | training (s) | test, 101 sub-images (s) |")
    lines = [head, "|" + "---|" * 10]

    def num(v, fmt):
        return "-" if v is None else format(v, fmt)
    for r in rows:
        if "precision" not in r:
            lines.append(f"| {r['model']} |" + " - |" * 9)
            continue
        q = "all (supervised)" if r.get("queries") is None else \
            f"{r['queries']} ({100 * r['query_fraction']:.1f} %)"
        lines.append(f"| {r['model']} | {r['precision']:.3f} | {r['f1']:.3f} | {r['threshold_mse']:.4f} "
                     f"| {r['early_stop_rate']:.3f} | {q} | {num(r['support_vectors'], 'd')} "
                     f"| {num(r['parameters'], ',d')} | {r['train_s']:.1f} | {r['test_101_s']:.4f} |")
    return "\n".join(lines)
