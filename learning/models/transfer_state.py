"""Saving and loading a `transfer.TransferClassifier`: safetensors and JSON, no pickle.

A directory holds the head's tensors (`TENSOR_FILE`), with a fine-tuned base or an untrained
base's BatchNorm statistics, and the parameters and provenance (`STATE_FILE`); a frozen
pretrained base is referenced by its weights file and SHA-256, not copied (hundreds of MB),
and a rebuilt base must match the fingerprint of the one the head was trained on.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TypeVar

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.utils.validation import check_is_fitted

from noisefeat.atomic import atomic_write
from noisefeat.safeio import read_input, read_json

from .bundle_check import file_sha256
from .estimators import LABELS
from .transfer_net import build_base, fingerprint, make_head

STATE_FILE = "transfer.json"
TENSOR_FILE = "transfer.safetensors"
#: the classifier class `load_classifier` rebuilds (`transfer.TransferClassifier`)
Classifier = TypeVar("Classifier", bound=BaseEstimator)


def save_classifier(est: BaseEstimator, path: str | os.PathLike) -> Path:
    """Write the head to a directory, with a fine-tuned base or an untrained base's
    BatchNorm statistics; a frozen pretrained base is referenced by its weights file and
    SHA-256, not copied (hundreds of MB)."""
    from safetensors.torch import save_file

    check_is_fitted(est, "head_")
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    tensors = {f"head.{k}": v.contiguous() for k, v in est.head_.state_dict().items()}
    if not est.freeze_base or not est.base_pretrained_:  # fine-tuned / calibrated base
        keep = None if not est.freeze_base else {k for k, _ in est.base_.named_buffers()}
        tensors.update({f"base.{k}": v.contiguous() for k, v in est.base_.state_dict().items()
                        if keep is None or k in keep})
    atomic_write(path / TENSOR_FILE, lambda tmp: save_file(tensors, str(tmp)))
    state = {"params": est.get_params(), "base_pretrained": est.base_pretrained_,
             "base_weights": est.base_weights_, "base_sha256": est.base_sha256_,
             "base_source": est.base_source_, "base_fingerprint": est.base_fingerprint_,
             "block_shape": list(getattr(est, "block_shape_", ()) or []) or None,
             "offset": float(est.offset_)}
    atomic_write(path / STATE_FILE, json.dumps(state, indent=2))
    return path


def load_classifier(cls: type[Classifier], path: str | os.PathLike) -> Classifier:
    """Rebuild a saved classifier; the frozen base must be the same weights file (hash checked)."""
    from safetensors.torch import load as load_tensors

    path = Path(path)
    for f in (STATE_FILE, TENSOR_FILE):
        if not (path / f).is_file():
            raise FileNotFoundError(f"{path / f}: missing (not a saved TransferClassifier)")
    try:
        state = read_json(path / STATE_FILE)
        est = cls(**state["params"])
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path / STATE_FILE}: not a TransferClassifier state ({exc})") from exc
    spec = est.check_params()
    tensors = load_tensors(read_input(path / TENSOR_FILE, "transfer head"))
    weights = Path(state["base_weights"]) if state["base_weights"] else None
    if est.freeze_base and weights is not None:
        if not weights.is_file():
            raise FileNotFoundError(f"{path}: its base weights {weights} are gone")
        if file_sha256(weights, "weights") != state["base_sha256"]:
            raise ValueError(f"{path}: base weights {weights} changed since training "
                             f"(SHA-256 differs): its verdicts would be wrong")
    est.base_ = build_base(est.arch, weights if est.freeze_base else None, int(est.random_state))
    base_tensors = {k[5:]: v for k, v in tensors.items() if k.startswith("base.")}
    if base_tensors:  # fine-tuned weights, or the calibrated statistics of a random base
        est.base_.load_state_dict(base_tensors, strict=False)
    est.base_fingerprint_ = fingerprint(est.base_)
    if est.base_fingerprint_ != state.get("base_fingerprint"):
        raise ValueError(f"{path}: the rebuilt {est.arch} base differs from the one it was "
                         f"trained on ({state['base_source']}): "
                         f"its verdicts would be wrong")
    for p in est.base_.parameters():
        p.requires_grad_(False)
    est.head_ = make_head(spec.n_features)
    est.head_.load_state_dict({k[5:]: v for k, v in tensors.items() if k.startswith("head.")})
    est.head_.eval()
    est.classes_ = np.array(LABELS)
    est.offset_ = float(state.get("offset", 0.0))
    if not np.isfinite(est.offset_):
        raise ValueError(f"{path / STATE_FILE}: decision offset {est.offset_!r} is not finite")
    est.base_pretrained_ = bool(state["base_pretrained"])
    est.base_weights_, est.base_sha256_ = state["base_weights"], state["base_sha256"]
    est.base_source_ = state["base_source"]
    if state.get("block_shape"):
        est.block_shape_ = tuple(state["block_shape"])
    return est
