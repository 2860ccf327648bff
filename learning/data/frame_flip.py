"""FLIP as the virtual observer runs it: flip-evaluator on whole frames of display images.

Why apart from the observer's rules: the observer (`block_terms`, `tile_terms`), the
`halves` input's reference route and the tests all need the FLIP map of two display images
exactly as NVIDIA's `flip_evaluator` computes it, and the display helpers as numpy.

FLIP (`flip_evaluator`) ends the process with sys.exit on bad arguments and raises a bare
RuntimeError on others, so inputs are validated here first and both are turned into
ValueError.
"""
from __future__ import annotations

import contextlib
import io
from collections.abc import Iterable, Iterator

import numpy as np
import torch

from noisefeat.display import display as _display
from noisefeat.display import srgb_decode as _srgb_decode
from noisefeat.extras import require
from noisefeat.flip_kernels import check_ppd

DEFAULT_PPD = 67.0


def display(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """DESIGN's one display transform (noisefeat.display) as float32 C-contiguous numpy."""
    return np.ascontiguousarray(_display(np.asarray(rgb), exposure).numpy(), dtype=np.float32)


def srgb_decode(srgb01: np.ndarray) -> np.ndarray:
    """Display values in [0, 1] -> linear (noisefeat's inverse sRGB), float32 numpy."""
    return _srgb_decode(torch.as_tensor(np.asarray(srgb01, np.float32))).numpy()


# ----------------------------------------------------------------------------- FLIP


def _check_ldr(img: np.ndarray, name: str) -> np.ndarray:
    if not isinstance(img, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(img).__name__}")
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"{name} must have shape [H, W, 3] with H, W > 0, got {img.shape}")
    if not np.issubdtype(img.dtype, np.floating):
        raise ValueError(f"{name} must be float sRGB values in [0, 1], got dtype {img.dtype}")
    out = np.ascontiguousarray(img, dtype=np.float32)
    if not np.isfinite(out).all():
        raise ValueError(f"{name} holds NaN or Inf; pass it through display() first")
    lo, hi = float(out.min()), float(out.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"{name} must lie in [0, 1] (sRGB), got range [{lo:g}, {hi:g}]")
    return out


def flip_map(ref_srgb: np.ndarray, test_srgb: np.ndarray, ppd: float = DEFAULT_PPD) -> np.ndarray:
    """Raw LDR-FLIP error map [H, W] float32 in [0, 1] of two sRGB images in [0, 1]."""
    flip_evaluator = require("flip_evaluator")

    p = check_ppd(ppd)
    ref = _check_ldr(ref_srgb, "reference")
    test = _check_ldr(test_srgb, "test image")
    if ref.shape != test.shape:
        raise ValueError(f"reference {ref.shape} and test image {test.shape} differ in shape")
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            emap, _, _ = flip_evaluator.evaluate(ref, test, "LDR", inputsRGB=True,
                                                 applyMagma=False, computeMeanError=False,
                                                 parameters={"ppd": p})
    except SystemExit as exc:
        raise ValueError(f"FLIP refused its arguments: {out.getvalue().strip() or exc}") from None
    except RuntimeError as exc:
        raise ValueError(f"FLIP failed: {exc}") from exc
    emap = np.asarray(emap, np.float32)
    return emap.reshape(emap.shape[0], emap.shape[1])


def level_maps(ref: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray], ppd: float,
               exposure: float) -> Iterator[tuple[torch.Tensor, torch.Tensor, np.ndarray]]:
    """(display(reference), display(level), FLIP map of the frame) for each level, in turn
    (one level in memory at a time)."""
    ref_t = _display(np.asarray(ref), exposure)
    ref_d = np.ascontiguousarray(ref_t.numpy(), dtype=np.float32)
    for k, lev in enumerate(levels_rgb):
        lev = np.asarray(lev)
        if lev.shape != ref.shape:
            raise ValueError(f"level {k} has shape {lev.shape}, the reference {ref.shape}")
        lev_t = _display(lev, exposure)
        yield ref_t, lev_t, flip_map(ref_d, np.ascontiguousarray(lev_t.numpy(), dtype=np.float32), ppd)
