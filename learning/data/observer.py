"""The virtual observer (DESIGN "Virtual observer"): FLIP-based labels for a stack.

Rules 1-2, the per-block errors, are `block_terms`' (FLIP by `frame_flip`); the same terms
per tile are `tile_terms`'. Here:

3. Level k of block b is converged iff e[j, b] <= tau for every j >= k (tau = 0.02).
4. T_b = spp of the first converged level, or None.
(Rule 5, the labels, lives in `Stack.labels`.)

`VirtualObserver` is the expert; its labeler record (meta.json `labeler`) names its tau,
ppd, exposure and pooling, so labels of another observer are never read as this one's:
one without "pooling" was labelled by the first observer (the mean). `relabel` makes
stored labels this observer's.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from noisefeat.dots import OBSERVER_DOTS
from noisefeat.flip_kernels import check_ppd
from noisefeat.pooling import DEFAULT_POOLING, DOTS, MEAN, POOLINGS, TILE, TILE_MAX, check_pooling, pool_blocks

from ..names import DEFAULT_TAU
from .block_terms import block_dots, block_errors, stack_observer_errors
from .frame_flip import DEFAULT_PPD, level_maps
from .stack import Stack
from .tile_terms import stack_tile_errors, tile_row
from .tile_truth import TILE_TRUTH, final_frame_levels


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
        """The tile truth on the frame a render ends with (`learning.data.tile_truth`): the
        fewest samples at which a tile may stop when every other tile stops at its
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
        `tile_terms` has them (`tile_row`). Tiles block-major."""
        (ref_t, lev_t, emap), = list(level_maps(np.asarray(reference), [frame], self.ppd, self.exposure))
        g = (int(grid[0]), int(grid[1]))
        blocks = np.maximum(pool_blocks(emap, g, TILE_MAX), block_dots(ref_t, lev_t, g))
        return blocks, np.maximum(*tile_row(ref_t, lev_t, emap, g, tile))

    def label_tiles_same_samples(self, stack: Stack, tile: int = TILE) -> list[int | None]:
        """The same-samples tile truth, kept for comparison: each tile converged from the
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
