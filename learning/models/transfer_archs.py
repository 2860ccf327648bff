"""The transfer baselines' conv bases (the paper's VGG19, MobileNet, InceptionV3, ResNet and
DenseNet) and how torchvision, which defines them, is imported.

torchvision: PyPI only has CUDA builds, whose C extension (detection operators such as
nms) cannot load next to a CPU torch. Only the model definitions are needed here, and
torchvision 0.28.0 registers fake kernels for `torchvision::nms` / `qnms` at import time
whether or not its extension loaded, which then fails ("operator torchvision::nms does not
exist"). `import_torchvision` defines those two operator schemas (no kernels) when, and
only when, that exact failure happens, then imports again; a working torchvision is left
alone. Calling `torchvision.ops.nms` afterwards raises torch's "no kernel" error.
"""
from __future__ import annotations

import logging
import re
import sys
from dataclasses import dataclass
from types import ModuleType

import torch

from noisefeat.extras import MissingExtra

log = logging.getLogger(__name__)

MIN_SIZE = 32


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


def arch_spec(arch: str) -> ArchSpec:
    """The `ArchSpec` of `arch`; a ValueError naming the choices for any other name."""
    if arch not in ARCHS:
        raise ValueError(f"unknown arch {arch!r}; choose one of {', '.join(ARCHS)}")
    return ARCHS[arch]


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
