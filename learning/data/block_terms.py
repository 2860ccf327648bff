"""The virtual observer's per-block judgement (DESIGN "Virtual observer", rules 1-2).

1. E_k = the raw FLIP map (LDR, 67 ppd) between display(reference) and display(level k),
   computed on the whole frame (`frame_flip`).
2. e[k, b] = E_k pooled over block b: the largest of its 16x16 tile means (`noisefeat.pooling`),
   so noise confined to part of a block is not averaged away by the clean rest; version 3
   ("tile16-max+dots", the default) takes the larger of that and the dot term
   (`noisefeat.dots`: the block's 17th-largest per-pixel display error / 1.5 for 64x64), so a
   block holding more than a handful of visible dots is not converged either. Version 2
   ("tile16-max") and the first observer's block mean ("mean") stay selectable for comparison.

Why apart: the terms are computed once per level and cached next to a stack
(`stack_observer_errors`), and every pooling, tau and labeler is made from them without
FLIP; the thresholds are `observer`'s, the same terms per tile `tile_terms`'.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch

from noisefeat.display import display as _display
from noisefeat.dots import DOT_DENSITY, DOT_LEVEL, display_error, rank_pool
from noisefeat.pooling import (DEFAULT_POOLING, DOTS, FLIP_POOLINGS, POOLINGS, TILE_MAX, check_pooling, pool_blocks,
                               pool_maps)

from .cache import cached_array
from .frame_flip import DEFAULT_PPD, flip_map, level_maps
from .stack import Stack
from .stack_format import block_shape

DOT_TERM = "dots"
#: the observer's per-block terms (`observer_terms`), from which every pooling is made
TERMS = (*FLIP_POOLINGS, DOT_TERM)


def observer_terms(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
                   grid: Sequence[int] = (4, 4), ppd: float = DEFAULT_PPD, exposure: float = 0.0) -> np.ndarray:
    """The observer's per-block terms, float64 [len(TERMS), K, n_blocks]: the FLIP map of
    display(reference) against display(level k) pooled in each of `FLIP_POOLINGS`, and the
    dot term (`noisefeat.dots`) of the display images. `poolings` combines them.

    `levels_rgb` is [K, H, W, 3] or any iterable of [H, W, 3] linear images (a generator
    keeps memory to one level).
    """
    ref = np.asarray(reference_rgb)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ValueError(f"reference must be linear RGB [H, W, 3], got shape {ref.shape}")
    block_shape(ref.shape[0], ref.shape[1], grid)
    g = (int(grid[0]), int(grid[1]))
    rows = [[*(pool_blocks(emap, g, p) for p in FLIP_POOLINGS), block_dots(ref_t, lev_t, g)]
            for ref_t, lev_t, emap in level_maps(ref, levels_rgb, ppd, exposure)]
    if not rows:
        raise ValueError("no levels given")
    return np.asarray(rows, np.float64).transpose(1, 0, 2)


def block_dots(ref_display: torch.Tensor, level_display: torch.Tensor, grid: Sequence[int]) -> np.ndarray:
    """float64 [n_blocks]: the dot term (`noisefeat.dots`) of each block of a frame's grid."""
    gh, gw = int(grid[0]), int(grid[1])
    err = display_error(level_display, ref_display)
    bh, bw = err.shape[0] // gh, err.shape[1] // gw
    return rank_pool(err.reshape(gh, bh, gw, bw).permute(0, 2, 1, 3).reshape(gh * gw, bh, bw)).numpy()


def poolings(terms: np.ndarray) -> np.ndarray:
    """e [len(POOLINGS), K, n_blocks] from `observer_terms`: each FLIP pooling as it is, and
    version 3 (DOTS) the larger of the tile maximum and the dot term (NaN stays NaN)."""
    t = np.asarray(terms, np.float64)
    by_name = {**{p: t[i] for i, p in enumerate(FLIP_POOLINGS)},
               DOTS: np.maximum(t[FLIP_POOLINGS.index(TILE_MAX)], t[TERMS.index(DOT_TERM)])}
    return np.stack([by_name[p] for p in POOLINGS])


