"""Cutting images into the grid of sub-images the method decides on, and back."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def grid_block_shape(shape: tuple[int, ...], grid: tuple[int, int]) -> tuple[int, int]:
    """The (height, width) of a `grid`'s blocks on an image of `shape`, or a ValueError saying why not."""
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
    """Cut an image into a grid of equal, non-overlapping blocks (the paper's sub-images).

    Parameters
    ----------
    image : numpy.ndarray
        [H, W, C] or [H, W]; H and W must be multiples of the grid's rows and columns.
    grid : tuple of int, default (4, 4)
        (rows, columns) of the grid; the paper's is 4x4.

    Returns
    -------
    numpy.ndarray
        [rows * columns, H / rows, W / columns, C] (or without C), contiguous; block 0 is the
        top-left one and blocks are numbered row-major, as in meta.json's `thresholds`.

    Raises
    ------
    ValueError
        If the image is not 2- or 3-dimensional, or the grid does not divide its size (the
        message suggests the nearest size that does).
    """
    img = np.asarray(image)
    if img.ndim not in (2, 3):
        raise ValueError(f"expected an image [H, W] or [H, W, C], got shape {img.shape}")
    bh, bw = grid_block_shape(img.shape, grid)
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


def compose(means: Sequence[np.ndarray], windows: Sequence[tuple[int, int, int, int]],
            spp: Sequence[int], frame: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image [H, W, C], spp per pixel [H, W], owner block per pixel [H, W]) of a frame
    whose (x, y, w, h) `windows` hold `means` at `spp` samples.

    Each pixel comes from the window holding it with the most samples (with keyed random
    numbers that window's samples include every other window's for the pixel). The one rule
    for the frame a render ends with: the renderer's (`renderer.live.block_windows`) and the
    simulation's on stored stacks (`learning.data.tile_truth`).
    """
    h, w = frame
    image = np.zeros((h, w, np.asarray(means[0]).shape[-1]), np.float64)
    best = np.full((h, w), -1, np.int64)
    owner = np.full((h, w), -1, np.int64)
    for b in np.argsort(np.asarray(spp), kind="stable"):     # most samples written last
        x, y, bw, bh = windows[b]
        image[y:y + bh, x:x + bw] = means[b]
        best[y:y + bh, x:x + bw] = spp[b]
        owner[y:y + bh, x:x + bw] = b
    if (owner < 0).any():
        raise ValueError("the block windows do not cover the frame")
    return image, best, owner
