"""The tile truth on the frame a render ends with (DESIGN "Decision grain").

The same-samples tile truth judged each 16x16 tile on a level where every tile has the
same samples. A render ends with each tile at its own stop, and a noisier neighbour reaches
a tile through FLIP's filters (about 10 px at 67 ppd): stopping every tile at that truth
left 27 blocks above tau where the block oracle left 14. This truth is measured on the
frame the render ends with instead, as a fixed point on the stack:

1. start from the same-samples truth (each tile's first level from which its FLIP mean is
   at most tau with at most one outlier pixel, at every later level too);
2. put the frame together with every tile at its current level (each pixel from the tile
   holding it with the most samples, as the renderer composes it) and judge it by the
   version-3 observer, per block and per tile;
3. in every block above tau, move each tile whose own error there is above tau one level
   on (where none is, the block's worst tiles: the block's dot term failed); a tile that is
   at the last level already can only be helped by its context, so its neighbours (the
   tiles that touch it, across block edges too) move one level on instead, unless the
   tile has no same-samples threshold either (noisy of itself: no context would help);
4. repeat until no tile moves.

Tiles only ever move later, so it ends, after at most as many rounds as levels. Every block
whose tiles did not reach the last level ends at or below tau by construction; a tile that
is still above tau at the last level has no threshold (censored), as in the same-samples truth.
What a tile's threshold means: the fewest samples at which it may stop given that every
other tile stops at its own threshold; its neighbours are its context.
"""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from noisefeat.blocks import compose
from noisefeat.dots import DOT_LEVEL
from noisefeat.pooling import tile_windows

from .cache import cached_array
from .stack import Stack
from .stack_format import block_shape

#: names the tile truth a stack's labeler record carries (`VirtualObserver.labeler`): tile
#: thresholds of another version are recomputed, never read as this one's
TILE_TRUTH = "final-frame"


class FrameJudge(Protocol):
    """What judges a frame here: the virtual observer (`learning.data.observer.
    VirtualObserver`), passed in so that this module and the observer's do not import each
    other."""

    tau: float
    ppd: float
    exposure: float

    def frame_errors(self, reference: np.ndarray, frame: np.ndarray, grid: Sequence[int],
                     tile: int) -> tuple[np.ndarray, np.ndarray]: ...


def unit_windows(width: int, height: int, grid: Sequence[int], tile: int) -> list[tuple[int, int, int, int]]:
    """(x, y, w, h) in the frame of every tile of every block of `grid`, block-major (the
    renderer's and `tile_terms`' numbering)."""
    bh, bw = block_shape(height, width, grid)
    inner = tile_windows(bh, bw, tile)
    return [(bx * bw + x, by * bh + y, w, h) for by in range(int(grid[0])) for bx in range(int(grid[1]))
            for x, y, w, h in inner]


def compose_levels(levels: np.ndarray, at: np.ndarray, windows: Sequence[tuple[int, int, int, int]]) -> np.ndarray:
    """The frame [H, W, 3] with tile u taken from level `at[u]` of `levels` [K, H, W, 3]; a
    pixel two tiles share comes from the one at the later level (most samples win: the
    renderer's `noisefeat.blocks.compose`)."""
    means = [levels[k, y:y + h, x:x + w] for k, (x, y, w, h) in zip(np.asarray(at).tolist(), windows)]
    return compose(means, windows, at, levels.shape[1:3])[0].astype(levels.dtype)


def touching(windows: Sequence[tuple[int, int, int, int]]) -> np.ndarray:
    """bool [n, n]: which windows touch or overlap another (diagonal neighbours included)."""
    x, y, w, h = (np.array([win[i] for win in windows])[:, None] for i in range(4))
    near = (x <= (x + w).T) & (x.T <= x + w) & (y <= (y + h).T) & (y.T <= y + h)
    np.fill_diagonal(near, False)
    return near


