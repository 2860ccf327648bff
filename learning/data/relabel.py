"""Stored labels made the virtual observer's: relabel in memory, add the tile truth, rewrite.

A stack's labeler record names its observer (`observer.VirtualObserver.labeler`). Labels of
another observer are never read as this one's: `observed` relabels in memory (from the
per-level errors cached next to the stack, so a new tau costs no FLIP), `relabel_if_stale`
rewrites meta.json; neither re-renders. Labels of any other labeler (human, LISIC,
synthetic) are the data itself and are never touched.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from noisefeat.pooling import DEFAULT_POOLING, TILE

from ..names import DEFAULT_TAU
from .check import ERROR, nonfinite_problem
from .dataset_dir import list_stacks
from .observer import is_virtual, labeler_matches, observer_for
from .stack import Stack, read_stack
from .stack_write import update_labels
from .tile_truth import TILE_TRUTH


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
    """The stack with its tile truth by the observer of its labels: as stored when
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
    never touched. Returns the stack as it now is and whether it was relabelled. A
    reference that `noisestop dataset check` calls an error (`check_reference`) is a
    ValueError, and nothing is written.
    """
    if not is_virtual(stack.labeler):
        return stack, False
    check_reference(stack)
    obs = observer_for(stack, tau, pooling)
    if labeler_matches(stack.labeler, obs) and stack.tile == TILE and stack.tile_thresholds is not None \
            and _current_tile_truth(stack.labeler):
        return stack, False
    return update_labels(stack, obs.label_stack(stack), obs.labeler, TILE, obs.label_tiles(stack)), True


def check_reference(stack: Stack) -> None:
    """ValueError if the stack's reference is one `noisestop dataset check` calls an error
    (`check.nonfinite_problem`): labels measured against NaN or Inf pixels are wrong."""
    problem = nonfinite_problem(stack.reference_path, stack.reference(), "reference", True)
    if problem is not None and problem.severity == ERROR:
        raise ValueError(f"{problem.path}: {problem.message}; not relabelled (labels against it would "
                         "be wrong): re-render the reference (`noisestop dataset check` lists every problem)")
