"""Half buffers and the training-free `flip` score: FLIP between the two halves of a block.

A progressive render can keep two half buffers per pixel, as Cycles does: A, the mean of
the even-numbered passes, and B, the mean of the odd-numbered ones. They are two
independent estimates of the same image, so display(A) against display(B) differs only
by noise: no scene content is left in the comparison. The `flip` criterion measures that
difference the way DESIGN's observer measures the difference to the reference: e = the
raw LDR-FLIP map (67 pixels per degree) between display(A) and display(B), pooled as the
observer pools (the largest 16x16 tile mean), the map computed on the block alone (the
live loop only has the active blocks). A block is converged when e <= c(tau), with the
curve c(tau) calibrated on training scenes (`calibrate_flip_curve`, shipped in
`learning/flip.json`; a user's `noisestop calibrate` writes `flip.json` in the user data
directory, which readers prefer: `noisefeat.userdata`).

On a stored stack the passes come back exactly from consecutive cumulative levels
(`recover_passes`), and a `UnitAccumulator` fed with them holds the very half buffers the
live loop keeps, so `stack_flip_errors` scores every (level, block) as the render would.
"""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from noisefeat.display import check_exposure
from noisefeat.dots import DOT_DENSITY, DOT_LEVEL, OBSERVER_DOTS, halves_dots
from noisefeat.flip import flip_halves, pool_tiles
from noisefeat.flip_maps import flip_maps_tensor
from noisefeat.pooling import CRITERION_POOLING, DEFAULT_POOLING, pool_maps, tile_windows
from noisefeat.safeio import InputFileError, read_json
from noisefeat.userdata import find as find_user_file

from ..data.accumulator import UnitAccumulator
from ..data.cache import cached_array
from ..data.frame_flip import DEFAULT_PPD, display, flip_map
from ..data.observer import label_tau
from ..data.stack import Stack
from ..stoprule import FLAT_TOLERANCE, flat_blocks

log = logging.getLogger(__name__)

#: the shipped calibration; a user's own, of the same name, lives in the user data directory
FLIP_CALIBRATION = Path(__file__).parents[1] / "flip.json"
FLIP_USER_FILE = "flip.json"
DEFAULT_C = 0.02   # used only when no calibration file ships (flip.json says what is shipped)


def recover_passes(stack: Stack) -> Iterator[tuple[int, np.ndarray, int, np.ndarray]]:
    """Yield (k, level_k [H, W, 3] float64, pass spp, pass_k [H, W, 3] float64), one level at a time.

    Level k is the cumulative mean of spp[k] samples, so sum_k = spp[k] * L_k and the
    pass between two levels is (sum_k - sum_{k-1}) / (spp[k] - spp[k-1]) (pass 0 = L_0).
    Pixels whose stored level is non-finite give a non-finite pass; the accumulator drops
    them exactly as it drops a renderer's non-finite samples.
    """
    prev_sum: np.ndarray | None = None
    prev_spp = 0
    for k, s in enumerate(stack.spp):
        level = stack.level(k).astype(np.float64)
        total = level * float(s)
        n = int(s) - prev_spp
        with np.errstate(invalid="ignore", over="ignore"):
            pass_img = total / n if prev_sum is None else (total - prev_sum) / n
        yield k, level, n, pass_img
        prev_sum, prev_spp = total, int(s)


def check_constant_step(stack: Stack) -> None:
    """Warn when levels are not evenly spaced: the recovered passes then differ in size and
    the half buffers A and B hold unequal sample counts."""
    steps = np.diff([0, *stack.spp])
    if len(set(steps.tolist())) > 1:
        log.warning("%s: spp steps are not constant (%s...): recovered passes differ in size, "
                    "so the half buffers A/B are unbalanced", stack.path, steps[:4].tolist())


