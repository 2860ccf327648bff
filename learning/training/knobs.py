"""Training's speed knobs, each beside its measured accuracy cost on held-out scenes.

* The cross-validation cap: grouped 5-fold CV over the 4 x 4 grid of C and gamma is 80 SVM
  fits; the supervised kinds run it on at most `cv_max_samples` rows (whole groups).
* The active-learning batch: labels bought per query round. A larger batch means fewer
  refits (faster) and less informed queries (the paper used batch mode too).

Each setting trains the same kind on the same training scenes; what changes is the knob.
"""
from __future__ import annotations

import time
from typing import Any

from ..evaluation.evaluate import evaluate_model
from ..evaluation.generalisation import split_tables
from ..models.bundle import Model
from .train import AL_BATCH, CV_MAX_SAMPLES, train_model

METRICS = ("precision", "f1", "early_stop_rate", "spp_ratio_vs_oracle")


def measure_knobs(data: str, heldout: str | None = None, quick: str = "none",
                  cv_caps: tuple[int, ...] = (1000, CV_MAX_SAMPLES, 0),
                  batches: tuple[int, ...] = (8, AL_BATCH, 64)) -> dict[str, Any]:
    """Rows of {knob, value, default, seconds, metrics...}: DSVM over the CV cap (0 = every
    training row), DSVM_AS over the active-learning batch size; trained on the training
    scenes, scored on the held-out ones (learning.evaluation.generalisation)."""
    table, test = split_tables(data, heldout, quick=quick)
    rows = []

    def row(knob: str, value: Any, default: bool, kind: str, **kw: Any) -> None:
        t0 = time.perf_counter()
        est, summary = train_model(kind, data, table=table, test_scenes=[], quick=quick, progress=False, **kw)
        seconds = time.perf_counter() - t0
        m = evaluate_model(Model(est, {"kind": kind, "input": "features", "quick": quick}), test)
        rows.append({"knob": knob, "kind": kind, "value": value, "default": default, "seconds": seconds,
                     "cv_rows": summary.get("cv_rows"), "labels": summary.get("n_labels"),
                     "C": summary["C"], "gamma": summary["gamma"], **{k: m[k] for k in METRICS}})

    for cap in cv_caps:
        row("cross-validation rows", cap or "all", cap == CV_MAX_SAMPLES, "dsvm", cv_max_samples=cap)
    for b in batches:
        row("active-learning batch", b, b == AL_BATCH, "dsvm_as", batch_size=b)
    return {"quick": quick, "rows": rows}
