"""How every criterion is judged: on scenes it has never seen, per scene, in two groups.

The protocol which every figure of BENCHMARKS.md follows:

* Training and calibration see the training scenes only (the default dataset); the
  held-out scenes (`renderer.scenes.heldout`, `make heldout`) are a separate dataset that no
  model, offset or threshold is fitted on. `check_disjoint` refuses a scene on both sides.
* Knobs are calibrated on out-of-fold scores: the model's offset on leave-one-scene-out
  scores of the training scenes (`learning.evaluation.calibrate`), flip's c on the training scenes
  (it has nothing to fit).
* Results are reported per scene, and pooled in two groups: scenes that converge inside
  their stacks (at least `CONVERGING_SHARE` of their blocks reach the observer's
  threshold before the last level) and scenes that do not. A scene that never converges
  can only test "never stop early": pooled with the others, it would hide a scene that
  stops at 64 spp behind its own harmless zeros.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from typing import Any

from ..data.stack import Stack
from ..names import DEFAULT_TAU

CONVERGING_SHARE = 0.5
CONVERGING = "converging"
NOT_CONVERGING = "not_converging"


def default_test_scenes(scenes: list[str]) -> list[str]:
    """Every fourth scene by name, starting with the second: about a quarter held out (when
    a dataset has no separate held-out set)."""
    return sorted(scenes)[1::4]


def converged_share(stack: Stack) -> float:
    """Share of the stack's blocks whose observer threshold lies inside the stack."""
    if stack.thresholds is None:
        raise ValueError(f"{stack.path}: stack has no thresholds (not labelled)")
    return sum(t is not None for t in stack.thresholds) / max(1, len(stack.thresholds))


def scene_groups(stacks: Iterable[Stack]) -> dict[str, list[str]]:
    """{'converging': scenes, 'not_converging': scenes}, by `CONVERGING_SHARE`."""
    groups: dict[str, list[str]] = {CONVERGING: [], NOT_CONVERGING: []}
    for st in sorted(stacks, key=lambda s: s.scene):
        groups[CONVERGING if converged_share(st) >= CONVERGING_SHARE else NOT_CONVERGING].append(st.scene)
    return groups


def check_disjoint(train_scenes: Sequence[str], heldout_scenes: Sequence[str]) -> None:
    """A scene is never on both sides of the protocol."""
    both = sorted(set(train_scenes) & set(heldout_scenes))
    if both:
        raise ValueError(f"scene(s) {', '.join(both)} would be both trained on and held out; "
                         "a held-out scene must take no part in training or calibration")


def split_stacks(data: str, heldout: str | None = None, tau: float = DEFAULT_TAU) -> tuple[list[Stack], list[Stack]]:
    """(training stacks, held-out stacks) of the protocol, labelled by the observer at `tau`.

    With `heldout` (a dataset of scenes no one trains on), every scene of `data` is a
    training scene. Without it, the older in-dataset split (every 4th scene by name held
    out) is used, with a warning: such scenes are alike and often never converge.
    """
    from ..data.dataset_dir import read_stacks
    from ..data.relabel import observed

    stacks = [observed(s, tau) for s in read_stacks(data)]
    if not stacks:
        raise ValueError(f"{data}: no stacks found")
    if heldout is not None:
        test = [observed(s, tau) for s in read_stacks(heldout)]
        if not test:
            raise ValueError(f"{heldout}: no stacks found (make heldout builds the held-out dataset)")
        check_disjoint([s.scene for s in stacks], [s.scene for s in test])
        return stacks, test
    logging.getLogger(__name__).warning(
        "no held-out dataset given: scenes of %s are held out instead (make heldout builds the "
        "held-out dataset)", data)
    held = set(default_test_scenes([s.scene for s in stacks]))
    return [s for s in stacks if s.scene not in held], [s for s in stacks if s.scene in held]


def split_tables(data: str, heldout: str | None = None, **load: Any) -> tuple[Any, Any]:
    """(training table, held-out table) of `split_stacks`' scenes, loaded with `load`
    (learning.inputs.table.load_table's options)."""
    from ..inputs.table import load_table

    train, test = split_stacks(data, heldout, load.get("tau", DEFAULT_TAU))
    return (load_table(data, progress=False, scenes=[s.scene for s in train], **load),
            load_table(heldout or data, progress=False, scenes=[s.scene for s in test], **load))
