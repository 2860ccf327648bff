"""The virtual observer (DESIGN "Virtual observer"): FLIP-based labels for a stack.

1. E_k = the raw FLIP map (LDR, 67 ppd) between display(reference) and display(level k),
   computed on the whole frame.
2. e[k, b] = E_k pooled over block b: the largest of its 16x16 tile means (`noisefeat.pooling`),
   so noise confined to part of a block is not averaged away by the clean rest; version 3
   ("tile16-max+dots", the default) takes the larger of that and the dot term
   (`noisefeat.dots`: the block's 17th-largest per-pixel display error / 1.5 for 64x64), so a
   block holding more than a handful of visible dots is not converged either. Version 2
   ("tile16-max") and the first observer's block mean ("mean") stay selectable for comparison.
3. Level k of block b is converged iff e[j, b] <= tau for every j >= k (tau = 0.02).
4. T_b = spp of the first converged level, or None.
(Rule 5, the labels, lives in `Stack.labels`.)

A stack's labeler record names its pooling; one without "pooling" was labelled by the
first observer (the mean). Labels of another observer are never read as this one's:
`observed` relabels in memory (from the per-level errors, cached next to the stack, so a
new tau costs no FLIP), `relabel_if_stale` rewrites meta.json; neither re-renders.

FLIP (`flip_evaluator`) ends the process with sys.exit on bad arguments and raises a bare
RuntimeError on others, so inputs are validated here first and both are turned into
ValueError.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import logging
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

import torch

from noisefeat.display import display as _display
from noisefeat.display import srgb_decode as _srgb_decode
from noisefeat.flip import check_ppd
from noisefeat.dots import DOT_DENSITY, DOT_LEVEL, OBSERVER_DOTS, display_error, rank_pool
from noisefeat.pooling import (DEFAULT_POOLING, DOTS, FLIP_POOLINGS, MEAN, POOLINGS, TILE, TILE_MAX, check_pooling,
                               pool_blocks, pool_maps, tile_windows)

from ..names import DEFAULT_TAU
from .cache import cached_array
from .stack import Stack, block_shape, list_stacks, read_stack, update_labels
from .tile_truth import TILE_TRUTH, final_frame_levels
from noisefeat.extras import require

log = logging.getLogger(__name__)

DEFAULT_PPD = 67.0
DOT_TERM = "dots"
#: the observer's per-block terms (`observer_terms`), from which every pooling is made
TERMS = (*FLIP_POOLINGS, DOT_TERM)


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
    rows = [[*(pool_blocks(emap, g, p) for p in FLIP_POOLINGS), _block_dots(ref_t, lev_t, g)]
            for ref_t, lev_t, emap in _level_maps(ref, levels_rgb, ppd, exposure)]
    if not rows:
        raise ValueError("no levels given")
    return np.asarray(rows, np.float64).transpose(1, 0, 2)


def _level_maps(ref: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray], ppd: float,
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


def _block_dots(ref_display: torch.Tensor, level_display: torch.Tensor, grid: Sequence[int]) -> np.ndarray:
    """float64 [n_blocks]: the dot term (`noisefeat.dots`) of each block of a frame's grid."""
    gh, gw = int(grid[0]), int(grid[1])
    err = display_error(level_display, ref_display)
    bh, bw = err.shape[0] // gh, err.shape[1] // gw
    return rank_pool(err.reshape(gh, bh, gw, bw).permute(0, 2, 1, 3).reshape(gh * gw, bh, bw)).numpy()


def tile_terms(reference_rgb: np.ndarray, levels_rgb: np.ndarray | Iterable[np.ndarray],
               grid: Sequence[int] = (4, 4), tile: int = TILE, ppd: float = DEFAULT_PPD,
               exposure: float = 0.0) -> np.ndarray:
    """The observer's terms per tile (issue 41), float64 [2, K, n_blocks * T]: for each
    block's tiles (`noisefeat.pooling.tile_windows`, block-major, as the renderer numbers
    its units), the mean of the frame's FLIP map over the tile and the tile's dot term (at
    most one outlier pixel in a 16x16 tile). `tile_errors` combines them."""
    ref = np.asarray(reference_rgb)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ValueError(f"reference must be linear RGB [H, W, 3], got shape {ref.shape}")
    block_shape(ref.shape[0], ref.shape[1], grid)
    rows = [_tile_row(ref_t, lev_t, frame_map, grid, tile)
            for ref_t, lev_t, frame_map in _level_maps(ref, levels_rgb, ppd, exposure)]
    if not rows:
        raise ValueError("no levels given")
    return np.asarray(rows, np.float64).transpose(1, 0, 2)


