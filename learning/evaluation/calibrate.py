"""Choosing a criterion's knob (the model's decision offset, flip's c) on training scenes.

A block stops at its first decided level whose score exceeds the offset (the one stop
rule, `learning.stoprule`), so raising the offset trades samples for fewer early stops.
The offset is calibrated without touching held-out scenes: each training scene is scored
by a model trained on the other training scenes (leave one scene out), the stop rule
turns those out-of-fold scores into stops exactly as the render loop would, and the
offset is chosen so that its early-stop rate meets the target on scenes it was not
chosen on (`choose_out_of_fold`); flip's c is chosen the same way.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from noisefeat.dots import OBSERVER_DOTS
from noisefeat.pooling import CRITERION_POOLING, DEFAULT_POOLING

from ..data.observer import label_tau, observer_for
from ..data.relabel import observed, with_tile_truth
from ..data.stack import Stack
from ..data.tile_truth import TILE_TRUTH, FinalFrame
from ..inputs.halves import flip_offset, guarded_flip_scores, guarded_tile_flip_scores
from ..inputs.halves import stack_flat
from ..inputs.history import STATISTIC
from ..inputs.table import SubImageTable
from ..names import DEFAULT_TAU
from ..stoprule import StopRule
from .evaluate import evaluate_scores
from .generalisation import scene_groups
from .metrics import add_end_counts, evaluate_verdicts, metrics_from_counts, pool_counts

log = logging.getLogger(__name__)

DEFAULT_OFFSETS = tuple(np.round(np.arange(-1.0, 6.01, 0.1), 2))
#: the noise targets flip's c(tau) and a model's offsets are calibrated at (DESIGN: at least
#: [0.01, 0.05])
CURVE_TAUS = (0.01, 0.0125, 0.015, 0.0175, 0.02, 0.025, 0.03, 0.035, 0.04, 0.045, 0.05)


def score_offsets(scores: np.ndarray, steps: int = 201) -> tuple[float, ...]:
    """Offsets to try: `DEFAULT_OFFSETS` and the quantiles of the finite out-of-fold
    `scores` (and 0, the hyperplane itself). A score's range depends on the model and the
    run, and a stricter or looser noise target moves the offset it needs beyond any fixed
    grid; the largest quantile never stops a block, the smallest stops every one."""
    s = scores[np.isfinite(scores)]
    q = np.quantile(s, np.linspace(0.0, 1.0, steps)) if len(s) else np.zeros(0)
    return tuple(np.unique(np.round(np.concatenate([q, DEFAULT_OFFSETS, [0.0]]), 3)).tolist())


def _record(chosen: dict) -> dict:
    return {k: v for k, v in chosen.items() if k not in ("per_scene", "groups")}


#: scenes are scored in at most this many folds: leave-one-scene-out up to that many
#: scenes, then groups of scenes (a hundred procedural scenes would cost a hundred fits)
CALIBRATION_FOLDS = 10


def scene_folds(scenes: Sequence[str], folds: int | None = CALIBRATION_FOLDS, seed: int = 0) -> list[list[str]]:
    """Scenes in folds: one per scene up to `folds` scenes (None: always), else `folds`
    seeded groups of near-equal size."""
    scenes = sorted(scenes)
    if folds is None or len(scenes) <= folds:
        return [[s] for s in scenes]
    order = np.random.default_rng(seed).permutation(len(scenes))
    return [sorted(scenes[i] for i in order[f::folds]) for f in range(folds)]


def out_of_fold_scores(fit: Callable[[SubImageTable], Any], table: SubImageTable,
                       scenes: Sequence[str], progress: bool = False,
                       folds: int | None = CALIBRATION_FOLDS) -> np.ndarray:
    """f(x) for every row of `scenes`, each scene scored by a model fit without it (nor
    the other scenes of its fold, `scene_folds`)."""
    scores = np.full(len(table), np.nan)
    groups = scene_folds(scenes, folds)
    for held in tqdm(groups, desc="out-of-fold scores", disable=not progress, leave=False):
        rest = [t for t in scenes if t not in held]
        model = fit(table.subset(table.scene_mask(rest)))
        m = table.scene_mask(held)
        scores[m] = model.decision_function(table.X[m])
    return scores


def sweep(scores: np.ndarray, table: SubImageTable, offsets: Sequence[float] = DEFAULT_OFFSETS,
          min_spp: int | None = None) -> list[dict]:
    """Metrics at each offset through the stop rule, for the scenes of `table` that have
    finite scores (overall, `per_scene` and `groups`)."""
    scored = sorted({str(s) for s in table.scene[np.isfinite(scores)]})
    mask = table.scene_mask(scored)
    sub = table.subset(mask)
    return [{"offset": float(off), **evaluate_scores(sub, scores[mask], StopRule(float(off), min_spp))}
            for off in offsets]


def _pick(curve: list[dict], max_early_stop: float, key: str, larger_is_safer: bool,
          rate: str = "early_stop_rate") -> dict | None:
    ok = [r for r in curve if r[rate] <= max_early_stop + 1e-12]
    if not ok:
        return None
    return min(ok, key=lambda r: r[key]) if larger_is_safer else max(ok, key=lambda r: r[key])


def choose_out_of_fold(curve: list[dict], max_early_stop: float = 0.05, *, key: str = "threshold",
                       larger_is_safer: bool = True, step: float = 0.0025, rate: str = "early_stop_rate") -> dict:
    """A setting whose early-stop rate on scenes it was *not* chosen on meets the target.

    Picking the least safe setting that meets the target on the training scenes lands on
    the edge, so on a new scene it exceeds the target about half the time. This estimates
    how the choice generalises: each training scene in turn is left out, the setting is
    chosen on the others, and the left-out scene is scored at that setting; the pooled
    out-of-fold early-stop rate is the procedure's. The internal target is lowered (by
    `step`) until that out-of-fold rate meets `max_early_stop`, and the setting is then
    chosen on every training scene at the internal target.

    `curve` rows need `key` and `per_scene` with `counts` (`learning.evaluation.metrics`);
    `rate` names the early rate the target is on (early stops; at tile grain the final
    frame's early blocks, ``end_early_rate``). Returns the chosen row plus
    ``internal_target`` and ``out_of_fold`` (pooled metrics).
    """
    scenes = sorted(curve[0]["per_scene"])

    def pooled(subset: list[str]) -> list[dict]:
        return [{key: r[key], **metrics_from_counts(pool_counts(r["per_scene"][s]["counts"] for s in subset))}
                for r in curve]

    def safest(rows: list[dict]) -> dict:
        return min(rows, key=lambda r: (r[rate], r["spp_ratio_vs_oracle"]))

    def pick(rows: list[dict], t: float) -> dict:
        return _pick(rows, t, key, larger_is_safer, rate) or safest(rows)

    by_setting = {r[key]: r for r in curve}
    folds = {s: pooled([x for x in scenes if x != s]) for s in scenes} if len(scenes) > 1 else {}
    t, oof = max_early_stop, None
    while folds:
        counts = [by_setting[pick(rows, t)[key]]["per_scene"][s]["counts"] for s, rows in folds.items()]
        oof = metrics_from_counts(pool_counts(counts))
        if oof[rate] <= max_early_stop + 1e-12 or t <= 0:
            break
        t = max(0.0, round(t - step, 6))
    chosen = by_setting[pick(pooled(scenes), t)[key]]
    if chosen[rate] > max_early_stop + 1e-12:
        log.warning("no %s reaches %s <= %.3f on the training scenes; the safest (%.3f at %g) "
                    "is used", key, rate, max_early_stop, chosen[rate], chosen[key])
    return {**chosen, "internal_target": t, "out_of_fold": oof}


def choose_offset(curve: list[dict], max_early_stop: float = 0.05) -> dict:
    """The offset for `max_early_stop`, chosen out of fold over the training scenes
    (`choose_out_of_fold`)."""
    return choose_out_of_fold(curve, max_early_stop, key="offset", larger_is_safer=True)



def calibrate_offset(fit: Callable[[SubImageTable], Any], table: SubImageTable, scenes: Sequence[str],
                     max_early_stop: float, offsets: Callable[[np.ndarray], Sequence[float]] | None = None,
                     progress: bool = True, taus: Sequence[float] = CURVE_TAUS) -> tuple[float, dict[str, Any]]:
    """A model's offset from out-of-fold scores of the training `scenes` (`fit` trains on a
    sub-table), and the calibration record a bundle keeps; `offsets(scores)` gives the
    offsets tried (default `score_offsets`).

    The same out-of-fold scores, judged against the observer's labels at each noise target
    in `taus`, give the record's `offsets_by_tau` (`learning.models.noise_target`): a
    stricter target never gets a smaller offset (running maximum from the largest tau
    down, as for flip's c(tau))."""
    t0 = time.perf_counter()
    scores = out_of_fold_scores(fit, table, list(scenes), progress=progress)
    tried = (offsets or score_offsets)(scores)
    curve = sweep(scores, table, tried)
    chosen = choose_offset(curve, max_early_stop)
    by_tau = []
    for tau in sorted(taus, reverse=True):
        pick = choose_offset(sweep(scores, table.relabelled(tau), tried), max_early_stop)
        safest = max([pick["offset"], *(r["offset"] for r in by_tau)])
        by_tau.append({"tau": float(tau), "offset": float(safest), "offset_raw": float(pick["offset"]),
                       "early_stop_rate": pick["early_stop_rate"],
                       "spp_ratio_vs_oracle": pick["spp_ratio_vs_oracle"]})
    # the bundle's own offset is the curve's at the labels' tau, so `offset` and `offset_at(tau)`
    # never disagree: the running maximum can raise it (the dot guard is tau's own, so a looser
    # target may need a larger offset than a stricter one)
    at_label = [r for r in by_tau if abs(r["tau"] - label_tau(next(iter(table.stacks.values())))) < 1e-12]
    if at_label and at_label[0]["offset"] != chosen["offset"]:
        row = next(r for r in curve if r["offset"] == at_label[0]["offset"])
        chosen = {**row, "internal_target": chosen.get("internal_target"), "out_of_fold": chosen.get("out_of_fold"),
                  "raised_from": float(chosen["offset"])}
    return float(chosen["offset"]), {
        "target_early_stop_rate": max_early_stop, "route": "stop rule",
        "chosen": _record(chosen),
        "per_scene": {sc: {k: v for k, v in m.items() if k != "counts"} for sc, m in chosen["per_scene"].items()},
        "curve": [_record(r) for r in curve],
        "offsets_by_tau": sorted(by_tau, key=lambda r: r["tau"]),
        "seconds": time.perf_counter() - t0}

#: c tried: a geometric grid (1.5 % apart: about 4 % in samples, since a block's half-buffer
#: FLIP falls about as spp^-0.36) wide enough for tile pooling at any tau of the curve
FLIP_CANDIDATES = tuple(float(f"{c:.5g}") for c in np.geomspace(0.004, 0.4, 311))


def flip_sweep(stacks: Sequence[Stack], candidates: Sequence[float] = FLIP_CANDIDATES, *,
               min_spp: int | None = None, progress: bool = False,
               pooling: str = CRITERION_POOLING, tile: int | None = None,
               estimates: Mapping[str, np.ndarray] | None = None) -> list[dict[str, Any]]:
    """Metrics of the flip criterion at each c (overall, per scene, per group), through the
    one stop rule (min spp, held stops, flat units at once), on labelled `stacks`: per
    block, or with `tile` per tile against the tile truth. `estimates` (scene
    -> [K, n_tiles], with `tile`): a learned error estimate compared with c in place of the
    halves' history (the `estimate` criterion), out of fold, with flip's dot guard."""
    if not stacks:
        raise ValueError("no stacks to sweep c on")
    unlabelled = [str(s.path) for s in stacks if s.thresholds is None]
    if unlabelled:
        raise ValueError(f"stacks without thresholds cannot be scored: {', '.join(unlabelled[:3])}")
    if tile is None:
        scores = {s.scene: guarded_flip_scores(s, progress=progress, pooling=pooling) for s in stacks}
        flats = {s.scene: stack_flat(s) for s in stacks}
        truth = {s.scene: (s.labels(), s.thresholds) for s in stacks}
    else:
        stacks = [with_tile_truth(s, tile) for s in stacks]
        both = {s.scene: guarded_tile_flip_scores(s, tile, progress=progress, estimate=None if estimates is None
                                                  else estimates[s.scene]) for s in stacks}
        scores, flats = {k: v[0] for k, v in both.items()}, {k: v[1] for k, v in both.items()}
        truth = {s.scene: (s.tile_labels(), s.tile_thresholds) for s in stacks}
    per_block = None if tile is None else {s.scene: len(s.tile_thresholds) // s.n_blocks for s in stacks}
    frames = {} if tile is None else {s.scene: FinalFrame(s, tile, observer_for(s)) for s in stacks}
    groups = scene_groups(stacks)
    curve = []
    for c in tqdm(sorted(candidates), desc="c", disable=not progress or tile is None, leave=False):
        rule = StopRule(flip_offset(c), min_spp)
        per = {s.scene: (rule.stops(scores[s.scene], s.spp, flats[s.scene]), *truth[s.scene], s.spp)
               for s in stacks}
        result = evaluate_verdicts(per, groups, per_block)
        if frames:       # at tile grain, what each final frame shows (`add_end_counts`)
            add_end_counts(result, {k: f.judge(per[k][0]) for k, f in frames.items()})
        curve.append({"threshold": float(c), **result})
    return curve


def calibrate_flip(stacks: Sequence[Stack], max_early_stop: float = 0.05, *, min_spp: int | None = None,
                   candidates: Sequence[float] = FLIP_CANDIDATES, progress: bool = True,
                   pooling: str = CRITERION_POOLING, tile: int | None = None,
                   estimates: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """c for the `flip` criterion on labelled `stacks` (training scenes, never the held-out
    ones): the largest c (fewest samples) whose early-stop rate stays within
    `max_early_stop` on scenes it was not chosen on (`choose_out_of_fold`); per block, or
    per tile of `tile` pixels, where the rate is the final frame's: of the blocks whose
    truth converges, those the frame the render ends with leaves above tau."""
    curve = flip_sweep(stacks, candidates, min_spp=min_spp, progress=progress, pooling=pooling, tile=tile,
                       estimates=estimates)
    chosen = choose_out_of_fold(curve, max_early_stop, larger_is_safer=False,
                                rate="early_stop_rate" if tile is None else "end_early_rate")
    return {"c": chosen["threshold"], "target_early_stop_rate": max_early_stop, "chosen": _record(chosen),
            "per_scene": {s: {k: v for k, v in m.items() if k != "counts"} for s, m in chosen["per_scene"].items()},
            "curve": [_record(r) for r in curve],
            "scenes": sorted(s.scene for s in stacks), "min_spp": min_spp}


def calibrate_flip_curve(stacks: Sequence[Stack], max_early_stop: float = 0.05, *,
                         taus: Sequence[float] = CURVE_TAUS, min_spp: int | None = None,
                         candidates: Sequence[float] | Callable[[float], Sequence[float]] = FLIP_CANDIDATES,
                         progress: bool = True,
                         pooling: str = CRITERION_POOLING, tile: int | None = None,
                         estimates: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The curve c(tau) for the `flip` criterion: at each noise target tau, the stacks are
    labelled by the observer at that tau (`observed`: relabelled from cached errors, never
    re-rendered) and c is chosen out of fold for `max_early_stop` (`calibrate_flip`).

    A stricter target never gets a larger c: a c that is safe against the labels of a tau
    is safe against those of any larger tau (every threshold can only come earlier), so
    where the chosen c's dip with tau the curve keeps the running maximum, which meets the
    target at both. `c_raw` records what was chosen before that. `candidates`: the c tried,
    or a function of tau giving them (an estimate of the error itself has its c near tau)."""
    points, raw = [], []
    for tau in tqdm(sorted(taus), desc="c(tau)", disable=not progress, leave=False):
        labelled = [observed(s, tau) for s in stacks]          # DESIGN's observer at this tau
        cal = calibrate_flip(labelled, max_early_stop, min_spp=min_spp,
                             candidates=candidates(tau) if callable(candidates) else candidates,
                             progress=False, pooling=pooling, tile=tile, estimates=estimates)
        raw.append(cal["c"])
        points.append({"tau": float(tau), "c": max(raw), "c_raw": cal["c"], "chosen": cal["chosen"],
                       "internal_target": cal["chosen"].get("internal_target"),
                       "per_scene": cal["per_scene"] if abs(tau - DEFAULT_TAU) < 1e-12 else None})
    at_default = [p for p in points if abs(p["tau"] - DEFAULT_TAU) < 1e-12]
    return {"format": "noisestop-flip-curve", "pooling": pooling, "observer_pooling": DEFAULT_POOLING,
            "unit": "block" if tile is None else f"tile{tile}",
            **({} if tile is None else {"statistic": STATISTIC, "tile_truth": TILE_TRUTH, "rate": "end_early_rate"}),
            "observer_dots": OBSERVER_DOTS,
            "target_early_stop_rate": max_early_stop,
            "curve": [{k: v for k, v in p.items() if v is not None} for p in points],
            "c": at_default[0]["c"] if at_default else None,
            "scenes": sorted(s.scene for s in stacks), "min_spp": min_spp}
