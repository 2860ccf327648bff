"""Model bundles: a directory with manifest.json and model.skops, never a pickle (the
transfer baselines' bundles hold safetensors instead: `learning.models.transfer_bundle`).
`Model`, the loaded bundle, and the manifest constants live in `learning.models.model`.

skops refuses types it does not know; we pass it an explicit allow-list (our estimator
classes and the scikit-learn parts they hold), never `trusted=True`. The manifest records
the model kind, what input it takes, the hash of the feature base it was trained on, the
training data summary, metrics and library versions. A feature model loaded under a
different feature base would give silently wrong verdicts, so that is a hard error.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import skops.io as sio

from noisefeat.errors import InputNotFound
from noisefeat import FeatureBase, default_base
from noisefeat.atomic import atomic_path, atomic_write
from noisefeat.jsonout import json_default

from ..inputs.noise_input import HALVES, n_inputs
from .bundle_check import check_estimator, file_sha256, load_skops, model_bytes, read_manifest
from .estimators import RBFSVM
from .model import FORMAT, MANIFEST, VERSION, Model, versions

__all__ = ["ALLOWED_TYPES", "BUNDLED_DIR", "FORMAT", "MANIFEST", "MODEL_FILE", "VERSION", "Model", "load_model",
           "save_model"]

MODEL_FILE = "model.skops"
BUNDLED_DIR = Path(__file__).parents[1] / "bundled"
ALLOWED_TYPES = [
    "learning.models.estimators.RBFSVM", "learning.models.estimators.DSVM", "learning.models.estimators.SVM",
    "sklearn.svm._classes.SVC", "sklearn.preprocessing._data.StandardScaler",
]


def save_model(estimator: RBFSVM, path: str | os.PathLike, *, kind: str, input: str,
               training: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None,
               base: FeatureBase | None = None, name: str | None = None,
               extra: dict[str, Any] | None = None) -> Path:
    """Write a bundle directory (files atomically, manifest last)."""
    if input not in ("features", "raw"):
        raise ValueError(f"input must be 'features' or 'raw', got {input!r}")
    extra = dict(extra or {})
    if extra.get("quick") == "halves" and input == "features":
        extra.setdefault("composition", HALVES)     # what the half buffers are turned into
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    base = base or default_base()
    with atomic_path(path / MODEL_FILE) as tmp:
        sio.dump(estimator, tmp)
        digest = file_sha256(tmp)
    manifest = {
        "format": FORMAT, "version": VERSION, "kind": kind, "name": name or kind, "input": input,
        "feature_base": {"hash": base.hash, "weights": base.weights_name, "wavelet": base.wavelet}
        if input == "features" else None,
        "n_features": int(estimator.n_features_in_), "offset": float(estimator.offset_),
        "support_vectors": int(estimator.n_support_), "parameters": int(estimator.n_parameters()),
        "params": {k: v for k, v in estimator.get_params().items() if isinstance(v, (int, float, str, bool, type(None)))},
        "training": training or {}, "metrics": metrics or {}, "versions": versions(),
        "model_sha256": digest, **(extra or {}),
    }
    atomic_write(path / MANIFEST, json.dumps(manifest, indent=2, default=json_default))
    return path


def load_model(path: str | os.PathLike | None = None, base: FeatureBase | None = None) -> Model:
    """Load a model bundle; no pickle involved.

    Everything is validated before the model answers anything (`learning.models.bundle_check`):
    the manifest's schema, the model file's hash and size, the allowed types, every fitted
    array the estimator reads, and the feature base.

    Parameters
    ----------
    path : str or os.PathLike, optional
        The bundle directory (or its manifest.json); None: the model bundled with the
        package (`learning/bundled`).
    base : FeatureBase, optional
        The feature base a feature model computes its input with; default: the package's.
        It must be the one the model was trained on (its hash is checked).

    Returns
    -------
    Model
        The loaded model: `decision_function(X)` and `predict(X)` on model inputs,
        `assess_blocks` / `assess_halves` for verdicts through the one stop rule at its
        calibrated `offset` (or `offset_at(tau)`). A transfer baseline's bundle gives a
        `TransferModel`.

    Raises
    ------
    noisefeat.errors.InputNotFound
        If `path` holds no bundle or a file of it is missing (a ValueError and a
        FileNotFoundError).
    ValueError
        On any damaged, inconsistent or foreign bundle, naming the file.
    """
    path = BUNDLED_DIR if path is None else Path(path)
    if path.is_file() and path.name == MANIFEST:
        path = path.parent
    if not (path / MANIFEST).exists():           # a FIFO or a device there is read_manifest's to name
        raise InputNotFound(f"{path}: not a noisestop model bundle (no {MANIFEST})")
    manifest = read_manifest(path / MANIFEST)
    if manifest["input"] == "image":        # a transfer baseline: torchvision, loaded only here
        from .transfer_bundle import load_transfer_model
        return load_transfer_model(path, manifest)
    model_file = path / MODEL_FILE
    if not model_file.exists():
        raise InputNotFound(f"{model_file}: missing")
    estimator = load_skops(model_bytes(model_file, manifest), ALLOWED_TYPES, model_file)
    if isinstance(estimator, RBFSVM) and "offset_" not in vars(estimator):   # written before offset_ was fitted
        estimator.offset_ = float(manifest.get("offset") if manifest.get("offset") is not None
                                  else getattr(estimator, "offset", 0.0))
    try:
        check_estimator(estimator, manifest.get("n_features"))
    except ValueError as exc:
        raise ValueError(f"{model_file}: {exc}") from None
    if manifest["input"] == "features":
        running = (base or default_base()).hash
        trained = manifest["feature_base"]["hash"]
        if trained != running:
            raise ValueError(
                f"{path}: trained on feature base {trained}, but this noisestop runs feature base "
                f"{running}: its verdicts would be wrong. Retrain it (noisestop train) or use "
                f"the weights it was trained with.")
    model = Model(estimator, manifest, path)
    if model.composition is not None:
        try:
            width = n_inputs(str(model.composition))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
        if width != model.n_features:
            raise ValueError(f"{path}: input composition {model.composition!r} has {width} columns, but the "
                             f"model was fitted on {model.n_features}")
    elif model.input == "features" and model.n_features != 26:
        raise ValueError(f"{path}: a feature model on the {model.quick} input reads 26 features, this one "
                         f"was fitted on {model.n_features}")
    return model
