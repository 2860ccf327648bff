"""The stop rule (DESIGN "The stop rule"): one definition for every consumer.

A block stops at the first *decided* level whose score exceeds the offset; no level is
decided before `min_spp`; a stop is held (the block is never asked again); a flat block
(its display image within one 8-bit level in every channel) stops at once, whatever its
score, because it shows no noise at all and a model trained on textured scenes has no
business judging such out-of-distribution input.

Who uses it: training's offset calibration and `evaluate` (`StopRule.stops` on stored
score matrices), the simulation on stacks and the live render loop (`decide_active`,
the gate `renderer.live.passloop.PassLoop.run_round` calls, with a criterion's `StopRule.verdict`), and the HTTP service
(`StopRule.verdict` on the blocks of one request). A NaN score is no decision: the block
stays noisy. The dot guard (`dots_ratio`, `hold_dotted`) is the observer's sparse-outlier
term seen through the half buffers: the live loop's criteria and the served `halves` route
hold a dotted block noisy by it.

Nothing here imports torch at load time (the display transform and the dots are imported
where they run): the command line lists the criteria, which read this rule, without it.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .names import OFFSET_LIMIT

CONVERGED = np.int8(1)
NOISY = np.int8(-1)
FLAT_TOLERANCE = 1.0 / 255.0  # one 8-bit code value of the display transform


def check_offset(offset: float) -> float:
    """`offset` as a float if it is a number within +-OFFSET_LIMIT, else ValueError."""
    if isinstance(offset, bool) or not isinstance(offset, (int, float, np.integer, np.floating)) \
            or not -OFFSET_LIMIT <= offset <= OFFSET_LIMIT:
        shown = offset if not isinstance(offset, int) or abs(offset) < 10**30 else \
            f"a {len(str(abs(offset)))}-digit number"
        raise ValueError(f"offset must be a finite number in [{-OFFSET_LIMIT:g}, {OFFSET_LIMIT:g}], got {shown}")
    return float(offset)


def flat_blocks(blocks: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """bool [N]: linear RGB blocks [N, h, w, 3] whose display image varies by at most one
    8-bit level in every channel (non-finite pixels follow the display rule)."""
    from noisefeat.display import display_range

    return display_range(blocks, exposure) <= FLAT_TOLERANCE


def flat_halves(even: Any, odd: Any, exposure: float = 0.0) -> np.ndarray:
    """bool [N]: blocks whose two half buffers [N, h, w, 3] show one flat image: both finite,
    and every pixel of either within one 8-bit level of every pixel of both (the display
    range of the two together). Why not the flat test of their mean: halves that disagree
    completely (all NaN against grey, +3e38 against -3e38) can have a flat mean, and a
    block whose halves disagree is noisy, never flat."""
    import torch

    from noisefeat.display import display_range

    e, o = torch.as_tensor(even), torch.as_tensor(odd)
    both = torch.cat([e, o], dim=1)
    if not len(both):
        return np.zeros(0, bool)
    finite = torch.isfinite(both).flatten(1).all(dim=1).cpu().numpy()
    return finite & (display_range(both, exposure) <= FLAT_TOLERANCE)


def dots_ratio(even: Any, odd: Any, exposure: float, tau: float) -> np.ndarray:
    """[N]: each block's dot term from its half buffers [N, h, w, 3] relative to the
    noise target (`noisefeat.dots.halves_dots` / tau), computed where the buffers live (a
    device tensor stays there; only the numbers cross to the host). Above 1 a block still
    holds more isolated outlier pixels than the observer at tau lets through: the
    observer's version-3 rule seen through the halves."""
    import torch

    from noisefeat.dots import halves_dots

    if not len(even):
        return np.zeros(0)
    dots = halves_dots(torch.as_tensor(even), torch.as_tensor(odd), exposure)
    return dots.cpu().numpy() / tau


