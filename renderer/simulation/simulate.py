"""A stopping criterion run over stored stacks instead of rendering (offline evaluation).

The passes between a stack's levels come back exactly (`learning.inputs.halves.recover_passes`)
and feed the live loop's own `PassLoop`, one round a level, so the half buffers and the stops
are the live render's. The verdicts V [K, units] are -1 until the loop stopped the unit, +1
from there on, as `learning.evaluation.metrics.evaluate_verdicts` scores.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable
from dataclasses import replace
from typing import Any

import numpy as np
from tqdm import tqdm

from learning.data.dataset_dir import read_stacks
from learning.data.observer import observer_for
from learning.data.relabel import observed, read_observed, with_tile_truth
from learning.data.stack import Stack
from learning.data.tile_truth import FinalFrame
from learning.evaluation.generalisation import scene_groups
from learning.evaluation.metrics import evaluate_verdicts
from learning.inputs.halves import check_constant_step, recover_passes
from learning.names import DEFAULT_TAU

from ..criteria import Criterion, GatedCriterion, external_counters, make_criterion
from ..live.block_windows import BlockWindows
from ..live.budget import Budget
from ..live.passloop import PassLoop
from ..setting_kinds import MAX_SIDE
from ..settings import ROW
from ..spec import COMMAND_LINE, checked, resolve

logger = logging.getLogger(__name__)


def simulate_loop(stack: Stack, criterion: Criterion, min_spp: int | None = None,
                  progress: bool = False, tile: int | None = None,
                  decide_skip: float = ROW["decide_skip"].default,
                  decide_growth: float = ROW["decide_growth"].default) -> tuple[np.ndarray, PassLoop]:
    """Verdicts V int8 [K, n_units] the live loop would give on this stack, and the loop (its
    `ledger`). Units: the stack's blocks, or with `tile` their tiles, numbered as live.
    The settings are the rows', as their door checked them."""
    if criterion.needs_halves:
        check_constant_step(stack)
    tiling = BlockWindows(stack.width, stack.height, grid=tuple(stack.grid), tile=tile)
    units = tiling._unit_idx.numpy()
    V = np.full((stack.n_levels, tiling.n_units), -1, np.int8)
    quick = stack.split(stack.quick()) if criterion.needs_quick else None
    loop = PassLoop(criterion, (stack.n_blocks, tiling.tiles_per_block), tiling.tile_shape, stack.spp, min_spp,
                    quick, tiling=tiling, decide_skip=decide_skip, decide_growth=decide_growth)
    for k, _, pass_spp, pass_img in tqdm(recover_passes(stack), total=len(V), desc=f"{stack.scene} simulate",
                                         unit="lvl", disable=not progress, leave=False):
        ids = np.flatnonzero(loop.active)
        if not ids.size:
            V[k:] = 1
            break
        tiles = pass_img.reshape(-1, 3)[units[ids]].reshape(len(ids), tiling.tile_h, tiling.tile_w, 3)
        loop.run_round(ids, [(tiles, pass_spp)])   # stopped units get no more samples
        V[k, ~loop.active] = 1
    return V, loop


def simulate_stack(stack: Stack, criterion: Criterion, min_spp: int | None = None,
                   progress: bool = False) -> np.ndarray:
    """Verdicts V int8 [K, n_blocks] the live loop would produce on this stack (`simulate_loop`)."""
    return simulate_loop(stack, criterion, min_spp, progress)[0]


def simulate_budget(stack: Any, criterion: Any, spp_budget: float, min_spp: int | None = None) -> dict[str, Any]:
    """The budget render on a stored stack: block b's j-th pass is the stack's pass j, as the
    live render's keyed samples make it. Returns each block's final spp (its image: the
    stack's level there), whether it stopped, the budget's report part and the rounds run."""
    if criterion.needs_halves:
        check_constant_step(stack)
    passes, pass_spp = [], []
    for _, _, spp_j, pass_img in recover_passes(stack):
        passes.append(stack.split(pass_img))
        pass_spp.append(int(spp_j))
    quick = stack.split(stack.quick()) if criterion.needs_quick else None
    loop = PassLoop(criterion, tuple(stack.grid), tuple(stack.block), np.cumsum(pass_spp), min_spp, quick)
    budget = Budget(spp_budget)
    rounds = 0
    while True:
        ids = budget.select(loop)
        if not ids:
            break
        index = loop.acc.pass_counts()[ids]                 # each block's next pass
        images = np.stack([passes[p][b] for b, p in zip(ids, index.tolist())])
        loop.run_round(ids, [(images, loop.pass_spp[index])])
        rounds += 1
        if not loop.active.any() or budget.finished(loop):
            break
    return {"spp": loop.acc.spp_all().tolist(), "converged": (~loop.active).tolist(),
            "budget": budget.describe(loop), "rounds": rounds}