def check_halves(even: np.ndarray, odd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two half buffers as arrays: linear RGB [N, h, w, 3] of one shape, floating point."""
    a, b = np.asarray(even), np.asarray(odd)
    if a.shape != b.shape or a.ndim != 4 or a.shape[-1] != 3:
        raise ValueError(f"half buffers must be two linear RGB arrays [N, h, w, 3] of one shape, got "
                         f"{a.shape} and {b.shape}")
    if not (np.issubdtype(a.dtype, np.floating) and np.issubdtype(b.dtype, np.floating)):
        raise ValueError(f"half buffers must be floating point, got {a.dtype} and {b.dtype}")
    return a, b


def _check_halves(even: np.ndarray, odd: np.ndarray, exposure: float) -> tuple[np.ndarray, np.ndarray, float]:
    return (*check_halves(even, odd), check_exposure(exposure))


def halves_flip(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                ppd: float = DEFAULT_PPD, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """e float64 [N]: per block, the raw FLIP map between display(A) and display(B), pooled
    (`noisefeat.pooling`: the largest 16x16 tile mean, or "mean").

    `even`, `odd`: linear RGB blocks [N, h, w, 3] (the two half-buffer means). Non-finite
    values follow the display rule (NaN/-Inf black, +Inf white), so e is always finite.
    Computed for all blocks at once by `noisefeat.flip` (FLIP's LDR pipeline in torch, each
    block alone), which agrees with `flip-evaluator` (`halves_flip_evaluator`) to float32
    rounding at a small fraction of its cost (docs/benchmarks/speed.md "FLIP between the halves").
    """
    even, odd, exposure = _check_halves(even, odd, exposure)
    return flip_halves(even, odd, exposure, ppd, pooling)


def halves_flip_evaluator(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                          ppd: float = DEFAULT_PPD, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """`halves_flip` by NVIDIA's `flip-evaluator`, one block per call: the reference
    implementation that the torch route is tested and timed against."""
    even, odd, exposure = _check_halves(even, odd, exposure)
    if len(even) == 0:
        return np.zeros(0)
    return pool_maps(np.stack([flip_map(display(a, exposure), display(b, exposure), ppd)
                               for a, b in zip(even, odd)]), pooling)


def flip_offset(c: float) -> float:
    """The stop-rule offset that makes `score > offset` (score = -e) mean e <= c exactly."""
    if not (np.isfinite(c) and c >= 0):
        raise ValueError(f"flip threshold c must be a non-negative number, got {c!r}")
    return float(np.nextafter(-float(c), -np.inf))


def iter_stack_halves(stack: Stack, progress: bool = False) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """(k, even [n_blocks, bh, bw, 3], odd [...]) for every level k >= 1: the half buffers a
    `UnitAccumulator` fed with the stack's recovered passes holds (the live loop's
    buffers, bit for bit). Level 0 has none: B is still empty there."""
    check_constant_step(stack)
    acc = UnitAccumulator(stack.grid, stack.block)
    ids = list(range(stack.n_blocks))
    for k, _, n, pass_img in tqdm(recover_passes(stack), total=stack.n_levels, disable=not progress,
                                  desc=f"{stack.scene} halves", leave=False):
        acc.add_many(ids, stack.split(pass_img), n)
        if k:
            halves = [acc.half_buffer(b) for b in ids]
            yield k, np.stack([h[0] for h in halves]), np.stack([h[1] for h in halves])


def stack_flat(stack: Stack, exposure: float = 0.0) -> np.ndarray:
    """bool [K, n_blocks]: which sub-images the stop rule calls flat (learning.stoprule),
    cached next to the stack like the features."""
    return cached_array(stack, f"flat-e{exposure:g}-t{FLAT_TOLERANCE:.9g}", (stack.n_levels, stack.n_blocks),
                        lambda: np.stack([flat_blocks(stack.blocks(k), exposure) for k in range(stack.n_levels)]),
                        dtype=bool)


def stack_flip_errors(stack: Stack, exposure: float = 0.0, ppd: float = DEFAULT_PPD,
                      progress: bool = False, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """e float64 [K, n_blocks] of a stack; NaN where B is still empty (one pass only) and
    where the block's image is flat (the stop rule stops it whatever e is, so FLIP, the
    expensive part, is not run there, as in the live loop).

    Cached next to the stack (`.cache/flip-halves-*.npz`, atomic), since every
    calibration and evaluation reads it.
    """
    flat = stack_flat(stack, exposure)
    shape = (stack.n_levels, stack.n_blocks)

    def compute() -> np.ndarray:
        e = np.full(shape, np.nan)             # level 0 stays NaN: B is empty there
        for k, even, odd in iter_stack_halves(stack, progress):
            todo = np.flatnonzero(~flat[k])
            if todo.size:
                e[k, todo] = halves_flip(even[todo], odd[todo], exposure, ppd, pooling)
        return e
    return cached_array(stack, f"flip-halves-{pooling}-e{exposure:g}-ppd{ppd:g}", shape, compute)


def stack_halves_dots(stack: Stack, exposure: float = 0.0, progress: bool = False) -> np.ndarray:
    """d float64 [K, n_blocks]: the criteria's dot term of every sub-image (`noisefeat.dots.
    halves_dots` of its half buffers; compare with tau), NaN at level 0 (B empty). Cached
    next to the stack like the half-buffer FLIP."""
    shape = (stack.n_levels, stack.n_blocks)

    def compute() -> np.ndarray:
        d = np.full(shape, np.nan)         # level 0 stays NaN: B is empty there
        for k, even, odd in iter_stack_halves(stack, progress):
            d[k] = halves_dots(torch.as_tensor(even), torch.as_tensor(odd), exposure).numpy()
        return d
    return cached_array(stack, f"dots-halves-v2-e{exposure:g}-l{DOT_LEVEL:g}-d{DOT_DENSITY}", shape, compute)


def guard_dots(scores: np.ndarray, dots: np.ndarray, tau: float) -> np.ndarray:
    """`scores` with NaN (no stop) where the dot term exceeds tau: what the live criteria do
    with a block whose halves still disagree on isolated pixels (`renderer.criteria`)."""
    with np.errstate(invalid="ignore"):
        return np.where(np.asarray(dots) > tau, np.nan, scores)


def guarded_flip_scores(stack: Stack, exposure: float = 0.0, progress: bool = False,
                        pooling: str = CRITERION_POOLING) -> np.ndarray:
    """The flip criterion's scores [K, n_blocks] of a stack as the live loop makes them:
    -e (`stack_flip_errors`), NaN where the dot guard holds the block at the stack's tau."""
    return guard_dots(-stack_flip_errors(stack, exposure, progress=progress, pooling=pooling),
                      stack_halves_dots(stack, exposure, progress), label_tau(stack))


# ----------------------------------------------------------------------------- at tile grain


def stack_tile_terms(stack: Stack, tile: int, exposure: float = 0.0, ppd: float = DEFAULT_PPD,
                     progress: bool = False, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """float64 [3, K, n_tiles]: the flip criterion's terms per tile, as the live
    loop makes them at tile grain: the FLIP map between the halves of each whole block (its
    tiles' neighbours are context) pooled over the tile; the tile's dot term; whether the
    tile is flat (1.0) in the level's image. Tiles block-major (`noisefeat.pooling.
    tile_windows`); level 0 NaN (B empty) but for the flat test. Cached next to the stack."""
    windows = tile_windows(stack.block[0], stack.block[1], tile)
    shape = (3, stack.n_levels, stack.n_blocks * len(windows))

    def per_tile(fn: Any) -> np.ndarray:
        """fn(slices of one tile in [n, bh, bw, ...] arrays) for every tile, block-major."""
        return torch.stack([torch.as_tensor(fn((slice(None), slice(y, y + h), slice(x, x + w))))
                            for x, y, w, h in windows], dim=1).to(torch.float64).reshape(-1).numpy()

    def compute() -> np.ndarray:
        out = np.full(shape, np.nan)
        for k in range(stack.n_levels):
            blocks = torch.as_tensor(stack.blocks(k), dtype=torch.float64)
            out[2, k] = per_tile(lambda t: flat_blocks(blocks[t], exposure))
        for k, even, odd in iter_stack_halves(stack, progress):
            a, b = torch.as_tensor(even), torch.as_tensor(odd)
            out[0, k] = pool_tiles(flip_maps_tensor(a, b, exposure, ppd), windows, pooling).reshape(-1).numpy()
            out[1, k] = per_tile(lambda t: halves_dots(a[t], b[t], exposure))
        return out
    return cached_array(stack, f"tile{tile}-flip-{pooling}-e{exposure:g}-ppd{ppd:g}-l{DOT_LEVEL:g}", shape, compute)


def guarded_tile_flip_scores(stack: Stack, tile: int, exposure: float = 0.0, progress: bool = False,
                             estimate: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(scores [K, n_tiles], flat [K, n_tiles]) of the flip criterion at tile grain: -e of
    the tile's history (`learning.inputs.history.running`), or of a learned
    `estimate` [K, n_tiles] of its error, NaN where the tile's dot guard holds it
    at the stack's tau; flat where the tile is."""
    from .history import running

    terms = stack_tile_terms(stack, tile, exposure, progress=progress)
    e = running(terms[0], stack.spp) if estimate is None else np.asarray(estimate, np.float64)
    if e.shape != terms[0].shape:
        raise ValueError(f"{stack.scene}: an estimate of shape {e.shape} for tiles of shape {terms[0].shape}")
    return guard_dots(-e, terms[1], label_tau(stack)), terms[2] > 0.5


# ----------------------------------------------------------------------------- the shipped c


def load_flip_calibration(path: str | os.PathLike | None = None) -> dict[str, Any]:
    """The calibration curve c(tau), checked: a curve of increasing tau with non-negative c,
    for the pooling the criterion uses.

    Which file: `path` if given, else `flip.json` in the user data directory if the user
    calibrated, else the shipped `learning/flip.json` (`noisefeat.userdata`). Without any:
    the fallback c = DEFAULT_C at every tau, with a warning."""
    p = Path(path) if path is not None else find_user_file(FLIP_USER_FILE, FLIP_CALIBRATION)
    if not (p.exists() or p.is_symlink()):
        if path is not None:
            raise FileNotFoundError(f"{p}: no flip calibration file")
        log.warning("no flip calibration shipped (%s); using c = %g", p, DEFAULT_C)
        return {"c": DEFAULT_C, "source": "fallback", "pooling": CRITERION_POOLING, "curve": []}
    try:
        cal = read_json(p, "flip.json")
        curve = cal.get("curve") if isinstance(cal, dict) else None
        if not isinstance(cal, dict) or cal.get("pooling") != CRITERION_POOLING or not isinstance(curve, list):
            raise ValueError(f"not a c(tau) curve for pooling {CRITERION_POOLING!r} (a file calibrated for "
                             "the block mean, observer version 1?); recalibrate with `noisestop calibrate`")
        if cal.get("observer_pooling") != DEFAULT_POOLING or cal.get("observer_dots") != OBSERVER_DOTS:
            raise ValueError(f"c(tau) was calibrated against the observer pooling {cal.get('observer_pooling')!r} "
                             f"(dots {cal.get('observer_dots')}), this noisestop's observer is {DEFAULT_POOLING!r} "
                             f"(version 3, dots {OBSERVER_DOTS}); recalibrate with `noisestop calibrate`")
        tiles = cal.get("tiles") or {}
        if not isinstance(tiles, dict):
            raise ValueError(f"tiles must be an object of curves by tile size, got {type(tiles).__name__}")
        for part in (cal, *tiles.values()):          # the block curve, and one per tile size
            check_curve(part["curve"] if isinstance(part, dict) else None)
    except InputFileError as exc:            # one line naming the file, as the others
        raise InputFileError(f"{p}: unreadable flip calibration ({str(exc).split(': ', 1)[-1]})") from None
    except (ValueError, KeyError, TypeError, OverflowError) as exc:
        raise ValueError(f"{p}: unreadable flip calibration ({exc})") from None
    return {**cal, "source": str(p)}


def check_curve(curve: Any) -> None:
    """A c(tau) curve: points of finite, increasing, positive tau and non-negative c."""
    if not isinstance(curve, list):
        raise ValueError(f"a curve must be a list of points, got {type(curve).__name__}")
    taus = [float(r["tau"]) for r in curve]
    if not all(t > 0 for t in taus):
        raise ValueError(f"taus must be positive, got {[t for t in taus if not t > 0][:3]}")
    for r in curve:
        flip_offset(float(r["c"]))
    if not taus or any(b <= a for a, b in zip(taus, taus[1:])) or not all(np.isfinite(taus)):
        raise ValueError(f"taus must be finite and increasing, got {taus[:6]}")


def unit_calibration(cal: dict[str, Any], tile: int | None) -> dict[str, Any]:
    """The part of a calibration for one grain: the block curve, or with `tile` the curve
    calibrated per tile against the tile truth (``tiles`` in flip.json) on the
    history's statistic (a tile curve of another statistic is refused); a file
    without it gives the block curve, with a warning (`noisestop calibrate` makes both)."""
    if tile is None:
        return {**cal, "unit": cal.get("unit", "block")}
    part = (cal.get("tiles") or {}).get(str(int(tile)))
    if not isinstance(part, dict) or not isinstance(part.get("curve"), list):
        log.warning("%s has no c(tau) for %d-pixel tiles: the block curve is used (recalibrate with "
                    "`noisestop calibrate`)", cal.get("source", "flip.json"), tile)
        return {**cal, "unit": "block"}
    from .history import STATISTIC

    if part.get("statistic") != STATISTIC:     # c of one level's score is not c of the history's
        raise ValueError(f"{cal.get('source', 'flip.json')}: its c(tau) for {int(tile)}-pixel tiles was calibrated "
                         f"on {part.get('statistic', 'one level')!r} scores, this noisestop decides tiles from "
                         f"{STATISTIC!r}; recalibrate with `noisestop calibrate --tile {int(tile)}`")
    return {**part, "source": cal.get("source"), "unit": f"tile{int(tile)}"}


def flip_tau_range(cal: dict[str, Any]) -> tuple[float, float] | None:
    """The tau range a calibration covers (None: the fallback, any tau)."""
    curve = cal.get("curve") or []
    return (float(curve[0]["tau"]), float(curve[-1]["tau"])) if curve else None


def flip_c(cal: dict[str, Any], tau: float) -> float:
    """c(tau) from a calibration curve: interpolated linearly in log c against log tau
    between calibrated points (c falls with tau roughly as a power law); a tau outside the
    calibrated range is refused, naming the range."""
    t = float(tau)
    rng = flip_tau_range(cal)
    if rng is None:
        return float(cal["c"])
    lo, hi = rng
    if not (np.isfinite(t) and lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9)):
        raise ValueError(f"tau {tau!r} is outside the calibrated range [{lo:g}, {hi:g}] of the flip criterion "
                         f"({cal.get('source', 'flip.json')})")
    taus = np.log([float(r["tau"]) for r in cal["curve"]])
    cs = [float(r["c"]) for r in cal["curve"]]
    if min(cs) <= 0:
        return float(np.interp(np.log(t), taus, cs))
    return float(np.exp(np.interp(np.log(t), taus, np.log(cs))))
