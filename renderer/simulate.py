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
from .spec import ROW

logger = logging.getLogger(__name__)


def simulate_loop(stack: Stack, criterion: Criterion, min_spp: int | None = None,
                  progress: bool = False) -> tuple[np.ndarray, PassLoop]:
    """Verdicts V int8 [K, n_blocks] the live loop would produce on this stack, and the
    loop (its decision counters and timers).

    `min_spp` (None: no minimum; else checked by the render spec's row): no decision
    before that many samples.
    """
    if min_spp is not None:
        ROW["min_spp"].check(min_spp)
    if criterion.needs_halves:
        check_constant_step(stack)
    K = stack.n_levels
    V = np.full((K, stack.n_blocks), -1, np.int8)
    quick = stack.split(stack.quick()) if criterion.needs_quick else None
    loop = PassLoop(criterion, tuple(stack.grid), tuple(stack.block), stack.spp, min_spp, quick)
    bar = tqdm(total=K, desc=f"{stack.scene} simulate", unit="lvl", disable=not progress, leave=False)
    for k, _, pass_spp, pass_img in recover_passes(stack):
        bar.update(1)
        ids = np.flatnonzero(loop.active)
        if not ids.size:
            V[k:] = 1
            break
        loop.step(ids, [(stack.split(pass_img)[ids], pass_spp)])   # stopped blocks get no more samples
        V[k, ~loop.active] = 1
    bar.close()
    return V, loop


def simulate_stack(stack: Stack, criterion: Criterion, min_spp: int | None = None,
                   progress: bool = False) -> np.ndarray:
    """Verdicts V int8 [K, n_blocks] the live loop would produce on this stack (`simulate_loop`)."""
    return simulate_loop(stack, criterion, min_spp, progress)[0]


def simulate_budget(stack: Any, criterion: Any, spp_budget: float, min_spp: int | None = None,
                    band: float | None = None) -> dict[str, Any]:
    """The budget render on a stored stack: block b's j-th pass is the stack's pass j
    (`learning.inputs.halves.recover_passes`), as the live render's keyed samples make it,
    so the loop (`Budget.select`, `PassLoop.step`) sees what it would see live.
    `spp_budget` is checked by the render spec's row.

    Returns each block's final spp, whether it stopped, the budget's report part and the
    rounds run. The final image of block b is the stack's level at its spp.
    """
    from .budget import BAND, Budget

    ROW["spp_budget"].check(spp_budget)
    if criterion.needs_halves:
        check_constant_step(stack)
    passes, pass_spp = [], []
    for _, _, spp_j, pass_img in recover_passes(stack):
        passes.append(stack.split(pass_img))
        pass_spp.append(int(spp_j))
    quick = stack.split(stack.quick()) if criterion.needs_quick else None
    loop = PassLoop(criterion, tuple(stack.grid), tuple(stack.block), np.cumsum(pass_spp), min_spp, quick)
    budget = Budget(spp_budget, band=BAND if band is None else band)
    rounds = 0
    while True:
        ids = budget.select(loop)
        if not ids:
            break
        own = loop.acc.passes_all()[ids]
        loop.step(ids, [(np.stack([passes[p][b] for b, p in zip(ids, own.tolist())]), loop.pass_spp[own])])
        rounds += 1
        if not loop.active.any() or budget.finished(loop):
            break
    return {"spp": loop.acc.spp_all().tolist(), "converged": (~loop.active).tolist(),
            "budget": budget.describe(loop), "rounds": rounds}


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
    returns the criterion for each stack (the oracle needs that stack's thresholds; the
    others are configuration only, one object for every stack).
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
        V, loop = simulate_loop(st, crit, min_spp=min_spp, progress=progress)
        per_scene[st.scene] = (V, st.labels(), st.thresholds, st.spp)
        for k, v in {**loop.counters, **loop.timers}.items():
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
                      exposure: float | None = None, tau: float | None = None) -> Callable[[Stack], Criterion]:
    """The criterion of each stack for `evaluate_criterion`, from command-line style options
    (None: not given), resolved and checked by the render spec and built by the one
    factory (`renderer.criteria.make_criterion`): one criterion for every stack, or the
    oracle with each stack's own thresholds."""
    from .criteria import make_criterion
    from .spec import COMMAND_LINE, resolve

    spec = resolve({"criterion": kind, "model": model, "server": server, "threshold": threshold,
                    "offset": offset, "exposure": exposure, "tau": tau}, source=COMMAND_LINE,
                   thresholds_known=True)
    if spec.criterion == "oracle":
        def oracle(st: Stack) -> Criterion:
            if st.thresholds is None:
                raise ValueError(f"{st.path}: stack has no thresholds; the oracle needs them")
            return make_criterion(spec, st.thresholds)
        return oracle
    crit = make_criterion(spec)
    return lambda st: crit


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


def find_stack(reference: Stack | str | os.PathLike, scene: str) -> Stack:
    """The stack of `scene` in a dataset directory (or that stack itself), not yet labelled."""
    if isinstance(reference, Stack):
        return reference
    root = Path(reference)
    stacks = [read_stack(p) for p in list_stacks(root)]
    match = [s for s in stacks if s.scene == scene]
    if len(stacks) == 1 and not match:
        raise ValueError(f"{root}: the stack there is scene {stacks[0].scene!r}, not {scene!r}")
    if not match:
        raise ValueError(f"{root}: no stack of scene {scene!r} (found: "
                         f"{', '.join(s.scene for s in stacks[:10]) or 'none'})")
    return match[0]


def find_reference(reference: Stack | str | os.PathLike, scene: str, tau: float = DEFAULT_TAU) -> Stack:
    """The stack of `scene` in a dataset directory (or that stack itself), labelled by the
    observer at `tau`."""
    return observed(find_stack(reference, scene), tau)