def _tile_row(ref_display: torch.Tensor, level_display: torch.Tensor, frame_map: np.ndarray, grid: Sequence[int],
              tile: int) -> tuple[np.ndarray, np.ndarray]:
    """(FLIP means [n_tiles], dot terms [n_tiles]) of one frame's tiles, block-major: the
    per-tile terms of `tile_terms` and of `VirtualObserver.frame_errors`."""
    gh, gw = int(grid[0]), int(grid[1])
    bh, bw = frame_map.shape[0] // gh, frame_map.shape[1] // gw
    windows = tile_windows(bh, bw, tile)

    def blocks(m: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        return m.reshape(gh, bh, gw, bw).transpose(1, 2).reshape(gh * gw, bh, bw) if isinstance(m, torch.Tensor) \
            else m.reshape(gh, bh, gw, bw).transpose(0, 2, 1, 3).reshape(gh * gw, bh, bw)
    emap = blocks(np.asarray(frame_map).astype(np.float64))
    derr = blocks(display_error(level_display, ref_display))
    flip_mean = np.stack([emap[:, y:y + h, x:x + w].mean(axis=(1, 2)) for x, y, w, h in windows], axis=1)
    dots = torch.stack([rank_pool(derr[:, y:y + h, x:x + w]) for x, y, w, h in windows], dim=1).numpy()
    return flip_mean.reshape(-1), dots.reshape(-1)


def tile_errors(terms: np.ndarray) -> np.ndarray:
    """e [K, n_tiles] from `tile_terms`: the larger of the tile's FLIP mean and its dot term
    (version 3 at the tile's grain; NaN stays NaN)."""
    return np.maximum(terms[0], terms[1])


def stack_tile_errors(stack: Stack, tile: int = TILE, ppd: float = DEFAULT_PPD, exposure: float = 0.0) -> np.ndarray:
    """e [K, n_tiles] of a stack (cached next to it, so relabelling at another tau costs no FLIP)."""
    n = stack.n_blocks * len(tile_windows(stack.block[0], stack.block[1], tile))
    terms = cached_array(stack, f"observer-tiles{tile}-e{exposure:g}-ppd{ppd:g}-l{DOT_LEVEL:g}", (2, stack.n_levels, n),
                         lambda: tile_terms(stack.reference(), stack.iter_levels(), stack.grid, tile, ppd, exposure))
    return tile_errors(terms)


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
    """The default expert: FLIP against the reference, pooled per block, threshold at tau."""

    tau: float = DEFAULT_TAU
    ppd: float = DEFAULT_PPD
    exposure: float = 0.0
    pooling: str = DEFAULT_POOLING

    def __post_init__(self) -> None:
        check_tau(self.tau)
        check_ppd(self.ppd)
        if self.pooling not in POOLINGS:
            raise ValueError(f"unknown pooling {self.pooling!r} for labels; known: {', '.join(POOLINGS)}")
        if not math.isfinite(self.exposure):
            raise ValueError(f"exposure must be a finite number, got {self.exposure!r}")

    @property
    def labeler(self) -> dict:
        """The meta.json `labeler` entry describing this observer (version 3 also records its
        dot level and density, so labels of other dot settings are relabelled, never read)."""
        dots = OBSERVER_DOTS if self.pooling == DOTS else {}
        return {"name": "flip", "tau": self.tau, "ppd": self.ppd, "display": "clip+srgb",
                "exposure": self.exposure, "pooling": self.pooling, **dots, "tile_truth": TILE_TRUTH}

    def errors(self, reference: np.ndarray, levels: np.ndarray | Iterable[np.ndarray],
               grid: Sequence[int] = (4, 4)) -> np.ndarray:
        """e [K, n_blocks] of this observer's pooling."""
        return block_errors(reference, levels, grid, self.ppd, self.exposure, self.pooling)

    def thresholds(self, reference: np.ndarray, levels: np.ndarray | Iterable[np.ndarray],
                   spp: Sequence[int], grid: Sequence[int] = (4, 4)) -> list[int | None]:
        return thresholds_from_errors(self.errors(reference, levels, grid), spp, self.tau)

    def stack_errors(self, stack: Stack) -> np.ndarray:
        """e [K, n_blocks] of a stack (cached next to it for every pooling at once)."""
        return stack_observer_errors(stack, self.ppd, self.exposure)[POOLINGS.index(self.pooling)]

    def label_stack(self, stack: Stack) -> list[int | None]:
        return thresholds_from_errors(self.stack_errors(stack), stack.spp, self.tau)

    def label_tiles(self, stack: Stack, tile: int = TILE) -> list[int | None]:
        """The tile truth on the frame a render ends with (`learning.data.tile_truth`, issue
        49): the fewest samples at which a tile may stop when every other tile stops at its
        own threshold, the finished frame still at or below tau in every block."""
        spp = list(stack.spp)
        start = np.array([len(spp) if t is None else spp.index(t) for t in self.label_tiles_same_samples(stack, tile)],
                         np.int64)
        at = final_frame_levels(stack, tile, self, start)
        return [None if k >= len(spp) else spp[k] for k in at.tolist()]

    def frame_errors(self, reference: np.ndarray, frame: np.ndarray, grid: Sequence[int],
                     tile: int) -> tuple[np.ndarray, np.ndarray]:
        """(block errors [n_blocks], tile errors [n_tiles]) of one frame, from one FLIP map: a
        block's error is this observer's version 3 (its largest 16x16 tile mean or its dot
        term); a tile's, its FLIP mean or its own dot term (at most one outlier pixel), as
        `tile_terms` has them (`_tile_row`). Tiles block-major."""
        (ref_t, lev_t, emap), = list(_level_maps(np.asarray(reference), [frame], self.ppd, self.exposure))
        g = (int(grid[0]), int(grid[1]))
        blocks = np.maximum(pool_blocks(emap, g, TILE_MAX), _block_dots(ref_t, lev_t, g))
        return blocks, np.maximum(*_tile_row(ref_t, lev_t, emap, g, tile))

    def label_tiles_same_samples(self, stack: Stack, tile: int = TILE) -> list[int | None]:
        """The first tile truth (issue 41), kept for comparison: each tile converged from the
        first level at which its FLIP mean is at most tau with at most one outlier pixel, at
        that level and every later one, on a frame where every tile has the same samples."""
        return thresholds_from_errors(stack_tile_errors(stack, tile, self.ppd, self.exposure), stack.spp, self.tau)


def check_tau(tau: object) -> float:
    """tau as a positive finite float, else ValueError (a noise target of 0 is never met)."""
    try:
        t = float(tau)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"tau must be a number, got {tau!r}") from None
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"tau must be a positive finite number, got {tau!r}")
    return t


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
        return np.stack([_block_dots(ref, _display(lev, exposure), stack.grid) for lev in stack.iter_levels()])
    flip_e = cached_array(stack, f"observer-e{exposure:g}-ppd{ppd:g}", (len(FLIP_POOLINGS), k, n), flip)
    dot_e = cached_array(stack, f"observer-dots-e{exposure:g}-l{DOT_LEVEL:g}-d{DOT_DENSITY}", (k, n), dots)
    return poolings(np.concatenate([flip_e, dot_e[None]]))


