"""Bundles of the transfer baselines (`learning.models.transfer`): manifest.json next to
the classifier's own files, transfer.json and transfer.safetensors (no pickle).

The manifest has the SVM bundles' format and fields (kind = the arch, `input` "image",
`quick` 'halves' or 'none') plus the SHA-256 of both files, checked before anything is
read; `TransferClassifier.load` then checks its frozen pretrained base by path and SHA-256
and the rebuilt base by fingerprint. `TransferModel` gives verdicts through the one stop
rule like any `Model`: it reads pictures (`learning.inputs.pictures`), not features.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from noisefeat.atomic import atomic_write
from noisefeat.jsonout import json_default

from ..inputs.pictures import image_input, noise_picture
from ..names import DEFAULT_TAU, OFFSET_LIMIT, TRANSFER_INPUTS, TRANSFER_KINDS
from ..stoprule import dots_ratio, flat_halves, hold_dotted
from .bundle_check import file_sha256
from .model import FORMAT, MANIFEST, VERSION, Model, nonfinite_counts, versions
from .transfer import TransferClassifier
from .transfer_archs import ARCHS, import_torchvision
from .transfer_state import STATE_FILE, TENSOR_FILE

#: `input` of an image classifier's manifest
IMAGE = "image"


class TransferModel(Model):
    """A loaded transfer bundle: verdicts on the block ('none') or on the noise picture of
    its half buffers ('halves'), at its training block size only (the base's features
    change with scale, so another size would be judged at a scale it never saw)."""

    estimator: TransferClassifier

    @property
    def input(self) -> str:
        return IMAGE

    @property
    def quick(self) -> str:
        return str(self.manifest.get("quick") or "none")

    @property
    def needs_quick(self) -> bool:
        return False

    @property
    def n_features(self) -> int:
        """Width of the pooled base features, what the head reads (not a request input)."""
        return ARCHS[self.estimator.arch].n_features

    @property
    def block_shape(self) -> tuple[int, int] | None:
        """(h, w) of the blocks it was trained on."""
        shape = getattr(self.estimator, "block_shape_", None)
        return None if shape is None else (int(shape[0]), int(shape[1]))

    @property
    def label(self) -> str:
        """'mobilenet_v2 (untrained base)', 'vgg19 (ImageNet)', ...: what the base transfers."""
        return self.estimator.report_label()

    def table_options(self) -> dict[str, Any]:
        return {"image": True, "quick": self.quick}

    def _check_size(self, shape: tuple[int, ...]) -> None:
        want = self.block_shape
        if want is not None and len(shape) == 4 and tuple(shape[1:3]) != want:
            raise ValueError(f"this {self.estimator.arch} model takes {want[0]}x{want[1]} blocks (its "
                             f"training size), got {shape[1]}x{shape[2]}")

    def inputs_from_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None,
                           base: Any = None, exposure: float = 0.0) -> np.ndarray:
        """The blocks as the classifier reads them (a 'none' model)."""
        if self.needs_halves:
            raise ValueError("this model reads the two half buffers (even and odd passes) of every "
                             "block, not the block alone: use score_halves")
        x = image_input(blocks, exposure)
        self._check_size(x.shape)
        return x

    def inputs_from_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = 0.0) -> np.ndarray:
        """The displayed noise picture of the half buffers (a 'halves' model)."""
        if not self.needs_halves:
            raise ValueError("this model reads the blocks, not half buffers")
        self._check_size(np.shape(even))
        return noise_picture(even, odd, exposure)

    def assess_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                      offset: float | None = None, tau: float = DEFAULT_TAU) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(verdict, score, non-finite pixels of both halves [N]); flat: both halves, alike;
        dotted blocks held noisy at `tau` (`learning.stoprule.hold_dotted`), as `Model.assess_halves`."""
        x = self.inputs_from_halves(even, odd, exposure)
        flat = flat_halves(even, odd, exposure) if len(x) else np.zeros(0, bool)
        verdict, score = self.score_inputs(x, offset, flat)
        return (hold_dotted(verdict, dots_ratio(even, odd, exposure, tau), flat), score,
                nonfinite_counts(even) + nonfinite_counts(odd))


