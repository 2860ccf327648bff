"""The virtual observer (DESIGN "Virtual observer"): FLIP-based labels for a stack.

1. e[k, b] = mean over block b of the raw FLIP map (LDR, 67 ppd) between
   display(reference) and display(level k), the map computed on the whole frame.
   Optionally (`edge_margin` m > 0, off by default) pixels closer than m to the frame's
   edge are left out, where FLIP pads the frame (its widest filter reaches 10 px at
   67 ppd). Measured on the training and held-out datasets (README "Virtual observer"),
   m = 10 made the flip criterion's c calibrated on 64x64 training frames transfer worse
   to 256x256 held-out frames, so DESIGN's whole-frame mean stays the default.
2. Level k of block b is converged iff e[j, b] <= tau for every j >= k (tau = 0.02).
3. T_b = spp of the first converged level, or None.
(Rule 4, the labels, lives in `Stack.labels`.)

FLIP (`flip_evaluator`) ends the process with sys.exit on bad arguments and raises a bare
RuntimeError on others, so inputs are validated here first and both are turned into
ValueError.
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

import torch

from noisefeat.display import display as _display
from noisefeat.display import srgb_decode as _srgb_decode
from noisefeat.flip import check_ppd

from .stack import Stack, block_shape, update_labels

log = logging.getLogger(__name__)

DEFAULT_TAU = 0.02
DEFAULT_PPD = 67.0
# FLIP's widest filter at 67 ppd: the chromatic CSF reaches ceil(3 sqrt(0.04 / (2 pi^2)) 67)
# = 10 px, the edge/point detector ceil(3 * 0.5 * 0.082 * 67) = 9 px; 10 is the margin that
# was measured. 0 (DESIGN's definition) is the default.
DEFAULT_EDGE_MARGIN = 0


# ----------------------------------------------------------------------------- display

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
    import flip_evaluator

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


def _check_margin(edge_margin: int) -> int:
    if isinstance(edge_margin, bool) or not isinstance(edge_margin, (int, np.integer)) \
            or edge_margin < 0:
        raise ValueError(f"edge_margin must be a non-negative integer, got {edge_margin!r}")
    return int(edge_margin)


def block_means(values: np.ndarray, grid: Sequence[int] = (4, 4), edge_margin: int = 0) -> np.ndarray:
    """[H, W] map -> [gh*gw] per-block means (float64), row-major.

    With `edge_margin` m > 0 a block's mean leaves out pixels closer than m to the frame's
    edge; a block with no pixel left keeps all of its pixels.
    """
    v = np.asarray(values, np.float64)
    bh, bw = block_shape(v.shape[0], v.shape[1], grid)
    gh, gw = int(grid[0]), int(grid[1])
    plain = v.reshape(gh, bh, gw, bw).mean(axis=(1, 3)).reshape(gh * gw)
    m = _check_margin(edge_margin)
    if m == 0:
        return plain
    inside = np.zeros(v.shape, np.float64)
    inside[m:v.shape[0] - m, m:v.shape[1] - m] = 1.0
    count = inside.reshape(gh, bh, gw, bw).sum(axis=(1, 3)).reshape(gh * gw)
    total = (v * inside).reshape(gh, bh, gw, bw).sum(axis=(1, 3)).reshape(gh * gw)
    return np.where(count > 0, total / np.maximum(count, 1.0), plain)


def block_errors(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
                 grid: Sequence[int] = (4, 4), ppd: float = DEFAULT_PPD,
                 exposure: float = 0.0, edge_margin: int = DEFAULT_EDGE_MARGIN) -> np.ndarray:
    """e [K, n_blocks] (rule 1): per-block mean FLIP between display(reference) and levels.

    `levels_rgb` is [K, H, W, 3] or any iterable of [H, W, 3] linear images (a generator
    keeps memory to one level).
    """
    ref = np.asarray(reference_rgb)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ValueError(f"reference must be linear RGB [H, W, 3], got shape {ref.shape}")
    block_shape(ref.shape[0], ref.shape[1], grid)
    _check_margin(edge_margin)
    ref_d = display(ref, exposure)
    rows = []
    for k, lev in enumerate(levels_rgb):
        lev = np.asarray(lev)
        if lev.shape != ref.shape:
            raise ValueError(f"level {k} has shape {lev.shape}, the reference {ref.shape}")
        rows.append(block_means(flip_map(ref_d, display(lev, exposure), ppd), grid, edge_margin))
    if not rows:
        raise ValueError("no levels given")
    return np.stack(rows)


def thresholds_from_errors(e: np.ndarray, spp: Sequence[int],
                           tau: float = DEFAULT_TAU) -> list[int | None]:
    """Rules 2-3: T_b = spp of the first level from which every error is <= tau, else None."""
    err = np.asarray(e, np.float64)
    if err.ndim != 2:
        raise ValueError(f"errors must be [K, n_blocks], got shape {err.shape}")
    if len(spp) != err.shape[0]:
        raise ValueError(f"{len(spp)} spp values for {err.shape[0]} levels of errors")
    if any(b <= a for a, b in zip(spp, spp[1:])):
        raise ValueError(f"spp must be strictly increasing, got {list(spp)[:8]}")
    ok = err <= tau  # NaN compares False: never converged
    # converged[k, b] = all(ok[k:, b]): reverse cumulative AND
    converged = np.logical_and.accumulate(ok[::-1], axis=0)[::-1]
    out: list[int | None] = []
    for b in range(err.shape[1]):
        ks = np.flatnonzero(converged[:, b])
        out.append(int(spp[ks[0]]) if ks.size else None)
    return out


@dataclass(frozen=True)
class VirtualObserver:
    """The default expert: FLIP per block against the reference, threshold at tau."""

    tau: float = DEFAULT_TAU
    ppd: float = DEFAULT_PPD
    exposure: float = 0.0
    edge_margin: int = DEFAULT_EDGE_MARGIN

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tau) and self.tau >= 0):
            raise ValueError(f"tau must be a non-negative number, got {self.tau!r}")
        check_ppd(self.ppd)
        _check_margin(self.edge_margin)

    @property
    def labeler(self) -> dict:
        """The meta.json `labeler` entry describing this observer."""
        lab = {"name": "flip", "tau": self.tau, "ppd": self.ppd, "display": "clip+srgb",
               "exposure": self.exposure}
        return {**lab, "edge_margin": self.edge_margin} if self.edge_margin else lab

    def errors(self, reference: np.ndarray, levels: np.ndarray | Iterable[np.ndarray],
               grid: Sequence[int] = (4, 4)) -> np.ndarray:
        return block_errors(reference, levels, grid, self.ppd, self.exposure, self.edge_margin)

    def thresholds(self, reference: np.ndarray, levels: np.ndarray | Iterable[np.ndarray],
                   spp: Sequence[int], grid: Sequence[int] = (4, 4)) -> list[int | None]:
        return thresholds_from_errors(self.errors(reference, levels, grid), spp, self.tau)

    def label_stack(self, stack: Stack) -> list[int | None]:
        return self.thresholds(stack.reference(), stack.iter_levels(), stack.spp, stack.grid)


def label_stack(stack: Stack, tau: float = DEFAULT_TAU, ppd: float = DEFAULT_PPD,
                exposure: float = 0.0) -> list[int | None]:
    """Thresholds of a stack by the virtual observer (levels read one at a time)."""
    return VirtualObserver(tau, ppd, exposure).label_stack(stack)


def labeler_matches(labeler: Mapping | None, observer: VirtualObserver) -> bool:
    """Whether stored labels came from this observer (so relabelling can be skipped)."""
    return isinstance(labeler, Mapping) and all(
        labeler.get(k) == v for k, v in observer.labeler.items()) \
        and int(labeler.get("edge_margin", 0)) == observer.edge_margin


def relabel_if_stale(stack: Stack, observer: VirtualObserver) -> tuple[Stack, bool]:
    """Relabel a complete stack whose virtual-observer labels came from another observer.

    Labels of any other labeler (human, LISIC, synthetic) are the data itself and are
    never touched. Returns the stack as it now is and whether it was relabelled.
    """
    lab = stack.labeler
    if not (isinstance(lab, Mapping) and lab.get("name") == "flip"):
        return stack, False
    # the stack's own tau, ppd and exposure; the current observer's way of averaging
    obs = VirtualObserver(tau=float(lab.get("tau", observer.tau)), ppd=float(lab.get("ppd", observer.ppd)),
                          exposure=float(lab.get("exposure", observer.exposure)),
                          edge_margin=observer.edge_margin)
    if labeler_matches(lab, obs):
        return stack, False
    return update_labels(stack, obs.label_stack(stack), obs.labeler), True
