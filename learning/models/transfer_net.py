"""The transfer baselines' network: a conv base with its ImageNet head cut off, pooled, and
the paper's small head on top.

The paper tops each base by Dense(256, sigmoid) -> Dropout(0.5) -> Dense(1, sigmoid). Here
the base's output is global-average pooled, and the head's last layer gives the logit of
the sigmoid output (> 0 means converged), so the offset knob and the -1/+1 labels work as
for the SVMs of `estimators`. `base_images` is what a base sees of linear RGB blocks.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from noisefeat.display import display

from .transfer_archs import arch_spec, import_torchvision
from .transfer_weights import load_into

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class _Pooled(nn.Module):
    """A torchvision classifier with its ImageNet head cut off: images -> pooled features."""

    def __init__(self, arch: str, model: nn.Module) -> None:
        super().__init__()
        self.arch = arch
        if arch == "vgg19":
            self.net = nn.Sequential(model.features, nn.AdaptiveAvgPool2d(1), nn.Flatten())
            return
        for name in arch_spec(arch).head:
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
        model = getattr(models, arch_spec(arch).builder)(**kwargs)
    if weights is not None:
        load_into(model, arch, weights)
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
    """(x - mean) / std with the training features' statistics, kept as buffers (saved with the head)."""

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


def base_images(blocks: np.ndarray | torch.Tensor, arch: str, input_size: int | None) -> torch.Tensor:
    """Linear RGB [n, h, w, 3] -> ImageNet-normalised sRGB [n, 3, H, W] at the base's size
    (`input_size` square, or None: the blocks' own size, raised to the base's minimum)."""
    x = display(torch.as_tensor(blocks)).permute(0, 3, 1, 2)
    h, w = x.shape[-2:]
    if input_size is not None:
        size = (int(input_size), int(input_size))
    else:
        m = arch_spec(arch).min_size
        size = (max(h, m), max(w, m))
    if size != (h, w):
        x = nn.functional.interpolate(x, size=size, mode="bilinear", align_corners=False,
                                      antialias=size[0] < h or size[1] < w)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x - mean) / std
