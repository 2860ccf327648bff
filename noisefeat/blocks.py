"""Cutting images into the grid of sub-images the method decides on, and back."""
from __future__ import annotations

import numpy as np


def _check_grid(shape: tuple[int, ...], grid: tuple[int, int]) -> tuple[int, int]:
    gh, gw = (int(g) for g in grid)
    if gh < 1 or gw < 1:
        raise ValueError(f"grid must be two positive integers, got {grid}")
    h, w = shape[0], shape[1]
    if h % gh or w % gw:
        raise ValueError(
            f"image of {h}x{w} pixels cannot be cut into a {gh}x{gw} grid of equal blocks; "
            f"use a size divisible by the grid (e.g. {h - h % gh}x{w - w % gw})")
    return h // gh, w // gw


def split_blocks(image: np.ndarray, grid: tuple[int, int] = (4, 4)) -> np.ndarray:
    """[H, W, C] (or [H, W]) -> [gh*gw, bh, bw, C] (or [gh*gw, bh, bw]), blocks row-major."""
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise ValueError(f"expected an image [H, W] or [H, W, C], got shape {img.shape}")
    bh, bw = _check_grid(img.shape, grid)
    gh, gw = img.shape[0] // bh, img.shape[1] // bw
    tail = img.shape[2:]
    out = img.reshape(gh, bh, gw, bw, *tail).swapaxes(1, 2)
    return np.ascontiguousarray(out.reshape(gh * gw, bh, bw, *tail))


def merge_blocks(blocks: np.ndarray, grid: tuple[int, int] = (4, 4)) -> np.ndarray:
    """Inverse of `split_blocks`."""
    b = np.asarray(blocks)
    gh, gw = grid
    if b.ndim not in (3, 4) or b.shape[0] != gh * gw:
        raise ValueError(f"expected {gh * gw} blocks [n, bh, bw(, C)], got shape {b.shape}")
    bh, bw = b.shape[1], b.shape[2]
    tail = b.shape[3:]
    out = b.reshape(gh, gw, bh, bw, *tail).swapaxes(1, 2)
    return np.ascontiguousarray(out.reshape(gh * bh, gw * bw, *tail))
