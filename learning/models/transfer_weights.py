"""The weights of a transfer baseline's conv base: found locally, read safely, loaded.

Weights are never downloaded: a classifier's `weights` names a local state_dict file, or
None to look in the torch hub cache (`torch.hub.get_dir()/checkpoints`) for torchvision's
own file name of the architecture (`find_cached_weights`). A file is read through
`noisefeat.safeio` and unpickled with `weights_only=True` (no pickled code); a base must find
every one of its tensors in it.
"""
from __future__ import annotations

import io
import re
from pathlib import Path

import torch
from torch import nn

from noisefeat.safeio import read_input

from .transfer_archs import arch_spec, import_torchvision


def checkpoint_names(arch: str) -> list[str]:
    """torchvision's ImageNet checkpoint file names for `arch`, its default first."""
    enum = getattr(import_torchvision().models, arch_spec(arch).weights_enum)
    members = [enum.DEFAULT] + [w for w in enum if w is not enum.DEFAULT]
    return [w.url.rsplit("/", 1)[-1] for w in members]


def find_cached_weights(arch: str) -> Path | None:
    """The first of `checkpoint_names(arch)` present in the torch hub cache, or None."""
    folder = Path(torch.hub.get_dir()) / "checkpoints"
    for name in checkpoint_names(arch):
        if (folder / name).is_file():
            return folder / name
    return None


def is_imagenet_file(arch: str, path: Path, sha: str) -> bool:
    """torchvision's name for this arch and the hash prefix that name carries (as its hub check)."""
    m = re.fullmatch(r".*-([0-9a-f]{8,})\.pth", path.name)
    return path.name in checkpoint_names(arch) and m is not None and sha.startswith(m.group(1))


_DENSENET_OLD_KEY = re.compile(
    r"^(.*denselayer\d+\.(?:norm|relu|conv))\.((?:[12])\.(?:weight|bias|running_mean|running_var))$")


def read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """The tensors of a torch state_dict file by name (a checkpoint's `state_dict` or `model`
    entry unwrapped, DenseNet's old key style renamed); a ValueError naming the file else."""
    try:
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


def load_into(model: nn.Module, arch: str, path: Path) -> None:
    """Load a full-model or base-only state_dict; every base tensor must be present."""
    state = read_state_dict(path)
    head = arch_spec(arch).head
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        raise ValueError(f"{path}: does not fit the {arch} architecture ({exc})") from exc
    missing = [k for k in missing if k.split(".", 1)[0] not in head]
    if missing or unexpected:
        raise ValueError(f"{path}: not a {arch} state_dict: {len(missing)} base tensor(s) missing "
                         f"(e.g. {missing[:3]}), {len(unexpected)} unexpected (e.g. {unexpected[:3]})")