def pooled_errors(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
                  grid: Sequence[int] = (4, 4), ppd: float = DEFAULT_PPD, exposure: float = 0.0) -> np.ndarray:
    """e [len(POOLINGS), K, n_blocks] (rules 1-2) in every known pooling (one FLIP map per
    level serves them all; `observer_terms`)."""
    return poolings(observer_terms(reference_rgb, levels_rgb, grid, ppd, exposure))


def window_errors(reference_rgb: np.ndarray, image_rgb: np.ndarray, windows: Sequence[Sequence[int]],
                  ppd: float = DEFAULT_PPD, exposure: float = 0.0, pooling: str = DEFAULT_POOLING) -> np.ndarray:
    """e [len(windows)] of one image: the observer's error of each (x, y, w, h) window of
    the frame (FLIP on the whole frame, as rule 1 says; windows may overlap)."""
    check_pooling(pooling)
    ref_t, img_t = _display(np.asarray(reference_rgb), exposure), _display(np.asarray(image_rgb), exposure)
    emap = flip_map(np.ascontiguousarray(ref_t.numpy(), np.float32), np.ascontiguousarray(img_t.numpy(), np.float32), ppd)
    derr = display_error(img_t, ref_t)
    out = []
    for x, y, w, h in windows:
        win = (slice(y, y + h), slice(x, x + w))
        if pooling == DOTS:
            tile = pool_maps(emap[None][(slice(None), *win)], TILE_MAX)[0]
            out.append(max(tile, float(rank_pool(derr[win][None])[0])) if np.isfinite(tile) else tile)
        else:
            out.append(pool_maps(emap[None][(slice(None), *win)], pooling)[0])
    return np.asarray(out, np.float64)


def block_errors(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
                 grid: Sequence[int] = (4, 4), ppd: float = DEFAULT_PPD, exposure: float = 0.0,
                 pooling: str = DEFAULT_POOLING) -> np.ndarray:
    """e [K, n_blocks] (rules 1-2) in one pooling (`pooled_errors`)."""
    check_pooling(pooling)
    return pooled_errors(reference_rgb, levels_rgb, grid, ppd, exposure)[POOLINGS.index(pooling)]


def stack_observer_errors(stack: Stack, ppd: float = DEFAULT_PPD, exposure: float = 0.0,
                          computed: np.ndarray | None = None) -> np.ndarray:
    """e float64 [len(POOLINGS), K, n_blocks]: the observer's errors of a stack for every
    pooling. The FLIP poolings (one FLIP map per level) and the dot term are cached next to
    the stack apart, so relabelling at another tau or pooling costs no FLIP, and a stack
    labelled before version 3 only needs its dot term computed. `computed`: the terms a
    build just computed (`observer_terms`), stored instead of computed again."""
    k, n = stack.n_levels, stack.n_blocks
    # every term from one pass over the levels, made at most once (FLIP's pass makes the dots too)
    made: list[np.ndarray] = [] if computed is None else [np.asarray(computed, np.float64)]

    def all_terms() -> np.ndarray:
        if not made:
            made.append(observer_terms(stack.reference(), stack.iter_levels(), stack.grid, ppd, exposure))
        return made[0]

    def flip() -> np.ndarray:
        return all_terms()[:len(FLIP_POOLINGS)]

    def dots() -> np.ndarray:
        if made:
            return made[0][TERMS.index(DOT_TERM)]
        ref = _display(stack.reference(), exposure)      # FLIP cached already: the dot term alone
        return np.stack([block_dots(ref, _display(lev, exposure), stack.grid) for lev in stack.iter_levels()])
    flip_e = cached_array(stack, f"observer-e{exposure:g}-ppd{ppd:g}", (len(FLIP_POOLINGS), k, n), flip)
    dot_e = cached_array(stack, f"observer-dots-e{exposure:g}-l{DOT_LEVEL:g}-d{DOT_DENSITY}", (k, n), dots)
    return poolings(np.concatenate([flip_e, dot_e[None]]))
