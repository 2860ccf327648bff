"""Transfer-learning baselines of the paper: an ImageNet conv base + the paper's small head.

The paper compares its SVMs with VGG19, MobileNet, InceptionV3 and ResNet conv
bases topped by Dense(256, sigmoid) -> Dropout(0.5) -> Dense(1, sigmoid). Here the base's
output is global-average pooled; with a frozen base (the default, as in the paper) the
pooled features are computed once and only the head is trained, which is cheap on a CPU.
`decision_function` is the logit of the sigmoid output (> 0 means converged), so the
offset knob and the -1/+1 labels work as for the SVMs of `estimators`.

Weights are never downloaded: `weights` names a local state_dict file, or None to look in
the torch hub cache (`torch.hub.get_dir()/checkpoints`) for torchvision's own file name of
the architecture. Without weights the base keeps its random initialisation (only its
BatchNorm statistics are estimated on the training blocks, see `prepare_base`); that is
logged as a WARNING and shows in `report_label()`, because such a "transfer" baseline
transfers nothing and must not be reported as the paper's.

torchvision: PyPI only has CUDA builds, whose C extension (detection operators such as
nms) cannot load next to a CPU torch. Only the model definitions are needed here, and
torchvision 0.28.0 registers fake kernels for `torchvision::nms` / `qnms` at import time
whether or not its extension loaded, which then fails ("operator torchvision::nms does not
exist"). `import_torchvision` defines those two operator schemas (no kernels) when, and
only when, that exact failure happens, then imports again; a working torchvision is left
alone. Calling `torchvision.ops.nms` afterwards raises torch's "no kernel" error.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.validation import check_is_fitted
from torch import nn
from tqdm import tqdm

from noisefeat.display import display
from noisefeat.atomic import atomic_write
from noisefeat.extras import MissingExtra

from ..stoprule import OffsetClassifierMixin
from .bundle_check import file_sha256
from .estimators import LABELS, check_labels

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MIN_SIZE = 32
CALIBRATION_BLOCKS = 1024
STATE_FILE = "transfer.json"
TENSOR_FILE = "transfer.safetensors"


@dataclass(frozen=True)
class ArchSpec:
    """What differs between the five bases: builder, weight enum, head to strip, min input."""

    builder: str          # torchvision.models function
    weights_enum: str     # torchvision.models WeightsEnum class (for checkpoint file names)
    head: tuple[str, ...]  # top-level modules that form the ImageNet classifier
    min_size: int         # smallest input side the base accepts
    n_features: int       # width of the pooled base output


ARCHS: dict[str, ArchSpec] = {
    "vgg19": ArchSpec("vgg19", "VGG19_Weights", ("avgpool", "classifier"), MIN_SIZE, 512),
    "mobilenet_v2": ArchSpec("mobilenet_v2", "MobileNet_V2_Weights", ("classifier",), MIN_SIZE, 1280),
    "inception_v3": ArchSpec("inception_v3", "Inception_V3_Weights", ("fc", "AuxLogits"), 75, 2048),
    "resnet50": ArchSpec("resnet50", "ResNet50_Weights", ("fc",), MIN_SIZE, 2048),
    "densenet201": ArchSpec("densenet201", "DenseNet201_Weights", ("classifier",), MIN_SIZE, 1920),
}

# ---------------------------------------------------------------------------- torchvision

# Operators torchvision 0.28.0's _meta_registrations.py registers fake kernels for without
# first checking that its C extension loaded (the others are guarded by _has_ops()).
_TV_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_TV_MISSING = re.compile(r"operator torchvision::(\w+) does not exist")
_shim_lib: torch.library.Library | None = None  # kept alive: a collected Library unregisters


def _install_schemas() -> list[str]:
    """Define the torchvision operator schemas that do not exist yet; their names."""
    global _shim_lib
    added = []
    for name, schema in _TV_SCHEMAS.items():
        if hasattr(torch.ops.torchvision, name):
            continue
        if _shim_lib is None:
            _shim_lib = torch.library.Library("torchvision", "FRAGMENT")
        _shim_lib.define(schema)
        added.append(name)
    return added


def import_torchvision() -> ModuleType:
    """`import torchvision`, working around a CUDA wheel's unloadable extension (module doc)."""
    hint = ("install the build matching torch 2.13.0 with `pip install torchvision==0.28.0` "
            "(with torch 2.13.0+cpu installed pip keeps it)")
    try:
        import torchvision
        return torchvision
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] != "torchvision":
            raise
        raise MissingExtra("torchvision", purpose=f"the transfer-learning baselines ({', '.join(ARCHS)})") \
            from None
    except RuntimeError as exc:
        m = _TV_MISSING.search(str(exc))
        if m is None or m.group(1) not in _TV_SCHEMAS:
            raise ImportError(f"torchvision failed to import ({exc}); the transfer-learning "
                              f"baselines ({', '.join(ARCHS)}) are unavailable: {hint}") from exc
    for name in [k for k in sys.modules if k == "torchvision" or k.startswith("torchvision.")]:
        del sys.modules[name]  # the failed partial import
    added = _install_schemas()
    log.debug("torchvision C extension unavailable; defined operator schemas %s", added)
    try:
        import torchvision
    except Exception as exc:
        raise ImportError(f"torchvision failed to import even with operator schemas {added} "
                          f"defined ({exc}); the transfer-learning baselines "
                          f"({', '.join(ARCHS)}) are unavailable: {hint}") from exc
    return torchvision