def save_transfer_model(clf: TransferClassifier, path: str | os.PathLike, *, quick: str,
                        training: dict[str, Any] | None = None, metrics: dict[str, Any] | None = None,
                        name: str | None = None) -> Path:
    """Write a transfer bundle directory (the classifier's files, then the manifest last)."""
    if quick not in TRANSFER_INPUTS:
        raise ValueError(f"a transfer model reads {' or '.join(TRANSFER_INPUTS)}, not {quick!r}")
    path = Path(path)
    clf.save(path)
    stale = path / "model.skops"          # an SVM bundle written here before would confuse readers
    if stale.exists():
        stale.unlink()
    manifest = {
        "format": FORMAT, "version": VERSION, "kind": clf.arch, "name": name or clf.arch, "input": IMAGE,
        "quick": quick, "feature_base": None, "offset": float(clf.offset_),
        "block": list(clf.block_shape_), "parameters": int(clf.n_parameters()),
        "trainable_parameters": int(clf.n_parameters(trainable_only=True)),
        "params": {k: v for k, v in clf.get_params().items() if isinstance(v, (int, float, str, bool, type(None)))},
        "base": {"label": clf.report_label(), "source": clf.base_source_, "pretrained": bool(clf.base_pretrained_),
                 "weights": clf.base_weights_, "weights_sha256": clf.base_sha256_},
        "training": training or {}, "metrics": metrics or {},
        "versions": {**versions(), "torchvision": import_torchvision().__version__},
        "model_sha256": file_sha256(path / TENSOR_FILE), "state_sha256": file_sha256(path / STATE_FILE),
    }
    atomic_write(path / MANIFEST, json.dumps(manifest, indent=2, default=json_default))
    return path


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def load_transfer_model(path: Path, manifest: dict[str, Any]) -> TransferModel:
    """The transfer bundle at `path` whose manifest `read_manifest` has checked: file hashes
    first, then the classifier (`TransferClassifier.load`: base weights by SHA-256, the
    rebuilt base by fingerprint), then what it holds against the manifest. Any problem is
    one ValueError (FileNotFoundError for a missing file) naming the file."""
    for fname, field in ((STATE_FILE, "state_sha256"), (TENSOR_FILE, "model_sha256")):
        f = path / fname
        if not f.exists():
            raise FileNotFoundError(f"{f}: missing")
        if file_sha256(f, "transfer head") != manifest[field]:      # a regular file within its cap
            raise ValueError(f"{f}: content does not match the manifest's {field} (changed or damaged)")
    try:
        clf = TransferClassifier.load(path)
    except FileNotFoundError as exc:
        raise FileNotFoundError(_one_line(exc)) from None
    except ValueError as exc:
        raise ValueError(_one_line(exc)) from None
    except Exception as exc:     # safetensors, torch and torchvision raise many kinds
        raise ValueError(f"{path / TENSOR_FILE}: unreadable transfer model "
                         f"({type(exc).__name__}: {_one_line(exc)})") from None
    state = path / STATE_FILE
    if clf.arch != manifest["kind"] or clf.arch not in TRANSFER_KINDS:
        raise ValueError(f"{state}: holds a {clf.arch!r} classifier, the manifest says {manifest['kind']!r}")
    if not (np.isfinite(clf.offset_) and abs(clf.offset_) <= OFFSET_LIMIT):
        raise ValueError(f"{state}: decision offset {clf.offset_!r} is not a number within {OFFSET_LIMIT:g}")
    if manifest.get("offset") is not None and float(manifest["offset"]) != clf.offset_:
        raise ValueError(f"{state}: decision offset {clf.offset_:g} differs from the manifest's {manifest['offset']:g}")
    block = getattr(clf, "block_shape_", None)
    if block is None or len(block) != 2 or list(block) != manifest.get("block") or min(block) < 1:
        raise ValueError(f"{state}: block shape {block} missing or not the manifest's {manifest.get('block')}")
    for part, module in (("head", clf.head_), ("base", clf.base_)):
        bad = [k for k, t in module.state_dict().items() if t.is_floating_point() and not torch.isfinite(t).all()]
        if bad:
            raise ValueError(f"{path / TENSOR_FILE}: {part} tensor {bad[0]} holds NaN or Inf")
    return TransferModel(clf, manifest, path)