def label_stack(stack: Stack, tau: float = DEFAULT_TAU, ppd: float = DEFAULT_PPD,
                exposure: float = 0.0, pooling: str = DEFAULT_POOLING) -> list[int | None]:
    """Thresholds of a stack by the virtual observer."""
    return VirtualObserver(tau, ppd, exposure, pooling).label_stack(stack)


def label_tau(stack: Stack) -> float:
    """The noise target a stack's labels are at: its observer's tau (DEFAULT_TAU for labels
    of any other labeler), which the criteria's dot guard is judged at on that stack."""
    lab = stack.labeler
    return float(lab.get("tau", DEFAULT_TAU)) if is_virtual(lab) else DEFAULT_TAU  # type: ignore[union-attr]


def labeler_pooling(labeler: Mapping) -> str:
    """The pooling a labeler record names; none named is the first observer's block mean."""
    return check_pooling(labeler.get("pooling", MEAN))


def is_virtual(labeler: Mapping | None) -> bool:
    """Whether labels came from the virtual observer (else they are data: human, LISIC, ...)."""
    return isinstance(labeler, Mapping) and labeler.get("name") == "flip"


def labeler_matches(labeler: Mapping | None, observer: VirtualObserver) -> bool:
    """Whether stored labels came from this observer (so relabelling can be skipped)."""
    if not is_virtual(labeler):
        return False
    want = observer.labeler
    return labeler_pooling(labeler) == observer.pooling and all(  # type: ignore[arg-type]
        labeler.get(k) == want.get(k) for k in ("tau", "ppd", "exposure", "dot_level", "dot_density"))  # type: ignore[union-attr]