# ---------------------------------------------------------------------------- weights

def checkpoint_names(arch: str) -> list[str]:
    """torchvision's ImageNet checkpoint file names for `arch`, its default first."""
    enum = getattr(import_torchvision().models, _spec(arch).weights_enum)
    members = [enum.DEFAULT] + [w for w in enum if w is not enum.DEFAULT]
    return [w.url.rsplit("/", 1)[-1] for w in members]


def find_cached_weights(arch: str) -> Path | None:
    """The first of `checkpoint_names(arch)` present in the torch hub cache, or None."""
    folder = Path(torch.hub.get_dir()) / "checkpoints"
    for name in checkpoint_names(arch):
        if (folder / name).is_file():
            return folder / name
    return None


def _is_imagenet_file(arch: str, path: Path, sha: str) -> bool:
    """torchvision's name for this arch and the hash prefix that name carries (as its hub check)."""
    m = re.fullmatch(r".*-([0-9a-f]{8,})\.pth", path.name)
    return path.name in checkpoint_names(arch) and m is not None and sha.startswith(m.group(1))


_DENSENET_OLD_KEY = re.compile(
    r"^(.*denselayer\d+\.(?:norm|relu|conv))\.((?:[12])\.(?:weight|bias|running_mean|running_var))$")


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    try:
        import io

        from noisefeat.safeio import read_input
        data = read_input(path, "transfer head")              # a regular file within its cap
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)  # no pickled code
    except Exception as exc:
        raise ValueError(f"{path}: not a readable torch state_dict file ({exc})") from exc
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: holds no state_dict (a mapping of names to tensors)")
    # torchvision's DenseNet checkpoints use the old 'norm.1' key style (see its _load_state_dict)
    return {(m.group(1) + m.group(2)) if (m := _DENSENET_OLD_KEY.match(k)) else k: v
            for k, v in state.items()}


def _load_into(model: nn.Module, arch: str, path: Path) -> None:
    """Load a full-model or base-only state_dict; every base tensor must be present."""
    state = _read_state_dict(path)
    head = _spec(arch).head
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        raise ValueError(f"{path}: does not fit the {arch} architecture ({exc})") from exc
    missing = [k for k in missing if k.split(".", 1)[0] not in head]
    if missing or unexpected:
        raise ValueError(f"{path}: not a {arch} state_dict: {len(missing)} base tensor(s) missing "
                         f"(e.g. {missing[:3]}), {len(unexpected)} unexpected (e.g. {unexpected[:3]})")


# ---------------------------------------------------------------------------- modules