def _as_stacks(stacks: Stack | str | os.PathLike | Iterable[Stack | str | os.PathLike],
               tau: float = DEFAULT_TAU) -> list[Stack]:
    """Stacks as given (labelled as the caller wants), or read from directories and labelled
    by the observer at `tau`."""
    if isinstance(stacks, Stack):
        return [stacks]
    if isinstance(stacks, (str, os.PathLike)):
        return [observed(s, tau) for s in read_stacks(stacks)]
    return [st for s in stacks for st in _as_stacks(s, tau)]


def evaluate_criterion(stacks: Stack | str | os.PathLike | Iterable[Stack | str | os.PathLike],
                       criterion_factory: Callable[[Stack], Criterion], min_spp: int | None = None,
                       progress: bool = False, tau: float = DEFAULT_TAU, tile: int | None = None,
                       decide_skip: float = ROW["decide_skip"].default,
                       decide_growth: float = ROW["decide_growth"].default) -> dict[str, Any]:
    """DESIGN metrics of a criterion simulated on labelled stacks, overall and per scene.

    `stacks`: a dataset directory, a stack, or a list of either; `criterion_factory(stack)`:
    each stack's criterion. Returns `evaluate_verdicts`' dict plus ``end``, ``criterion`` (its
    description) and ``counters`` (summed). With `tile`, units are tiles scored against the tile
    truth, and ``blocks`` holds the metrics per block (stopped when all its tiles are).
    """
    todo = _as_stacks(stacks, tau)
    if not todo:
        raise ValueError(f"no stacks found in {stacks!r}")
    per_scene: dict[str, tuple] = {}
    per_block: dict[str, tuple] = {}
    end: dict[str, dict[str, float]] = {}
    counters: dict[str, float] = {}
    description: dict[str, Any] = {}
    for st in tqdm(todo, desc="stacks", unit="stack", disable=not progress):
        if st.thresholds is None:
            raise ValueError(f"{st.path}: stack has no thresholds; label it first")
        if st.scene in per_scene:
            raise ValueError(f"{st.path}: scene {st.scene!r} appears twice")
        if tile is not None:
            st = with_tile_truth(st, tile)
        crit = criterion_factory(st)
        V, loop = simulate_loop(st, crit, min_spp=min_spp, progress=progress, tile=tile, decide_skip=decide_skip,
                                decide_growth=decide_growth)
        if tile is None:
            per_scene[st.scene] = (V, st.labels(), st.thresholds, st.spp)
        else:
            per_scene[st.scene] = (V, st.tile_labels(), st.tile_thresholds, st.spp)
            blocks = V.reshape(len(V), st.n_blocks, -1).min(axis=2)          # +1 once every tile is
            per_block[st.scene] = (blocks, st.labels(), st.thresholds, st.spp)
        end[st.scene] = end_of_render(st, V, tile, tau)
        for k, v in {**loop.ledger.counters, **loop.ledger.timers}.items():
            counters[k] = counters.get(k, 0) + v
        description = crit.describe()
        if description.get("name") == "oracle":
            description = {"name": "oracle"}
    per_unit = None if tile is None else {s: len(v[2]) // len(per_block[s][2]) for s, v in per_scene.items()}
    out = evaluate_verdicts(per_scene, scene_groups(todo), per_unit)
    if tile is not None:
        out["tile"] = int(tile)
        out["blocks"] = evaluate_verdicts(per_block, scene_groups(todo))
        _against_block_oracle(out)
    out["end"] = {"per_scene": end, "above_tau": sum(e["above_tau"] for e in end.values()),
                  "blocks": sum(e["blocks"] for e in end.values())}
    out["criterion"] = description
    out["counters"] = external_counters(counters)
    return out


def end_of_render(stack: Stack, verdicts: np.ndarray, tile: int | None, tau: float) -> dict[str, float]:
    """The block observer's verdict on the frame the simulated render ends with: each unit at
    the level it stopped at (the last if never), judged per block (`FinalFrame`), so a tile
    that stopped early shows in its block whatever the tile truth says."""
    return FinalFrame(stack, tile, observer_for(stack, tau)).judge(verdicts)


def _against_block_oracle(out: dict[str, Any]) -> None:
    """Add to a tile-grain evaluation, per scene and overall, the samples spent and the tile
    oracle's as ratios to the block oracle's: what deciding per tile saves."""
    totals = {"spent": 0.0, "tile_oracle": 0.0, "block_oracle": 0.0}
    for scene, entry in out["per_scene"].items():
        t, b = entry["counts"], out["blocks"]["per_scene"][scene]["counts"]
        per_block = t["blocks"] / b["blocks"]                  # tiles a block
        mine = {"spent": t["spent"] / per_block, "tile_oracle": t["oracle"] / per_block,
                "block_oracle": float(b["oracle"])}
        for k in totals:
            totals[k] += mine[k]
        out["blocks"]["per_scene"][scene].update(_ratios(mine))
    out["blocks"].update(_ratios(totals))


def _ratios(c: dict[str, float]) -> dict[str, float]:
    div = c["block_oracle"] or float("nan")
    return {"spp_ratio_vs_block_oracle": c["spent"] / div, "tile_oracle_vs_block_oracle": c["tile_oracle"] / div}


def criterion_factory(kind: str, *, model: str | None = None, server: str | None = None,
                      threshold: float | None = None, offset: float | None = None,
                      exposure: float | None = None, tau: float | None = None,
                      tile: int | None = None) -> Callable[[Stack], Criterion]:
    """Each stack's criterion for `evaluate_criterion`, from command-line style options (None:
    not given) resolved by the render spec: one per block size (a `tile` as large as the
    block is block grain, as live), or the oracle with each stack's (tiles') thresholds."""
    spec = resolve({"criterion": kind, "model": model, "server": server, "threshold": threshold,
                    "offset": offset, "exposure": exposure, "tau": tau,
                    "tile": MAX_SIDE if tile is None else tile},    # None: whole blocks
                   source=COMMAND_LINE, thresholds_known=True)
    if spec.criterion == "oracle":
        def oracle(st: Stack) -> Criterion:
            truth = st.thresholds if tile is None else st.tile_thresholds     # one per unit
            if truth is None:
                raise ValueError(f"{st.path}: stack has no thresholds; the oracle needs them")
            return make_criterion(spec, truth)
        return oracle
    first = make_criterion(spec)           # a model is loaded now: a bad one fails before any stack is read
    built: dict[bool, Criterion] = {spec.tile_grain() is None: first}

    def per_block(st: Stack) -> Criterion:
        fitted = replace(spec, block=max(int(b) for b in st.block), grid=None)
        whole = fitted.tile_grain() is None
        if whole not in built:
            built[whole] = first.gate if whole and isinstance(first, GatedCriterion) else make_criterion(fitted)
        return built[whole]
    return per_block


def evaluate_criterion_cli(data: str | os.PathLike, criterion: str, scenes: list[str] | None = None, *,
                           min_spp: int | None = None, threshold: float | None = None,
                           offset: float | None = None, model: str | None = None,
                           server: str | None = None, progress: bool = True,
                           tau: float = DEFAULT_TAU, tile: int | None = None,
                           decide_skip: float = ROW["decide_skip"].default,
                           decide_growth: float = ROW["decide_growth"].default) -> dict[str, Any]:
    """`noisestop evaluate --criterion C`: C simulated on the stacks of `data` (only `scenes`
    if given) labelled at `tau`; the DESIGN metrics. The simulation's door: its settings are
    checked here, by their rows, before any stack is read."""
    checked({"min_spp": min_spp, "decide_skip": decide_skip, "decide_growth": decide_growth})
    factory = criterion_factory(criterion, model=model, server=server, threshold=threshold, offset=offset,
                                tau=tau, tile=tile)   # a knob out of range fails before any stack is read
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
    out = evaluate_criterion(stacks, factory, min_spp=min_spp, progress=progress, tau=tau, tile=tile,
                             decide_skip=decide_skip, decide_growth=decide_growth)
    return {**out, "tau": float(tau)}