def hold_dotted(verdict: np.ndarray, dots: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """int8 `verdict` with NOISY where a block is dotted (`dots_ratio` above 1) and not flat:
    the one dot guard of every route (a flat block has no dots to see)."""
    dotted = np.asarray(dots) > 1
    return np.where(dotted & ~np.asarray(flat, bool), NOISY, np.asarray(verdict)).astype(np.int8)


def decide_active(active: np.ndarray, spp: int | np.ndarray, min_spp: int | None,
                  decide: Callable[[list[int]], np.ndarray], among: np.ndarray | None = None) -> np.ndarray:
    """One decision of the rule for the blocks still `active` (bool [B], updated in place).

    `spp`: the level's spp, one for every block or one per block (a budget round puts
    blocks at different spp); `among`: the block ids this decision is about (default:
    all). Nothing is decided below `min_spp`; otherwise `decide(ids)` answers (+1/-1 per
    id) for the active blocks only, and those it calls converged leave `active` for good.
    Returns the verdict row, int8 [B]: +1 / -1 for the blocks asked, 0 for the others.
    """
    row = np.zeros(len(active), np.int8)
    asked = active.copy()
    if among is not None:
        mask = np.zeros(len(active), bool)
        mask[np.asarray(among, np.int64)] = True
        asked &= mask
    if min_spp is not None:
        asked &= np.broadcast_to(np.asarray(spp), asked.shape) >= min_spp
    ids = np.flatnonzero(asked).tolist()
    if not ids:
        return row
    verdict = np.asarray(decide(ids))
    if verdict.shape != (len(ids),):
        raise RuntimeError(f"{len(ids)} blocks asked, {verdict.shape} verdicts returned")
    row[ids] = np.where(verdict > 0, CONVERGED, NOISY)
    active[np.asarray(ids)[verdict > 0]] = False
    return row


@dataclass(frozen=True)
class StopRule:
    """The rule with its two knobs: `offset` (the speed/accuracy knob: a larger offset
    stops later) and `min_spp` (no decision below it; None: from the first level)."""

    offset: float = 0.0
    min_spp: int | None = None

    def __post_init__(self) -> None:
        # any finite offset is a rule (stability matrix: 1e308 included); the user-facing
        # entry points hold offsets to OFFSET_LIMIT (`check_offset`)
        if not np.isfinite(self.offset):
            raise ValueError(f"offset must be a finite number, got {self.offset!r}")
        if self.min_spp is not None and (isinstance(self.min_spp, bool) or int(self.min_spp) != self.min_spp
                                         or self.min_spp < 1):
            raise ValueError(f"min_spp must be a positive integer or None, got {self.min_spp!r}")

    def verdict(self, score: np.ndarray, flat: np.ndarray | None = None) -> np.ndarray:
        """int8 [N] for one decided level: +1 where the block is flat or its score exceeds
        the offset, -1 elsewhere (a NaN score is -1)."""
        score = np.asarray(score, np.float64)
        with np.errstate(invalid="ignore"):
            converged = score > self.offset
        if flat is not None:
            flat = np.asarray(flat, bool)
            if flat.shape != score.shape:
                raise ValueError(f"flat {flat.shape} and scores {score.shape} differ in shape")
            converged = converged | flat
        return np.where(converged, CONVERGED, NOISY)

    def stops(self, scores: np.ndarray, spp: Sequence[int], flat: np.ndarray | None = None) -> np.ndarray:
        """Held verdicts V int8 [K, B] from per-level scores [K, B] (and flat flags [K, B]):
        -1 up to the level where the block stops, +1 from there on. The same levels are
        decided and the same blocks asked as in the render loop."""
        scores = np.asarray(scores, np.float64)
        if scores.ndim != 2 or scores.shape[0] != len(spp):
            raise ValueError(f"scores must be [levels, blocks] with {len(spp)} levels, got {scores.shape}")
        if flat is not None and np.shape(flat) != scores.shape:
            raise ValueError(f"flat {np.shape(flat)} and scores {scores.shape} differ in shape")
        K, B = scores.shape
        V = np.full((K, B), NOISY, np.int8)
        active = np.ones(B, bool)
        for k in range(K):
            if k:
                V[k] = V[k - 1]
            row = decide_active(active, int(spp[k]), self.min_spp,
                                lambda ids, k=k: self.verdict(scores[k, ids],
                                                              None if flat is None else flat[k, ids]))
            V[k, row > 0] = CONVERGED
        return V


class OffsetClassifierMixin:
    """`predict` of every model: the stop rule's verdict on `decision_function` at the
    fitted `offset_` (scikit-learn's `FixedThresholdClassifier` on the decision function,
    the offset playing `TunedThresholdClassifierCV.best_threshold_`, calibrated out of
    fold by `learning.evaluation.calibrate`). No flat-block test here: rows of features do not show
    whether their block was flat (`learning.models.bundle.Model` adds it)."""

    offset_: float

    def predict(self, X: Any) -> np.ndarray:
        """-1 / +1 per row."""
        return StopRule(float(self.offset_)).verdict(self.decision_function(X))  # type: ignore[attr-defined]