def _spec(arch: str) -> ArchSpec:
    if arch not in ARCHS:
        raise ValueError(f"unknown arch {arch!r}; choose one of {', '.join(ARCHS)}")
    return ARCHS[arch]


class _Pooled(nn.Module):
    """A torchvision classifier with its ImageNet head cut off: images -> pooled features."""

    def __init__(self, arch: str, model: nn.Module) -> None:
        super().__init__()
        self.arch = arch
        if arch == "vgg19":
            self.net = nn.Sequential(model.features, nn.AdaptiveAvgPool2d(1), nn.Flatten())
            return
        for name in _spec(arch).head:
            setattr(model, name, nn.Identity() if name != "AuxLogits" else None)
        if arch == "inception_v3":
            model.aux_logits = False
        self.net = model  # its forward pools, flattens, then applies the Identity head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def build_base(arch: str, weights: Path | None, seed: int) -> nn.Module:
    """The pooled conv base, from `weights` or (None) randomly initialised with `seed`."""
    models = import_torchvision().models
    kwargs: dict[str, Any] = {"weights": None}
    if arch == "inception_v3":  # as torchvision does for its ImageNet weights
        kwargs.update(aux_logits=True, transform_input=weights is not None,
                      init_weights=weights is None)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = getattr(models, _spec(arch).builder)(**kwargs)
    if weights is not None:
        _load_into(model, arch, weights)
    base = _Pooled(arch, model)
    base.eval()
    return base


def fingerprint(module: nn.Module) -> str:
    """SHA-256 of a module's tensors: proves a rebuilt base is the one a head was trained on."""
    h = hashlib.sha256()
    for k, v in module.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().contiguous().cpu().numpy().tobytes())
    return h.hexdigest()


