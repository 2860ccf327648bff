"""Run a stopping criterion over stored stacks instead of rendering (offline evaluation).

Level k of a stack is the cumulative mean of spp[k] samples; the passes between levels
come back exactly (`learning.inputs.halves.recover_passes`), and feeding them to a
`BlockAccumulator` gives the very half buffers the live loop keeps (A = even passes,
B = odd passes). With a constant step every pass has the same size and A and B hold
equal sample counts, as in the live loop; with a varying step (e.g. doubling spp) halves
are unbalanced and a warning says so.

`simulate_stack` then runs the live loop's own pass step (`renderer.passloop.PassLoop`):
once spp >= min_spp, after each level, only the still-active blocks are asked, and a block
once converged stays converged and is never asked again. The verdict matrix V [K, B] therefore holds -1 up to
the level where the loop would have stopped the block and +1 from there on, which is what
`learning.evaluation.metrics.evaluate_verdicts` scores.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learning.evaluation.generalisation import scene_groups
from learning.inputs.halves import check_constant_step, recover_passes
from learning.evaluation.metrics import evaluate_verdicts
from learning.data.observer import observed, read_observed
from learning.data.stack import Stack, list_stacks, read_stack, read_stacks
from learning.names import DEFAULT_TAU

from .criteria import Criterion
from .passloop import PassLoop

logger = logging.getLogger(__name__)


def simulate_stack(stack: Stack, criterion: Criterion, min_spp: int | None = None,
                   progress: bool = False) -> np.ndarray:
    """Verdicts V int8 [K, n_blocks] the live loop would produce on this stack.

    `min_spp` (None: no minimum): no decision before that many samples.
    """
    if min_spp is not None and min_spp < 1:
        raise ValueError(f"min_spp must be a positive integer, got {min_spp!r}")
    n = stack.n_blocks
    K = stack.n_levels
    V = np.full((K, n), -1, np.int8)
    quick = stack.split(stack.quick()) if criterion.needs_quick else None
    if quick is not None:
        criterion.prepare(list(range(n)), quick)
    if criterion.needs_halves:
        check_constant_step(stack)
    loop = PassLoop(criterion, tuple(stack.grid), tuple(stack.block), min_spp, quick)
    bar = tqdm(total=K, desc=f"{stack.scene} simulate", unit="lvl", disable=not progress, leave=False)
    for k, _, pass_spp, pass_img in recover_passes(stack):
        bar.update(1)
        ids = loop.active_ids
        if not ids:
            V[k:] = 1
            break
        loop.step(ids, [(stack.split(pass_img)[ids], pass_spp)])   # stopped blocks get no more samples
        V[k, ~loop.active] = 1
    bar.close()
    return V


def _as_stacks(stacks: Stack | str | os.PathLike | Iterable[Stack | str | os.PathLike],
               tau: float = DEFAULT_TAU) -> list[Stack]:
    """Stacks as given (already labelled as the caller wants), or read from directories
    and labelled by the observer at `tau` (`learning.data.observer.observed`)."""
    if isinstance(stacks, Stack):
        return [stacks]
    if isinstance(stacks, (str, os.PathLike)):
        return [observed(s, tau) for s in read_stacks(stacks)]
    out = []
    for s in stacks:
        out.extend(_as_stacks(s, tau) if not isinstance(s, Stack) else [s])
    return out


def evaluate_criterion(stacks: Stack | str | os.PathLike | Iterable[Stack | str | os.PathLike],
                       criterion_factory: Callable[[Stack], Criterion], min_spp: int | None = None,
                       progress: bool = False, tau: float = DEFAULT_TAU) -> dict[str, Any]:
    """DESIGN metrics of a criterion simulated on labelled stacks, overall and per scene.

    `stacks`: a dataset directory, a stack, or a list of either. `criterion_factory(stack)`
    returns a fresh criterion for each stack (the oracle needs that stack's thresholds).
    Stacks read from directories are labelled by the observer at `tau`. The result is `evaluate_verdicts`' dict plus ``criterion`` (its description) and
    ``counters`` (summed criterion counters and timers).
    """
    todo = _as_stacks(stacks, tau)
    if not todo:
        raise ValueError(f"no stacks found in {stacks!r}")
    per_scene: dict[str, tuple] = {}
    counters: dict[str, float] = {}
    description: dict[str, Any] = {}
    for st in tqdm(todo, desc="stacks", unit="stack", disable=not progress):
        if st.thresholds is None:
            raise ValueError(f"{st.path}: stack has no thresholds; label it first")
        if st.scene in per_scene:
            raise ValueError(f"{st.path}: scene {st.scene!r} appears twice")
        crit = criterion_factory(st)
        V = simulate_stack(st, crit, min_spp=min_spp, progress=progress)
        per_scene[st.scene] = (V, st.labels(), st.thresholds, st.spp)
        for k, v in {**crit.counters, **crit.timers}.items():
            counters[k] = counters.get(k, 0) + v
        description = crit.describe()
        if description.get("name") == "oracle":
            description = {"name": "oracle"}
    out = evaluate_verdicts(per_scene, scene_groups(todo))
    out["criterion"] = description
    out["counters"] = counters
    return out


def criterion_factory(kind: str, *, model: str | None = None, server: str | None = None,
                      threshold: float | None = None, offset: float | None = None,
                      exposure: float = 0.0, tau: float = DEFAULT_TAU) -> Callable[[Stack], Criterion]:
    """A fresh criterion per stack for `evaluate_criterion`, from command-line style options.

    The model (or server connection) is set up once and shared; the oracle takes each
    stack's own thresholds. `threshold`: flip's c or variance's threshold (None: their
    defaults); `offset`: the model's decision offset (None: its calibrated one at `tau`,
    the noise target, which also picks flip's c).
    """
    from .criteria import CRITERIA, ModelCriterion, OracleCriterion, build_criterion

    if kind not in CRITERIA:
        raise ValueError(f"unknown criterion {kind!r}; choose one of {', '.join(CRITERIA)}")
    if kind == "oracle":
        def oracle(st: Stack) -> Criterion:
            if st.thresholds is None:
                raise ValueError(f"{st.path}: stack has no thresholds; the oracle needs them")
            return OracleCriterion(st.thresholds)
        return oracle
    if kind == "model":
        shared = build_criterion("model", model=model, server=server, offset=offset, exposure=exposure, tau=tau)
        assert isinstance(shared, ModelCriterion)
        return lambda st: ModelCriterion(shared.model, exposure=shared.exposure, offset=shared.offset, tau=tau)
    return lambda st: build_criterion(kind, threshold=threshold, exposure=exposure, tau=tau)


def evaluate_criterion_cli(data: str | os.PathLike, criterion: str, scenes: list[str] | None = None, *,
                           min_spp: int | None = None, threshold: float | None = None,
                           offset: float | None = None, model: str | None = None,
                           server: str | None = None, progress: bool = True,
                           tau: float = DEFAULT_TAU) -> dict[str, Any]:
    """What `noisestop evaluate --criterion C` runs for a rule criterion: simulate C on the
    stacks of `data` (only `scenes` if given), labelled by the observer at the noise target
    `tau`, and return the DESIGN metrics, overall and per scene."""
    factory = criterion_factory(criterion, model=model, server=server, threshold=threshold, offset=offset,
                                tau=tau)         # a knob out of range fails before any stack is read
    stacks = read_observed(str(data), tau)
    if scenes:
        missing = sorted(set(scenes) - {st.scene for st in stacks})
        if missing:
            raise ValueError(f"{data}: no stack of scene(s) {', '.join(missing)}")
        stacks = [st for st in stacks if st.scene in scenes]
    unlabelled = [str(st.path) for st in stacks if st.thresholds is None]
    if unlabelled:
        logger.warning("skipping %d unlabelled stack(s): %s", len(unlabelled), ", ".join(unlabelled[:3]))
        stacks = [st for st in stacks if st.thresholds is not None]
    if not stacks:
        raise ValueError(f"{data}: no labelled stacks to evaluate on")
    for st in stacks:
        st.validate()
    out = evaluate_criterion(stacks, factory, min_spp=min_spp, progress=progress, tau=tau)
    return {**out, "tau": float(tau)}


def find_reference(reference: Stack | str | os.PathLike, scene: str, tau: float = DEFAULT_TAU) -> Stack:
    """The stack of `scene` in a dataset directory (or that stack itself), labelled by the
    observer at `tau`."""
    if isinstance(reference, Stack):
        return observed(reference, tau)
    root = Path(reference)
    stacks = [observed(read_stack(p), tau) for p in list_stacks(root)]
    match = [s for s in stacks if s.scene == scene]
    if len(stacks) == 1 and not match:
        raise ValueError(f"{root}: the stack there is scene {stacks[0].scene!r}, not {scene!r}")
    if not match:
        raise ValueError(f"{root}: no stack of scene {scene!r} (found: "
                         f"{', '.join(s.scene for s in stacks[:10]) or 'none'})")
    return match[0]