def observer_for(stack: Stack, tau: float | None = None, pooling: str = DEFAULT_POOLING) -> VirtualObserver:
    """The observer that labels `stack` at `tau` (None: the stack's own) and `pooling`, at
    the stack's own ppd and exposure."""
    lab = stack.labeler if isinstance(stack.labeler, Mapping) else {}
    return VirtualObserver(tau=float(lab.get("tau", DEFAULT_TAU)) if tau is None else check_tau(tau),
                           ppd=float(lab.get("ppd", DEFAULT_PPD)),
                           exposure=float(lab.get("exposure", 0.0)), pooling=pooling)


def observed(stack: Stack, tau: float | None = DEFAULT_TAU, pooling: str = DEFAULT_POOLING) -> Stack:
    """The stack with the labels of the observer at `tau` (None: the stack's own tau) and
    `pooling`, in memory (meta.json untouched).

    Virtual-observer labels of another tau or pooling (a stack of the first observer
    included) are recomputed from the cached per-level errors; labels of any other labeler
    (human, LISIC, synthetic) and unlabelled stacks are returned as they are.
    """
    if not is_virtual(stack.labeler) or stack.thresholds is None:
        return stack
    obs = observer_for(stack, tau, pooling)
    if labeler_matches(stack.labeler, obs):
        return stack
    return dataclasses.replace(stack, thresholds=obs.label_stack(stack), labeler=obs.labeler, tile=None,
                               tile_thresholds=None)


def with_tile_truth(stack: Stack, tile: int = TILE) -> Stack:
    """The stack with its tile truth (issue 41) by the observer of its labels: as stored when
    meta.json holds it for this observer and tile, else computed (cached per stack)."""
    if stack.tile == tile and stack.tile_thresholds is not None and _current_tile_truth(stack.labeler):
        return stack
    if not is_virtual(stack.labeler):
        raise ValueError(f"{stack.path}: labels of labeler {(stack.labeler or {}).get('name')!r} have no tile "
                         "truth (only the virtual observer's can be computed)")
    obs = observer_for(stack)
    return dataclasses.replace(stack, tile=tile, tile_thresholds=obs.label_tiles(stack, tile),
                               labeler={**stack.labeler, "tile_truth": obs.labeler["tile_truth"]})  # type: ignore[dict-item]


def _current_tile_truth(labeler: Mapping | None) -> bool:
    """Whether stored tile thresholds are this version's (`learning.data.tile_truth`)."""
    return isinstance(labeler, Mapping) and labeler.get("tile_truth") == TILE_TRUTH


def read_observed(root: str, tau: float | None = DEFAULT_TAU, pooling: str = DEFAULT_POOLING) -> list[Stack]:
    """Every stack under `root`, labelled by the observer at `tau` and `pooling` (`observed`)."""
    return [observed(read_stack(p), tau, pooling) for p in list_stacks(root)]


def relabel_if_stale(stack: Stack, pooling: str = DEFAULT_POOLING,
                     tau: float | None = None) -> tuple[Stack, bool]:
    """Rewrite a complete stack's virtual-observer labels in meta.json when they came from
    another observer (another pooling, or `tau` when given; None keeps the stack's own).

    Labels of any other labeler (human, LISIC, synthetic) are the data itself and are
    never touched. Returns the stack as it now is and whether it was relabelled.
    """
    if not is_virtual(stack.labeler):
        return stack, False
    obs = observer_for(stack, tau, pooling)
    if labeler_matches(stack.labeler, obs) and stack.tile == TILE and stack.tile_thresholds is not None \
            and _current_tile_truth(stack.labeler):
        return stack, False
    return update_labels(stack, obs.label_stack(stack), obs.labeler, TILE, obs.label_tiles(stack)), True