class _Standardize(nn.Module):
    def __init__(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("mean", mean)
        self.register_buffer("std", std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


def make_head(n_features: int, mean: torch.Tensor | None = None,
              std: torch.Tensor | None = None) -> nn.Sequential:
    """Standardise -> Dense(256, sigmoid) -> Dropout(0.5) -> Dense(1): the logit of the paper's head."""
    mean = torch.zeros(n_features) if mean is None else mean
    std = torch.ones(n_features) if std is None else std
    return nn.Sequential(_Standardize(mean, std), nn.Linear(n_features, 256), nn.Sigmoid(),
                         nn.Dropout(0.5), nn.Linear(256, 1))


# ---------------------------------------------------------------------------- estimator

class TransferClassifier(OffsetClassifierMixin, ClassifierMixin, BaseEstimator):
    """A conv base (ImageNet weights when found locally) + the paper's head; labels -1/+1.

    X is linear RGB blocks [N, h, w, 3] (display transform, resize, ImageNet normalisation
    happen here) or, with a frozen base, the pooled base features [N, n_features] that
    `transform` returns, so callers can cache the expensive part.
    """

    def __init__(self, arch: str = "vgg19", weights: str | None = None, input_size: int | None = None,
                 epochs: int = 30, batch_size: int = 64, lr: float = 1e-3, freeze_base: bool = True,
                 random_state: int = 0, progress: bool = False) -> None:
        self.arch = arch
        self.weights = weights
        self.input_size = input_size
        self.epochs = epochs
        self.batch_size = batch_size
        self.lr = lr
        self.freeze_base = freeze_base
        self.random_state = random_state
        self.progress = progress

    # -- parameters and the base

    def _check_params(self) -> ArchSpec:
        spec = _spec(self.arch)
        if self.input_size is not None and not (isinstance(self.input_size, (int, np.integer))
                                                and self.input_size >= spec.min_size):
            raise ValueError(f"input_size must be None or an integer >= {spec.min_size} "
                             f"for {self.arch}, got {self.input_size!r}")
        for name in ("epochs", "batch_size"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not (np.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a positive finite number, got {self.lr}")
        return spec

    def _resolve_weights(self) -> Path | None:
        if self.weights is not None:
            path = Path(self.weights).expanduser()
            if not path.is_file():
                raise FileNotFoundError(f"{path}: weights file for {self.arch} does not exist")
            return path
        return find_cached_weights(self.arch)

    def prepare_base(self, blocks: np.ndarray | torch.Tensor | None = None) -> TransferClassifier:
        """Build the conv base (fit does this); then `transform` works, so base features can be
        computed and cached before training heads on them.

        An untrained base's BatchNorm layers still hold the identity statistics of a fresh
        network, under which its random features vanish (mobilenet_v2: ~1e-10); their
        statistics are therefore estimated on up to CALIBRATION_BLOCKS of `blocks` (weights
        stay random). Sets base_, base_pretrained_, base_weights_, base_sha256_, base_source_,
        base_fingerprint_ (the cache key for base features) and block_shape_.
        """
        self._check_params()
        if blocks is not None:
            blocks = self._check_blocks(blocks)
            self.block_shape_ = tuple(int(s) for s in blocks.shape[1:3])
        path = self._resolve_weights()
        self.base_ = build_base(self.arch, path, int(self.random_state))
        self.base_pretrained_ = path is not None
        self.base_weights_ = str(path) if path is not None else None
        self.base_sha256_ = file_sha256(path, "weights") if path is not None else None
        if path is None:
            self.base_source_ = "untrained base"
            folder = Path(torch.hub.get_dir()) / "checkpoints"
            log.warning("%s: no ImageNet weights (looked for %s in %s); the base is UNTRAINED "
                        "(random init, seed %d) and its results are labelled '%s'",
                        self.arch, " or ".join(checkpoint_names(self.arch)), folder,
                        self.random_state, self.report_label())
            if blocks is not None:
                self._calibrate(blocks)
            elif any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in self.base_.modules()):
                log.warning("%s: untrained base prepared without blocks: its BatchNorm statistics "
                            "are not calibrated and its features are near zero", self.arch)
        elif _is_imagenet_file(self.arch, path, self.base_sha256_):
            self.base_source_ = "ImageNet"
        else:
            self.base_source_ = f"weights {path.name}"
        for p in self.base_.parameters():
            p.requires_grad_(not self.freeze_base)
        self.base_fingerprint_ = fingerprint(self.base_)
        return self

    def _calibrate(self, blocks: np.ndarray | torch.Tensor) -> None:
        """BatchNorm running statistics of the (random) base from a seeded sample of blocks."""
        bns = [m for m in self.base_.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
        if not bns:
            return
        gen = torch.Generator().manual_seed(int(self.random_state))
        pick = torch.randperm(len(blocks), generator=gen)[:CALIBRATION_BLOCKS].sort().values.numpy()
        for m in bns:
            m.reset_running_stats()
            m.momentum = None  # cumulative average over the calibration batches
            m.train()
        bs = max(int(self.batch_size), 2)
        with torch.no_grad():
            for i in range(0, len(pick), bs):
                if len(pick[i:i + bs]) > 1:  # BatchNorm needs two samples per batch
                    self.base_(self._images(blocks[pick[i:i + bs]]))
        for m in bns:
            m.momentum = 0.1
        self.base_.eval()

    def report_label(self) -> str:
        """'vgg19 (ImageNet)', 'vgg19 (untrained base)' or 'vgg19 (weights file.pth)'."""
        return f"{self.arch} ({getattr(self, 'base_source_', 'unfitted')})"

    # -- inputs

    def _images(self, blocks: np.ndarray | torch.Tensor) -> torch.Tensor:
        """Linear RGB [n, h, w, 3] -> ImageNet-normalised sRGB [n, 3, H, W] at the base's size."""
        x = display(torch.as_tensor(blocks)).permute(0, 3, 1, 2)
        h, w = x.shape[-2:]
        if self.input_size is not None:
            size = (int(self.input_size), int(self.input_size))
        else:
            m = _spec(self.arch).min_size
            size = (max(h, m), max(w, m))
        if size != (h, w):
            x = nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False,
                                          antialias=size[0] < h or size[1] < w)
        mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        return (x - mean) / std

    def _check_blocks(self, X: Any) -> np.ndarray | torch.Tensor:
        if not isinstance(X, torch.Tensor):
            X = np.asarray(X)
            if not np.issubdtype(X.dtype, np.number):
                raise ValueError(f"expected numbers, got dtype {X.dtype}")
        if X.ndim != 4 or X.shape[-1] != 3:
            raise ValueError(f"expected linear RGB blocks [n, h, w, 3] or base features "
                             f"[n, {_spec(self.arch).n_features}], got shape {tuple(X.shape)}")
        if min(X.shape[1:3], default=0) < 1:
            raise ValueError(f"empty blocks of shape {tuple(X.shape[1:3])}")
        return X

    def _features(self, X: Any) -> np.ndarray:
        """Pooled base features float32 [n, D]: computed from blocks, or checked if given."""
        if not isinstance(X, torch.Tensor):
            X = np.asarray(X)
        D = _spec(self.arch).n_features
        if X.ndim == 2:
            if X.shape[1] != D:
                raise ValueError(f"expected {D} {self.arch} base features per sample, got {X.shape[1]}")
            F = np.asarray(X, dtype=np.float32)
            if F.size and not np.isfinite(F).all():
                raise ValueError(f"{int((~np.isfinite(F)).any(axis=1).sum())} sample(s) hold NaN or Inf features")
            return F
        return self.transform(X)

    def transform(self, X: np.ndarray | torch.Tensor) -> np.ndarray:
        """Pooled base features float32 [n, n_features] of linear RGB blocks [n, h, w, 3]."""
        check_is_fitted(self, "base_")
        X = self._check_blocks(X)
        shape = tuple(X.shape[1:3])
        if self.input_size is None and getattr(self, "block_shape_", shape) != shape:
            log.warning("%s: blocks of %s, but trained on %s with input_size=None: base features "
                        "change with scale", self.arch, shape, self.block_shape_)
        out = []
        bs = int(self.batch_size)
        with torch.inference_mode():
            for i in tqdm(range(0, len(X), bs), desc=f"{self.arch} features",
                          disable=not self.progress, leave=False):
                out.append(self.base_(self._images(X[i:i + bs])))
        if not out:
            return np.zeros((0, _spec(self.arch).n_features), np.float32)
        return torch.cat(out).numpy().astype(np.float32, copy=False)

    # -- fit / predict

    def fit(self, X: np.ndarray | torch.Tensor, y: np.ndarray) -> TransferClassifier:
        """Build the base from blocks [n, h, w, 3], or keep the prepared one for features [n, D];
        then train the head (and, with freeze_base=False, the base)."""
        spec = self._check_params()
        y = check_labels(y)
        if len(X) != len(y):
            raise ValueError(f"{len(X)} samples but {len(y)} labels")
        if len(y) == 0:
            raise ValueError("cannot fit on an empty training set")
        if np.ndim(X) == 2:
            if not self.freeze_base:
                raise ValueError("precomputed base features need freeze_base=True")
            if getattr(self, "base_", None) is None:
                raise ValueError("precomputed base features need the base that made them: call "
                                 "prepare_base(blocks) and transform(blocks) first, or fit on blocks")
            if self.base_.arch != self.arch:
                raise ValueError(f"precomputed features: the prepared base is {self.base_.arch}, "
                                 f"not {self.arch}")
        else:
            self.prepare_base(X)
        self.classes_ = np.array(LABELS)
        self.offset_ = 0.0
        F = torch.from_numpy(self._features(X))
        mean, std = F.mean(0), F.std(0, unbiased=False).clamp_min(1e-6)
        target = torch.from_numpy((y > 0).astype(np.float32))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(self.random_state))
            self.head_ = make_head(spec.n_features, mean, std)
            if self.freeze_base:
                self._train(lambda idx: F[idx], target, list(self.head_.parameters()))
            else:
                blocks = self._check_blocks(X)
                self._train(lambda idx: self.base_(self._images(blocks[idx.numpy()])), target,
                            list(self.head_.parameters()) + list(self.base_.parameters()))
                self.base_fingerprint_ = fingerprint(self.base_)
        self.head_.eval()
        return self

    def _train(self, inputs: Any, target: torch.Tensor, params: list[nn.Parameter]) -> None:
        """Adam on BCE of the logit (= sigmoid output + BCE, stable); base stays in eval mode."""
        opt = torch.optim.Adam(params, lr=float(self.lr))
        loss_fn = nn.BCEWithLogitsLoss()
        n, bs = len(target), int(self.batch_size)
        self.head_.train()
        self.loss_curve_ = []
        for _ in tqdm(range(int(self.epochs)), desc=f"{self.arch} head", disable=not self.progress,
                      leave=False):
            order, total = torch.randperm(n), 0.0
            for i in range(0, n, bs):
                idx = order[i:i + bs]
                loss = loss_fn(self.head_(inputs(idx)).squeeze(1), target[idx])
                opt.zero_grad()
                loss.backward()
                opt.step()
                total += float(loss.detach()) * len(idx)
            self.loss_curve_.append(total / n)

    def decision_function(self, X: np.ndarray | torch.Tensor) -> np.ndarray:
        """Logit of the converged probability, float64 [n]: > 0 means converged."""
        check_is_fitted(self, "head_")
        F = torch.from_numpy(self._features(X))
        with torch.inference_mode():
            return self.head_(F).squeeze(1).double().numpy()

    def predict_proba(self, X: np.ndarray | torch.Tensor) -> np.ndarray:
        """[n, 2]: P(noisy), P(converged) (columns follow classes_ = [-1, 1])."""
        p = 1.0 / (1.0 + np.exp(-self.decision_function(X)))
        return np.stack([1.0 - p, p], axis=1)

    def n_parameters(self, trainable_only: bool = False) -> int:
        """Numbers the model uses (base + head incl. its standardisation), or only the trained ones."""
        check_is_fitted(self, "head_")
        head = sum(p.numel() for p in self.head_.parameters())
        if trainable_only:
            return head + (0 if self.freeze_base else sum(p.numel() for p in self.base_.parameters()))
        buffers = sum(b.numel() for b in self.head_.buffers())
        return sum(p.numel() for p in self.base_.parameters()) + head + buffers

    # -- persistence (safetensors + JSON, no pickle)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the head to a directory, with a fine-tuned base or an untrained base's
        BatchNorm statistics; a frozen pretrained base is referenced by its weights file and
        SHA-256, not copied (hundreds of MB)."""
        from safetensors.torch import save_file
        check_is_fitted(self, "head_")
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        tensors = {f"head.{k}": v.contiguous() for k, v in self.head_.state_dict().items()}
        if not self.freeze_base or not self.base_pretrained_:  # fine-tuned / calibrated base
            keep = None if not self.freeze_base else {k for k, _ in self.base_.named_buffers()}
            tensors.update({f"base.{k}": v.contiguous() for k, v in self.base_.state_dict().items()
                            if keep is None or k in keep})
        atomic_write(path / TENSOR_FILE, lambda tmp: save_file(tensors, str(tmp)))
        state = {"params": self.get_params(), "base_pretrained": self.base_pretrained_,
                 "base_weights": self.base_weights_, "base_sha256": self.base_sha256_,
                 "base_source": self.base_source_, "base_fingerprint": self.base_fingerprint_,
                 "block_shape": list(getattr(self, "block_shape_", ()) or []) or None,
                 "offset": float(self.offset_)}
        atomic_write(path / STATE_FILE, json.dumps(state, indent=2))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> TransferClassifier:
        """Rebuild a saved classifier; the frozen base must be the same weights file (hash checked)."""
        from safetensors.torch import load as load_tensors

        from noisefeat.safeio import read_input, read_json
        path = Path(path)
        for f in (STATE_FILE, TENSOR_FILE):
            if not (path / f).is_file():
                raise FileNotFoundError(f"{path / f}: missing (not a saved TransferClassifier)")
        try:
            state = read_json(path / STATE_FILE)
            est = cls(**state["params"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{path / STATE_FILE}: not a TransferClassifier state ({exc})") from exc
        spec = est._check_params()
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
