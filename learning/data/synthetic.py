"""A small synthetic stack for tests: fast, deterministic, with realistic structure.

reference = albedo x shading (smooth patterns, linear values in about [0.03, 0.9]);
quick = the albedo alone (noise-free, "albedo-like" as Mitsuba's aov quick image);
levels are true cumulative means: level k adds (spp[k] - spp[k-1]) fresh unit-variance
samples per pixel to a running sum, so its noise has std noise * amplitude / sqrt(spp[k])
and consecutive levels give back the passes between them, like rendered stacks. The
amplitude grows from left to right so that blocks converge at different spp.
"""
from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from .stack import Stack
from .stack_write import write_stack

DEFAULT_SPP = (4, 8, 16, 32, 64, 128, 256, 512, 1024)


def synthetic_images(size: int = 64, spp: Sequence[int] = DEFAULT_SPP, seed: int = 0,
                     noise: float = 0.15) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reference [H, W, 3], quick [H, W, 3], levels [K, H, W, 3]) float32, H = W = size."""
    if size < 1:
        raise ValueError(f"size must be positive, got {size}")
    if not spp or any(s <= 0 for s in spp) or any(b <= a for a, b in zip(spp, spp[1:])):
        raise ValueError(f"spp must be strictly increasing positive integers, got {list(spp)}")
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) / size
    albedo = np.stack([0.45 + 0.35 * np.sin(2 * np.pi * x) * np.cos(np.pi * y),
                       0.40 + 0.30 * np.cos(2 * np.pi * (x + y)),
                       0.35 + 0.25 * np.sin(np.pi * (2 * y - x))], axis=-1)
    shading = 0.35 + 0.65 * np.exp(-((x - 0.3) ** 2 + (y - 0.4) ** 2) / 0.18)
    reference = albedo * shading[..., None]
    amplitude = (0.15 + 0.85 * x)[..., None]  # noisier to the right: staggered thresholds
    rng = np.random.default_rng(seed)
    total = np.zeros_like(reference)
    prev = 0
    levels = []
    for s in spp:
        n = int(s) - prev
        total += rng.standard_normal(reference.shape) * np.sqrt(n)  # sum of n unit samples
        prev = int(s)
        levels.append(np.maximum(reference + noise * amplitude * total / s, 0.0))
    return (reference.astype(np.float32), albedo.astype(np.float32),
            np.stack(levels).astype(np.float32))


def make_synthetic_stack(path: str | os.PathLike, scene: str = "synthetic", size: int = 64,
                         grid: Sequence[int] = (4, 4), spp: Sequence[int] = DEFAULT_SPP,
                         seed: int = 0, noise: float = 0.15, label: bool = True,
                         thresholds: Sequence[int | None] | None = None) -> Stack:
    """Write a synthetic format-v1 stack at `path` and return it.

    Labels: explicit `thresholds` (labeler "synthetic") if given, else the virtual observer
    when `label` (FLIP: ~0.1 s at 64x64 with 9 levels), else none. With the
    defaults the observer gives thresholds spread over 64..1024 spp plus a few None.
    """
    reference, quick, levels = synthetic_images(size, spp, seed, noise)
    labeler = None
    if thresholds is not None:
        labeler = {"name": "synthetic"}
    elif label:
        from .observer import VirtualObserver

        obs = VirtualObserver()
        thresholds = obs.thresholds(reference, levels, list(spp), grid)
        labeler = obs.labeler
    return write_stack(path, scene=scene, levels=list(levels), spp=list(spp),
                       reference=reference, quick=quick, reference_spp=int(spp[-1]) * 16,
                       quick_description="synthetic albedo", renderer="synthetic",
                       grid=grid, labeler=labeler, thresholds=thresholds,
                       synthetic={"seed": seed, "noise": noise})
