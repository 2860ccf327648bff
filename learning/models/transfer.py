"""Transfer-learning baselines of the paper: an ImageNet conv base + the paper's small head,
as a scikit-learn classifier with labels -1/+1.

With a frozen base (the default, as in the paper) the pooled base features are computed
once and only the head is trained, which is cheap on a CPU. `decision_function` is the
logit of the sigmoid output (> 0 means converged), so the offset knob and the -1/+1 labels
work as for the SVMs of `estimators`.

Where the parts live: the bases and torchvision's import in `transfer_archs`, their weights
in `transfer_weights`, the network (pooled base, head, what a base sees of a block) in
`transfer_net`, saving and loading in `transfer_state`; here, preparing the base and
training the head. Without weights the base keeps its random initialisation (only its
BatchNorm statistics are estimated on the training blocks, see `prepare_base`); that is
logged as a WARNING and shows in `report_label()`, because such a "transfer" baseline
transfers nothing and must not be reported as the paper's.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, ClassifierMixin
from sklearn.utils.validation import check_is_fitted
from torch import nn
from tqdm import tqdm

from ..stoprule import OffsetClassifierMixin
from .bundle_check import file_sha256
from .estimators import LABELS, check_labels
from .transfer_archs import ArchSpec, arch_spec
from .transfer_net import base_images, build_base, fingerprint, make_head
from .transfer_state import load_classifier, save_classifier
from .transfer_weights import checkpoint_names, find_cached_weights, is_imagenet_file

log = logging.getLogger(__name__)

CALIBRATION_BLOCKS = 1024


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

    def check_params(self) -> ArchSpec:
        """The arch's `ArchSpec`, if every parameter is valid; else a ValueError naming it
        (`transfer_state` checks a saved state's parameters with it too)."""
        spec = arch_spec(self.arch)
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
        self.check_params()
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
        elif is_imagenet_file(self.arch, path, self.base_sha256_):
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
        return base_images(blocks, self.arch, self.input_size)

    def _check_blocks(self, X: Any) -> np.ndarray | torch.Tensor:
        if not isinstance(X, torch.Tensor):
            X = np.asarray(X)
            if not np.issubdtype(X.dtype, np.number):
                raise ValueError(f"expected numbers, got dtype {X.dtype}")
        if X.ndim != 4 or X.shape[-1] != 3:
            raise ValueError(f"expected linear RGB blocks [n, h, w, 3] or base features "
                             f"[n, {arch_spec(self.arch).n_features}], got shape {tuple(X.shape)}")
        if min(X.shape[1:3], default=0) < 1:
            raise ValueError(f"empty blocks of shape {tuple(X.shape[1:3])}")
        return X

    def _features(self, X: Any) -> np.ndarray:
        """Pooled base features float32 [n, D]: computed from blocks, or checked if given."""
        if not isinstance(X, torch.Tensor):
            X = np.asarray(X)
        D = arch_spec(self.arch).n_features
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
            return np.zeros((0, arch_spec(self.arch).n_features), np.float32)
        return torch.cat(out).numpy().astype(np.float32, copy=False)

    # -- fit / predict

    def fit(self, X: np.ndarray | torch.Tensor, y: np.ndarray) -> TransferClassifier:
        """Build the base from blocks [n, h, w, 3], or keep the prepared one for features [n, D];
        then train the head (and, with freeze_base=False, the base)."""
        spec = self.check_params()
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

    # -- persistence (`transfer_state`: safetensors + JSON, no pickle)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the head to a directory (`transfer_state.save_classifier`)."""
        return save_classifier(self, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> TransferClassifier:
        """Rebuild a saved classifier (`transfer_state.load_classifier`); the frozen base must
        be the same weights file (hash checked)."""
        return load_classifier(cls, path)
