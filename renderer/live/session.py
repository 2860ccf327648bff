"""One adaptive render in progress: its renderer, loop, budget, ledger, checkpoint and report.

`renderer.live.adaptive.run_adaptive` prepares the render (`renderer.live.plan.prepare`: the
spec resolved, the renderer and the criterion built), opens a `RenderSession`, calls
`advance` until the session is done, and asks it for the result. The words (unit, pass,
round, launch) and a round are explained once, in `renderer.live.passloop`; `advance` plans one
launch (`plan`: the units and the passes each gets), queues it
(`BlockRenderer.submit_passes`), waits for its images and hands each pass to
`PassLoop.run_round`.

The session owns the render's `renderer.live.ledger.Ledger` (its counters and timers): it hands
it to the renderer, the loop and the budget, which report into it. It also keeps what
survives a crash: `snapshot` is the state the checkpoint holds (`renderer.live.checkpoint`),
`checkpoint` writes it, and `counts` is what every attempt cost in Mitsuba.
`renderer.live.report.render_result` turns a finished session into the result.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learning.inputs.history import last_decided_spp
from noisefeat.runtime import torch_threads
from noisefeat.safeio import present

from ..criteria import COUNTER_NAMES, TIMER_NAMES, UnitBatch, Criterion
from ..spec import RenderSpec
from .blocks import BlockRenderer
from .budget import Budget
from .checkpoint import load_checkpoint, save_checkpoint
from .launches import LAUNCH_LANES, NEAR, ahead_passes, grown_passes
from .ledger import RENDER_COUNTERS, RENDER_TIMERS, Ledger
from .passloop import PassLoop, next_decision, schedule
from .wavefront import Traced

logger = logging.getLogger(__name__)


def run_settings(spec: RenderSpec, br: BlockRenderer, crit: Criterion, variant: str, scene: str) -> dict[str, Any]:
    """What a resume must match and the report repeats: the spec as rendered (the frame's
    blocks, the criterion as built, the variant)."""
    gh, gw = br.grid
    return {"scene": scene, "resolution": [br.width, br.height], "grid": [gh, gw], "block": [br.block_h, br.block_w],
            "tile": [br.tile_h, br.tile_w],
            "exposure": float(spec.exposure), "step": int(spec.step), "min_spp": int(spec.min_spp),
            "max_spp": int(spec.max_spp), "decide_skip": float(spec.decide_skip),
            "decide_growth": float(spec.decide_growth), "seed": int(spec.seed), "quick_spp": int(spec.quick_spp),
            "quick": crit.quick_kind if crit.needs_quick else "none", "criterion": crit.describe(),
            "variant": variant, "defines": dict(spec.defines or {}), "tau": float(spec.tau),
            **({} if spec.spp_budget is None else {"spp_budget": float(spec.spp_budget)})}


#: how far a resumed checkpoint's mean radiance may lie from its first pass traced again
RADIANCE_RATIO = 1e6


def check_radiance(path: Path, acc: Any, br: BlockRenderer, first_spp: int, seed: int) -> None:
    """ValueError unless a checkpoint's radiance is what its scene renders: a forged file
    whose sums were scaled (x1e30: every unit then "converged") passes every check the file
    alone allows, its digest recomputed. The first pass depends only on (seed, pixel, pass),
    so it is traced again over the frame (`render_full`: one pass, not added to the image;
    its Mitsuba call is counted) and the mean radiance held must be within a factor
    RADIANCE_RATIO of its mean: both estimate the frame's mean, so a true checkpoint is
    within noise of it. A black first pass proves nothing (light found later) and is not
    held against the file."""
    units = np.flatnonzero(acc.pass_counts() > 0)
    if not units.size:
        return
    again = np.nan_to_num(br.render_full(int(first_spp), seed, 0).astype(np.float64), nan=0.0, posinf=0.0,
                          neginf=0.0)
    traced = float(np.abs(again).mean())
    held = float(acc.means(units).abs().mean().cpu())
    if traced > 0 and not traced / RADIANCE_RATIO <= held <= traced * RADIANCE_RATIO:
        raise ValueError(f"{path}: inconsistent checkpoint: its mean radiance is {held / traced:.3g} times what "
                         "its first pass traces again (forged or damaged); delete it (or rerun without "
                         "--resume) to start over")


#: how far a unit's mean noise estimate may lie from its halves' estimate now
EVIDENCE_RATIO = 1e3
#: how far a unit's next decision may lie past the one its ratio now asks for
NEXT_RATIO = 1e3


def _refuse(path: Path, what: str) -> None:
    """The one-line refusal of a checkpoint whose decision state its halves contradict."""
    raise ValueError(f"{path}: inconsistent checkpoint: {what} (forged or damaged); delete it (or rerun "
                     "without --resume) to start over")


def check_evidence(path: Path, loop: PassLoop) -> None:
    """ValueError unless a resumed loop's decision evidence and next decisions agree with
    the half buffers its checkpoint holds. Neither can be recomputed from the file: the
    scores they came from were taken on halves at spp long past, so a forged file (sums
    zeroed or 1e300, every next decision at the latest the format allows, digest
    recomputed) silently stopped units early or ran them to max spp. Every decision of a
    unit estimated one per-unit constant (noise falls as 1/sqrt(spp)), so the criterion
    is asked once more on the units as they stand, keeping nothing (no verdict, evidence,
    counter or timer: the resumed render counts as the uninterrupted one), and the file is
    refused where a unit judged at the spp it holds held less evidence than that very
    decision added (same state, same estimate: half of it, for a tile's context), where its mean estimate lies more than
    EVIDENCE_RATIO from its halves' now or is 0 while they give more (honest ones: within
    a factor 3 on cornell), or where its next decision lies more than NEXT_RATIO past the
    one its ratio now asks for. Only active units that were judged are asked."""
    decided = loop.evidence.last
    ids = np.flatnonzero(loop.active & (decided > 0))
    if not ids.size or not loop.criterion.noise_ratio:
        return
    d = loop.criterion.decide(ids, UnitBatch.from_accumulator(loop.acc, ids, loop.quick, loop.tiling,
                                                               loop.evidence))
    spp = loop.acc.spp_all()[ids]
    ratio = np.asarray(d.ratio, np.float64)
    if loop.decide_skip > 0 or loop.decide_growth > 0:
        known = np.isfinite(ratio)
        asked = next_decision(spp[known], ratio[known], loop.decide_skip, loop.decide_growth)
        late = loop.next_spp[ids[known]] > NEXT_RATIO * np.maximum(asked, spp[known] + 1)
        if late.any():
            _refuse(path, f"unit {int(ids[known][late][0])}'s next decision is far past what its noise asks for")
    if d.evidence is None:
        return
    x = np.asarray(d.evidence, np.float64)
    total, weight = loop.evidence.sums[ids, 0], loop.evidence.sums[ids, 1]
    fresh = np.isfinite(x)
    # judged at the spp it holds: that decision added (spp - the one before) x (the same up
    # to a tile's context, hence half of it)
    here = fresh & (spp == decided[ids])
    if here.any():
        before = _decided_before(loop, ids[here])
        w = (spp[here] - before).astype(np.float64)
        short = (weight[here] < w) | (total[here] < 0.5 * w * x[here])
        if short.any():
            _refuse(path, f"unit {int(ids[here][short][0])} holds less evidence than its last decision added")
    held = fresh & (weight > 0) & (x > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(held, total / np.where(weight > 0, weight, 1.0), np.nan)
        off = held & ~((mean >= x / EVIDENCE_RATIO) & (mean <= x * EVIDENCE_RATIO))
    if off.any():
        _refuse(path, f"unit {int(ids[off][0])}'s decision evidence is {mean[off][0]:.3g} per sample, its "
                      f"half buffers give {x[off][0]:.3g}")


def _decided_before(loop: PassLoop, ids: np.ndarray) -> np.ndarray:
    """int64 [k]: the spp of each unit's decision before its last one (0: none), from the
    verdict history."""
    asked = loop.history[:, ids] != 0
    if asked.any():                    # each unit's last decision left out, the last before it remains
        asked[len(asked) - 1 - np.argmax(asked[::-1], axis=0), np.arange(len(ids))] = False
    return last_decided_spp(asked, loop.history_unit_spp[:, ids])


class RenderSession:
    """The state of one render between its set-up and its result (see the module docstring).

    `state` is what a checkpoint restores, under the checkpoint's names ("pass_index": the
    history rows so far, `rows`; done, counters, timers, quick image, a budget's state; the
    loop's arrays come from `loop.state()`); `settings` (`run_settings`) are what a resume
    must match; `ledger` holds the render's counters and timers.
    """

    def __init__(self, br: BlockRenderer, crit: Criterion, spec: RenderSpec, settings: dict[str, Any], *,
                 label: str, ckpt_path: Path | None, resume: bool, grow: bool, t_start: float) -> None:
        self.br, self.crit, self.spec, self.settings = br, crit, spec, settings
        self.label, self.ckpt_path, self.grow, self.t_start = label, ckpt_path, grow, t_start
        self.ledger = Ledger(COUNTER_NAMES + RENDER_COUNTERS, TIMER_NAMES + RENDER_TIMERS)
        br.ledger = self.ledger                       # the renderer's Mitsuba calls, from now on
        sched = schedule(spec.step, spec.max_spp)
        self.state = self._initial_state(resume, np.diff(sched, prepend=0).tolist())
        self.budget = Budget.for_spec(spec, self.ledger, resumed=self.state.get("budget") is not None)
        self.ledger.time("setup_s", time.perf_counter() - t_start)  # imports, scene load, checkpoint read
        quick_blocks = None
        if crit.needs_quick:
            if self.state["quick"] is None:
                t0 = time.perf_counter()
                self.state["quick"] = br.quick_image(spp=spec.quick_spp, seed=spec.seed, kind=crit.quick_kind)
                self.ledger.time("render_s", time.perf_counter() - t0)
            quick_blocks = br.cut_blocks(self.state["quick"])
        # the loop's units: the blocks' tiles (T a block; the blocks themselves when T = 1)
        self.loop = PassLoop(crit, (br.n_blocks, br.tiles_per_block), br.tile_shape, sched, spec.min_spp, quick_blocks,
                             device=br.device, tiling=br, ledger=self.ledger,
                             # an spp budget that can bind judges every unit it renders (`Budget.judges_every_unit`)
                             **({"decide_skip": 0.0, "decide_growth": 0.0}
                                if self.budget is not None and self.budget.judges_every_unit(spec.max_spp)
                                else {"decide_skip": spec.decide_skip, "decide_growth": spec.decide_growth}))
        if "acc" in self.state:                       # resumed: counters and timers go on from there
            self.loop.restore(self.state)
            check_evidence(self.ckpt_path, self.loop)   # what the file alone cannot vouch for
            self.ledger.restore(self.state["counters"], self.state["timers"])
            if self.budget is not None and self.state.get("budget") is not None:
                self.budget.restore(self.state["budget"])
                asked, ratio = self.state["budget"]["ratio_asked"], self.state["budget"]["ratio"]
                taken = last_decided_spp(self.loop.history, self.loop.history_unit_spp)   # at the last decision
                self.loop.ratios.put(np.flatnonzero(asked), ratio[asked], taken[asked])   # what rounds are chosen by
        #: the next launch, queued on the device while this one is judged (`advance`)
        self._ahead: tuple[np.ndarray, list[np.ndarray], Traced[torch.Tensor]] | None = None

    def _initial_state(self, resume: bool, pass_spp: list[int]) -> dict[str, Any]:
        path, br = self.ckpt_path, self.br
        if path is not None and resume and present(path):      # a broken or looping link: refused there
            state = load_checkpoint(path, self.settings, pass_spp=pass_spp, grid=(br.n_blocks, br.tiles_per_block),
                                    unit_shape=br.tile_shape, frame=(br.height, br.width), nonnegative=br.nonnegative)
            check_radiance(path, state["acc"], self.br, pass_spp[0], self.spec.seed)
            logger.info("%s: resuming after pass %d (%d active units)", path, state["pass_index"],
                        int(state["active"].sum()))
            return state
        if path is not None and resume:
            logger.info("%s: no checkpoint, starting from the beginning", path)
        elif path is not None and path.exists():
            logger.warning("%s: existing checkpoint ignored and replaced (use resume to continue it)", path)
        return {"pass_index": 0, "done": False, "counters": {}, "timers": {}, "quick": None}

    # -- the launch ----------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return bool(self.state["done"])

    @property
    def rows(self) -> int:
        """The verdict history's rows so far, one a pass (report.json "passes", the
        checkpoint's "pass_index"): the passes of the longest unit in a plain render."""
        return int(self.state["pass_index"])

    def plan(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The units of the next launch and, for each of its passes, every unit's pass index
        ([] when the render is over): every pending unit at its own next pass (all at the
        same one, unless a resumed budget render left them at different counts), or the units a
        budget picks."""
        loop = self.loop
        counts = loop.acc.pass_counts()
        if self.budget is None:
            ids = np.flatnonzero(loop.pending())
            return ids, self._grown(ids, counts[ids])
        elapsed = time.perf_counter() - self.t_start
        ids = np.asarray(self.budget.select(loop, elapsed), np.int64)
        if not ids.size:
            return ids, []
        if self.budget.spp_budget is not None or not self.grow:   # a sample budget pays pass by pass
            return ids, [counts[ids]]
        # a time limit: the round's blocks get passes as a grown launch would (a launch of a few
        # blocks costs up to 2.6x a lane of a full one: BENCHMARKS "cost per kept sample"), as
        # many as the time left pays for at the rate so far (one pass until a rate is known)
        grown = self._grown(ids, counts[ids])
        one = float(loop.pass_spp[counts[ids]].sum())
        left = self.budget.left(loop.acc.spp_all(), elapsed)      # inf: no rate known yet
        return ids, grown[:max(1, int(left // max(one, 1.0)) if math.isfinite(left) else 1)]

    def _grown(self, ids: np.ndarray, first: np.ndarray, stale: np.ndarray | None = None) -> list[np.ndarray]:
        """The pass indices of units `ids` in one launch, from their next ones `first`: as
        many passes as `grown_passes` gives ([] for none): past decisions that may stop a
        unit (`NEAR`) only as far as `ahead_passes` allows; every unit is judged at its own
        pass within the launch. `stale`: units whose next decision is not known yet (judged
        in a launch queued before this one, `_queue_next`): taken as due at their first pass."""
        if not ids.size:
            return []
        loop = self.loop
        passes_left = len(loop.schedule) - int(first.max())
        due = loop.due_pass(ids, first)
        if stale is not None:
            due = np.where(stale, first, due)
        near = ~(loop.ratios.predicted(ids, loop.schedule[due]) > NEAR)     # NaN: no estimate, may stop
        lanes = len(ids) * self.br.tile_h * self.br.tile_w * int(loop.pass_spp[first].max())
        cap = min(passes_left, max(1, LAUNCH_LANES // max(1, lanes)))
        k = grown_passes(self.br.n_units, len(ids), passes_left, self.grow,
                         undecided=ahead_passes((due - first)[near], len(ids), cap), lane_cap=cap)
        return [first + j for j in range(k)]

    def advance(self) -> int:
        """One launch: plan it (`plan`), queue it, wait for its images, then a round
        (`PassLoop.run_round`, `renderer.live.passloop`) per pass; returns the passes it added,
        the history rows (0: done).

        Without a budget (and with `grow`) the next launch is queued on the device as soon
        as this one's images are in, before they are judged, planned as if none of its
        units stopped (`_queue_next`): the device traces while the host accumulates and
        decides. (Queued before waiting for this launch instead, the host's work competes
        with the trace for a CPU's cores: 3 % slower on this project's 2-core machine.) The
        passes queued for units that stop are dropped, as a grown launch drops those past a
        stop, so the image, the stops and the history are those of the pass-by-pass loop;
        only samples_traced counts the dropped passes."""
        ahead, self._ahead = self._ahead, None
        t0 = time.perf_counter()
        if ahead is None:
            ids, pass_ids = self.plan()
            if not ids.size:
                self.state["done"] = True
                return 0
            traced = self._submit(ids, pass_ids)
        else:
            ids, pass_ids, traced = ahead
        images = traced.result()
        if self.budget is None and self.grow:
            self._ahead = self._queue_next(ids, pass_ids)
        self.ledger.time("render_s", time.perf_counter() - t0)
        loop, m = self.loop, len(ids)
        added = 0
        with torch_threads(1):
            for j, index in enumerate(pass_ids):      # the passes of one launch, in order: a round each
                keep = np.flatnonzero(loop.active[ids])
                if not keep.size:                      # every unit stopped: the rest is dropped
                    break
                if (loop.acc.pass_counts()[ids[keep]] != index[keep]).any():
                    raise RuntimeError("internal: a queued pass is not its unit's next pass")
                rows = torch.from_numpy(j * m + keep).to(images.device)
                loop.run_round(ids[keep], [(images[rows], loop.pass_spp[index[keep]])])
                added += 1
        if self.budget is not None:   # decisions too: they spend the time; every pass traced
            self.budget.record(time.perf_counter() - t0, int(sum(loop.pass_spp[index].sum() for index in pass_ids)))
        self.state["pass_index"] = self.rows + added
        self.state["done"] = not loop.pending().any() if self.budget is None else self.budget.finished(loop)
        if self.done:
            self._ahead = None        # a launch queued for units that have all stopped since
        return added

    def _submit(self, ids: np.ndarray, pass_ids: list[np.ndarray]) -> Traced[torch.Tensor]:
        """Queue the launch of these passes: jobs (unit, pass index), pass-major."""
        jobs = np.concatenate([np.stack([ids, index], axis=1) for index in pass_ids])
        return self.br.submit_passes(jobs, np.concatenate([self.loop.pass_spp[index] for index in pass_ids]),
                                     self.spec.seed)

    def _queue_next(self, ids: np.ndarray, pass_ids: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray],
                                                                                 Traced[torch.Tensor]] | None:
        """The launch `plan` would give after this one if none of its units stopped, queued
        (None when there is none): this launch's units still active (it is not judged yet)
        with passes left, each at its next pass, grown by their count."""
        after = pass_ids[-1] + 1
        go = self.loop.active[ids] & (after < len(self.loop.schedule))
        if not go.any():
            return None
        # a unit judged in this launch gets its next decision only then
        stale = self.loop.due_pass(ids, pass_ids[0]) <= pass_ids[-1]
        nxt, ahead = ids[go], self._grown(ids[go], after[go], stale=stale[go])
        return nxt, ahead, self._submit(nxt, ahead)

    # -- what survives a crash ---------------------------------------------------------

    def counts(self) -> dict[str, int]:
        """What the render cost in Mitsuba calls and kernels, over every attempt
        (report.json "render_calls"; reading the kernel compilations waits for the device)."""
        self.br.count_kernels()
        return {k: self.ledger.counters[k] for k in RENDER_COUNTERS}

    def snapshot(self) -> dict[str, Any]:
        """The state a checkpoint holds: the session's and the loop's, the budget's, and the
        ledger's counters and timers (wall_s up to now)."""
        self.br.count_kernels()                      # waits for the device
        timers = dict(self.ledger.timers)
        timers["wall_s"] += time.perf_counter() - self.t_start
        return {**self.state, **self.loop.state(), "settings": self.settings,
                "budget": None if self.budget is None else {
                    **self.budget.state(), **dict(zip(("ratio_asked", "ratio"),
                                                      self.loop.ratios.take(np.arange(self.br.n_units))))},
                "counters": dict(self.ledger.counters), "timers": timers}

    def drop_checkpoint(self) -> None:
        """A finished render that wrote no checkpoint: remove one an earlier run left, so
        that no stale state stays beside this render's outputs."""
        if self.ckpt_path is not None:
            self.ckpt_path.unlink(missing_ok=True)

    def checkpoint(self) -> None:
        """Write the checkpoint (in memory: nothing to resume from, so nothing)."""
        if self.ckpt_path is None:
            return
        self.ledger.count("checkpoints")
        save_checkpoint(self.ckpt_path, self.snapshot())