def fixed_point(levels: np.ndarray, reference: np.ndarray, start: Sequence[int], grid: Sequence[int],
                tile: int, observer: FrameJudge) -> tuple[np.ndarray, int]:
    """(level index of each tile [n_tiles], rounds) of the fixed point (module docstring),
    from the level indices `start` (the same-samples truth; len(levels) where it has none:
    such a tile is noisy of itself, and its neighbours are not held for it). A tile still
    above tau at the last level gets len(levels): no threshold. `observer` judges each
    composed frame (`VirtualObserver`: its tau and `frame_errors`)."""
    tau = observer.tau
    last = len(levels) - 1
    hopeless = np.asarray(start, np.int64) > last
    at = np.minimum(np.asarray(start, np.int64), last)
    h, w = reference.shape[:2]
    windows = unit_windows(w, h, grid, tile)
    per_block = len(windows) // (int(grid[0]) * int(grid[1]))
    near = touching(windows)
    rounds = 0
    while True:
        rounds += 1
        block_e, tile_e = observer.frame_errors(reference, compose_levels(levels, at, windows), grid, tile)
        move = np.zeros(len(at), bool)
        for b in np.flatnonzero(~(block_e <= tau)):
            own = slice(b * per_block, (b + 1) * per_block)
            bad = ~(tile_e[own] <= tau)
            if not bad.any():          # the block's dot term: its worst tiles carry it
                bad = tile_e[own] >= np.nanmax(tile_e[own]) if np.isfinite(tile_e[own]).any() else ~bad
            move[own] |= bad
        bad, capped = move, move & (at >= last) & ~hopeless
        move = (bad | (near[capped].any(axis=0) if capped.any() else False)) & (at < last)
        if not move.any():
            at[bad] = len(levels)          # above tau at the last level (all that can move has): censored
            return at, rounds
        at[move] += 1


def final_frame_levels(stack: Stack, tile: int, observer: FrameJudge, start: np.ndarray) -> np.ndarray:
    """The fixed point's level of every tile of `stack` (len(levels): none), from the
    same-samples truth's level indices `start`; cached next to the stack per observer (one
    fixed point costs a FLIP of the frame a round)."""
    def compute() -> np.ndarray:
        levels = np.stack([np.asarray(x, np.float32) for x in stack.iter_levels()])
        at, _ = fixed_point(levels, np.asarray(stack.reference(), np.float32), start, stack.grid, tile, observer)
        return at.astype(np.float64)
    name = (f"tile{tile}-final-frame-t{observer.tau:g}-e{observer.exposure:g}-ppd{observer.ppd:g}-l{DOT_LEVEL:g}"
            f"-{hashlib.sha256(np.asarray(start, np.int64).tobytes()).hexdigest()[:12]}")
    return cached_array(stack, name, (len(start),), compute).astype(np.int64)


class FinalFrame:
    """The frame a simulated render of `stack` ends with, judged by the version-3 block
    observer: each unit (a tile of `tile` pixels, or a whole block when None) at the level it
    stopped at, put together as the renderer composes it. The judge of every stop
    (DESIGN "The judge of every stop is the final frame"): `renderer.simulation.simulate.end_of_render`
    and the calibration against blocks above tau at the end. `observer`: the stack's at the
    noise target (`learning.data.observer.observer_for`). Levels are read once."""

    def __init__(self, stack: Stack, tile: int | None, observer: FrameJudge) -> None:
        self.stack, self.observer, self.tau = stack, observer, observer.tau
        self.tile = max(stack.block) if tile is None else int(tile)
        self.windows = unit_windows(stack.width, stack.height, stack.grid, self.tile)
        self.levels = np.stack([np.asarray(x, np.float32) for x in stack.iter_levels()])
        self.reference = np.asarray(stack.reference(), np.float32)
        #: bool [n_blocks]: the blocks whose truth converges in the stack
        self.converging = np.array([t is not None for t in (stack.thresholds or [None] * stack.n_blocks)])
        self._seen: dict[bytes, np.ndarray] = {}

    def block_errors(self, at: np.ndarray) -> np.ndarray:
        """e [n_blocks] of the frame with unit u at level `at[u]` (the last where at[u] is
        past it); the same stops are judged once."""
        at = np.minimum(np.asarray(at, np.int64), len(self.levels) - 1)
        key = at.tobytes()
        if key not in self._seen:
            self._seen[key], _ = self.observer.frame_errors(
                self.reference, compose_levels(self.levels, at, self.windows), self.stack.grid, self.tile)
        return self._seen[key]

    def judge(self, verdicts: np.ndarray) -> dict[str, float]:
        """``above_tau`` (blocks above tau), ``early`` (of those, blocks whose own truth
        converges in the stack: noise left that the observer says could be gone),
        ``converging`` (such blocks), ``blocks`` and ``worst`` of the frame verdicts V
        [K, n_units] end with (each unit at its first +1 level, the last if none)."""
        stopped = np.asarray(verdicts) > 0
        e = self.block_errors(np.where(stopped.any(axis=0), stopped.argmax(axis=0), len(stopped) - 1))
        above = ~(e <= self.tau)
        conv = self.converging
        return {"above_tau": int(above.sum()), "early": int((above & conv).sum()), "converging": int(conv.sum()),
                "blocks": int(e.size), "worst": float(np.nanmax(e))}
