"""Conv-layer weights of the feature base: the shipped files, the smoothing initialisation.

Weights live in safetensors files inside the package (no pickle). `smoothing.safetensors`
is the documented deterministic initialisation: normalised binomial kernels (3x3 from
[1, 2, 1], 5x5 from [1, 4, 6, 4, 1]), so each layer is a slightly stronger low-pass than
the one before and the noise maps input - O_l grow with l; it is the default, because it
measured better on held-out scenes than `pretrained.safetensors` (the conv layers trained
as a denoiser by `noisestop pretrain`, selectable by name or NOISESTOP_FEATURE_WEIGHTS). `noisestop pretrain` writes the user's
own `pretrained.safetensors` to the user data directory, where the name 'pretrained' finds it
first (`noisefeat.userdata`); only `--update-package` rewrites the shipped file.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load, save_file

from .atomic import atomic_write
from .safeio import read_input
from .userdata import find as find_user_file

KERNEL_SIZES: tuple[int, ...] = (3, 5) * 6
WEIGHTS_DIR = Path(__file__).with_name("weights")
SMOOTHING_FILE = WEIGHTS_DIR / "smoothing.safetensors"
PRETRAINED_FILE = WEIGHTS_DIR / "pretrained.safetensors"
#: where `noisestop pretrain` writes by default, relative to the user data directory
PRETRAINED_USER_FILE = "weights/pretrained.safetensors"


def _binomial(k: int) -> np.ndarray:
    row = np.array([1.0])
    for _ in range(k - 1):
        row = np.convolve(row, [1.0, 1.0])
    kern = np.outer(row, row)
    return kern / kern.sum()


def smoothing_kernels() -> list[torch.Tensor]:
    """The deterministic initialisation: one [k, k] float32 kernel per layer."""
    return [torch.tensor(_binomial(k), dtype=torch.float32) for k in KERNEL_SIZES]


def save_kernels(path: Path, kernels: list[torch.Tensor], metadata: dict[str, str]) -> None:
    """Write kernels as `conv.{i}.weight` [1, 1, k, k] tensors, atomically."""
    path = Path(path)
    tensors = {f"conv.{i}.weight": k.detach().reshape(1, 1, *k.shape[-2:]).contiguous().float()
               for i, k in enumerate(kernels)}
    atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=metadata))


def named_file(name: str) -> Path | None:
    """The file of a named weight set: 'smoothing' (shipped only), 'pretrained' (the user's
    own pre-training in the user data directory if there is one, else the shipped file)."""
    if name == "smoothing":
        return SMOOTHING_FILE
    if name == "pretrained":
        return find_user_file(PRETRAINED_USER_FILE, PRETRAINED_FILE)
    return None


def load_kernels(path: Path | str | None = None) -> tuple[list[torch.Tensor], str]:
    """Kernels from a safetensors file, or by name: 'smoothing' (None), 'pretrained'."""
    path = SMOOTHING_FILE if path is None else named_file(str(path)) or Path(path)
    if not path.exists():
        raise FileNotFoundError(f"feature-base weights not found: {path}")
    data = read_input(path, "weights")       # a regular file within its cap: a FIFO or device is refused
    try:
        tensors = load(data)
    except Exception as exc:  # safetensors raises its own error types
        raise ValueError(f"{path}: not a readable safetensors file ({exc})") from exc
    kernels = []
    for i, k in enumerate(KERNEL_SIZES):
        key = f"conv.{i}.weight"
        if key not in tensors:
            raise ValueError(f"{path}: missing tensor {key!r}")
        t = tensors[key].float()
        if tuple(t.shape) != (1, 1, k, k):
            raise ValueError(f"{path}: {key} has shape {tuple(t.shape)}, expected (1, 1, {k}, {k})")
        if not torch.isfinite(t).all():
            raise ValueError(f"{path}: {key} holds non-finite weights")
        kernels.append(t[0, 0])
    return kernels, path.name


def kernels_hash(kernels: list[torch.Tensor], wavelet: str) -> str:
    """Identity of a feature base: models trained on one base are invalid on another."""
    h = hashlib.sha256(wavelet.encode())
    for k in kernels:
        h.update(k.detach().float().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


if __name__ == "__main__":  # python -m noisefeat.weights: (re)write the smoothing file
    save_kernels(SMOOTHING_FILE, smoothing_kernels(),
                 {"init": "normalised binomial smoothing kernels", "layers": "3,5,3,5,..."})
    print(SMOOTHING_FILE)
