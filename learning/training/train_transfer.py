"""Training a transfer baseline (`learning.models.transfer`) for a bundle, as `train_model`
does an SVM: on the training scenes of a picture table (`load_table(image=True)`), with the
decision offset calibrated on out-of-fold scores of those scenes through the stop rule.

The base is frozen, so its pooled features are computed once for every training row; each
calibration fold then refits only the head on them (seconds), instead of running the
conv base once per fold.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

from sklearn.base import clone

from ..evaluation.calibrate import calibrate_offset, score_offsets
from ..inputs.table import SubImageTable, load_table
from ..models.transfer import TransferClassifier
from ..names import TRANSFER_INPUTS, TRANSFER_KINDS
from .train import split_scenes

log = logging.getLogger(__name__)

def _head_on(clf: TransferClassifier, table: SubImageTable) -> TransferClassifier:
    """A new head fitted on the trainable rows of a table of base features, on `clf`'s base."""
    fold = clone(clf)
    for name in ("base_", "base_pretrained_", "base_weights_", "base_sha256_", "base_source_",
                 "base_fingerprint_", "block_shape_"):
        setattr(fold, name, getattr(clf, name))
    rows = table.trainable()
    return fold.fit(rows.X, rows.y.astype(int))


def train_transfer(arch: str, data: str, *, quick: str = "halves", weights: str | None = None,
                   test_scenes: list[str] | None = None, table: SubImageTable | None = None,
                   max_early_stop: float | None = None, seed: int = 0, epochs: int = 30,
                   batch_size: int = 64, progress: bool = True) -> tuple[TransferClassifier, dict[str, Any]]:
    """Fit `arch` (frozen base + the paper's head) on the training scenes of `data`; returns
    (fitted classifier, training summary for the manifest).

    `quick`: 'halves' (the noise picture of the half buffers) or 'none' (the block, the
    paper's). `weights`: a local ImageNet state_dict (None: the torch hub cache, else an
    untrained base, logged and labelled so). With `max_early_stop`, the offset is chosen on
    out-of-fold scores of the training scenes (`learning.evaluation.calibrate`)."""
    arch = arch.lower()
    if arch not in TRANSFER_KINDS:
        raise ValueError(f"unknown transfer baseline {arch!r}; one of {', '.join(TRANSFER_KINDS)}")
    if quick not in TRANSFER_INPUTS:
        raise ValueError(f"a transfer baseline reads {' or '.join(TRANSFER_INPUTS)}, not {quick!r}")
    t0 = time.perf_counter()
    table = table if table is not None else load_table(data, image=True, quick=quick, progress=progress)
    if table.X.ndim != 4:
        raise ValueError("a transfer baseline trains on a picture table (load_table(image=True))")
    train_scenes, test = split_scenes(table, test_scenes)
    train = table.subset(table.scene_mask(train_scenes))
    t_data = time.perf_counter() - t0
    summary: dict[str, Any] = {"kind": arch, "input": "image", "quick": quick, "train_scenes": train_scenes,
                               "test_scenes": test, "n_train": int(len(train)), "data": str(data),
                               "seed": seed, "table_s": t_data}
    t1 = time.perf_counter()
    clf = TransferClassifier(arch=arch, weights=weights, epochs=epochs, batch_size=batch_size,
                             random_state=seed, progress=progress)
    clf.prepare_base(train.trainable().X)       # BatchNorm statistics of an untrained base, if so
    t_base = time.perf_counter()
    feats = dataclasses.replace(train, X=clf.transform(train.X))     # the base runs once per row
    summary["features_s"] = time.perf_counter() - t_base
    fit_rows = feats.trainable()
    clf.fit(fit_rows.X, fit_rows.y.astype(int))
    summary.update(n_labels=int(len(fit_rows)), label_fraction=1.0, train_s=time.perf_counter() - t1,
                   base=clf.report_label(), base_source=clf.base_source_, weights=clf.base_weights_,
                   block=list(clf.block_shape_))
    if max_early_stop is not None:
        clf.offset_, summary["calibration"] = calibrate_offset(lambda sub: _head_on(clf, sub), feats, train_scenes,
                                                               max_early_stop, score_offsets, progress=progress)
    clf.set_params(progress=False)      # a bundle's verdicts draw no progress bars
    summary["offset"] = float(clf.offset_)
    summary["parameters"] = int(clf.n_parameters())
    log.info("%s: trained on %d scenes in %.1f s (base features %.1f s), offset %.2f", clf.report_label(),
             len(train_scenes), summary["train_s"], summary["features_s"], clf.offset_)
    return clf, summary
