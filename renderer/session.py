"""One adaptive render in progress: its renderer, loop, budget, checkpoint and report.

`renderer.adaptive.run_adaptive` resolves the render spec, opens a `RenderSession`, calls
`step` until the session is done, and asks it for the result. A step is explained once, in
`renderer.passloop`; here it picks the blocks and passes (`plan`), traces them in one
launch (`BlockRenderer.render_passes`) and hands them to `PassLoop.step`.

The session also keeps what survives a crash: `snapshot` is the state the checkpoint
holds, `checkpoint` writes it (`renderer.checkpoint`), and `counts` adds up what earlier
attempts cost. `renderer.report.render_result` turns a finished session into the result.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from noisefeat.runtime import torch_threads

from .blocks import BlockRenderer
from .budget import Budget
from .checkpoint import load_checkpoint, save_checkpoint
from .criteria import Criterion
from .passloop import PassLoop, schedule
from .spec import RenderSpec
from .wavefront import Traced

#: what a render cost in Mitsuba, over every attempt (report.json "render_calls"); like the
#: timings these depend on the process (a resumed run compiles its kernel again)
RENDER_COUNTERS = ("mitsuba_calls", "kernel_launches", "kernel_lanes", "kernel_compiles", "checkpoints",
                   "samples_traced")

logger = logging.getLogger(__name__)

def grown_passes(n_blocks: int, n_pending: int, passes_left: int, grow: bool = True) -> int:
    """How many passes of the pending blocks one launch traces (the rule that keeps the
    device busy): as blocks stop, the remaining ones get more passes per launch, so each
    launch holds about as many samples as the first (all blocks, one pass). The count is
    floor(n_blocks / n_pending), made even (a pass goes to each half buffer in turn, so an
    even count keeps them balanced), capped by the passes left; 1 without `grow`.

    The passes keep their own pass indices (so their own random numbers) and are judged one
    after the other, so a grown launch changes neither the stops nor the image: a block
    still gets a decision every pass, and the passes traced past its stop are dropped."""
    if not grow or n_pending <= 0:
        return 1
    k = n_blocks // n_pending
    if k >= 2:
        k -= k % 2
    return max(1, min(k, passes_left))


def run_settings(spec: RenderSpec, br: BlockRenderer, crit: Criterion, variant: str, scene: str) -> dict[str, Any]:
    """What a resume must match and the report repeats: the spec as rendered (the frame's
    blocks, the criterion as built, the variant)."""
    gh, gw = br.grid
    return {"scene": scene, "resolution": [br.width, br.height], "grid": [gh, gw], "block": [br.block_h, br.block_w],
            "tile": [br.tile_h, br.tile_w],
            "exposure": float(spec.exposure), "step": int(spec.step), "min_spp": int(spec.min_spp),
            "max_spp": int(spec.max_spp), "decide_skip": float(spec.decide_skip), "seed": int(spec.seed), "quick_spp": int(spec.quick_spp),
            "quick": crit.quick_kind if crit.needs_quick else "none", "criterion": crit.describe(),
            "variant": variant, "defines": dict(spec.defines or {}), "tau": float(spec.tau),
            **({} if spec.spp_budget is None else {"spp_budget": float(spec.spp_budget)})}


#: how far a resumed checkpoint's mean radiance may lie from its first pass traced again
RADIANCE_RATIO = 1e6


def check_radiance(path: Path, acc: Any, br: BlockRenderer, first_spp: int, seed: int) -> None:
    """ValueError unless a checkpoint's radiance is what its scene renders: a forged file
    whose sums were scaled (x1e30: every block then "converged") passes every check the file
    alone allows, its digest recomputed. The first pass depends only on (seed, pixel, pass),
    so it is traced again over the frame (`render_full`: one pass, not counted as the
    render's) and the mean radiance held must be within a factor RADIANCE_RATIO of its
    mean: both estimate the frame's mean, so a true checkpoint is within noise of it. A
    black first pass proves nothing (light found later) and is not held against the file."""
    units = np.flatnonzero(acc.passes_all() > 0)
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


class RenderSession:
    """The state of one render between its set-up and its result (see the module docstring).

    `state` is what a checkpoint restores (pass index: the history rows so far, done,
    counters, timers, quick image, a budget's state; the loop's arrays come from
    `loop.state()`); `settings` (`run_settings`) are what a resume must match.
    """

    def __init__(self, br: BlockRenderer, crit: Criterion, spec: RenderSpec, settings: dict[str, Any], *,
                 label: str, ckpt_path: Path | None, resume: bool, grow: bool, t_start: float) -> None:
        self.br, self.crit, self.spec, self.settings = br, crit, spec, settings
        self.label, self.ckpt_path, self.grow, self.t_start = label, ckpt_path, grow, t_start
        self.budget = Budget.for_spec(spec)
        sched = schedule(spec.step, spec.max_spp)
        self.state = self._initial_state(resume, np.diff(sched, prepend=0).tolist())
        self.timers = {"render_s": 0.0, "wall_s": 0.0, "setup_s": 0.0,
                       **{k: float(v) for k, v in self.state["timers"].items()
                          if k in ("render_s", "wall_s", "setup_s")}}
        self.timers["setup_s"] += time.perf_counter() - t_start  # imports, scene load, checkpoint read
        quick_blocks = None
        if crit.needs_quick:
            if self.state["quick"] is None:
                t0 = time.perf_counter()
                self.state["quick"] = br.quick_image(spp=spec.quick_spp, seed=spec.seed, kind=crit.quick_kind)
                self.timers["render_s"] += time.perf_counter() - t0
            quick_blocks = br.cut_blocks(self.state["quick"])
        # the loop's units: the blocks' tiles (T a block; the blocks themselves when T = 1)
        self.loop = PassLoop(crit, (br.n_blocks, br.tiles_per_block), br.tile_shape, sched, spec.min_spp, quick_blocks,
                             device=br.device, tiling=br,
                             decide_skip=spec.decide_skip if self.budget is None else 0.0)   # a budget spends by fresh ratios
        if "acc" in self.state:                       # resumed: counters and timers go on from there
            self.loop.restore(self.state)
            if self.budget is not None and self.state.get("budget") is not None:
                self.budget.restore(self.state["budget"])
                asked, ratio = self.state["budget"]["ratio_asked"], self.state["budget"]["ratio"]
                self.loop.ratios.put(np.flatnonzero(asked), ratio[asked])   # what the rounds are chosen by
        self.done_before = {k: int(self.state["counters"].pop(k, 0)) for k in RENDER_COUNTERS}
        self.checkpoints_written = 0
        #: the next step, queued on the device while this one is judged (`step`)
        self._ahead: tuple[np.ndarray, list[np.ndarray], Traced[torch.Tensor]] | None = None

    def _initial_state(self, resume: bool, pass_spp: list[int]) -> dict[str, Any]:
        path, br = self.ckpt_path, self.br
        if path is not None and resume and path.exists():
            state = load_checkpoint(path, self.settings, pass_spp=pass_spp, grid=(br.n_blocks, br.tiles_per_block),
                                    block=br.tile_shape, frame=(br.height, br.width), nonnegative=br.nonnegative)
            check_radiance(path, state["acc"], self.br, pass_spp[0], self.spec.seed)
            logger.info("%s: resuming after pass %d (%d active blocks)", path, state["pass_index"],
                        int(state["active"].sum()))
            return state
        if path is not None and resume:
            logger.info("%s: no checkpoint, starting from the beginning", path)
        elif path is not None and path.exists():
            logger.warning("%s: existing checkpoint ignored and replaced (use resume to continue it)", path)
        return {"pass_index": 0, "done": False, "counters": {}, "timers": {}, "quick": None}

    # -- the step ----------------------------------------------------------------------

    @property
    def done(self) -> bool:
        return bool(self.state["done"])

    @property
    def pass_index(self) -> int:
        return int(self.state["pass_index"])

    def plan(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The blocks of the next step and each pass's pass index per block ([] when the
        render is over): every pending block at its own next pass (all at the same one,
        unless a resumed budget render put them out of step), or the blocks a budget picks."""
        loop = self.loop
        own_all = loop.acc.passes_all()
        if self.budget is None:
            ids = np.flatnonzero(loop.pending())
            return ids, self._grown(ids, own_all[ids])
        ids = np.asarray(self.budget.select(loop, time.perf_counter() - self.t_start), np.int64)
        return ids, [own_all[ids]] if ids.size else []

    def _grown(self, ids: np.ndarray, own: np.ndarray) -> list[np.ndarray]:
        """The passes of blocks `ids`, at their own pass counts `own`, in one launch: as many
        as `grown_passes` gives for that many pending blocks ([] for none)."""
        if not ids.size:
            return []
        k = grown_passes(self.br.n_units, len(ids), len(self.loop.schedule) - int(own.max()), self.grow)
        return [own + j for j in range(k)]

    def step(self) -> int:
        """One step (`renderer.passloop`); returns the passes it added (0: done).

        Without a budget (and with `grow`) the next step is queued on the device as soon as
        this one's passes are in, before they are judged, planned as if none of its blocks
        stopped (`_queue_next`): the device traces while the host accumulates and decides.
        (Queued before waiting for this step instead, the host's work competes with the
        trace for a CPU's cores: 3 % slower on this project's 2-core machine.) The passes
        queued for blocks that stop are dropped, as a grown launch drops those past a stop,
        so the image, the stops and the history are those of the step-by-step loop; only
        samples_traced counts the dropped passes."""
        ahead, self._ahead = self._ahead, None
        t0 = time.perf_counter()
        if ahead is None:
            ids, passes = self.plan()
            if not ids.size:
                self.state["done"] = True
                return 0
            traced = self._submit(ids, passes)
        else:
            ids, passes, traced = ahead
        images = traced.result()
        if self.budget is None and self.grow:
            self._ahead = self._queue_next(ids, passes)
        self.timers["render_s"] += time.perf_counter() - t0
        loop, m = self.loop, len(ids)
        stepped = 0
        with torch_threads(1):
            for j, own in enumerate(passes):          # the passes of one launch, in order
                keep = np.flatnonzero(loop.active[ids])
                if not keep.size:                      # every block stopped: the rest is dropped
                    break
                if (loop.acc.passes_all()[ids[keep]] != own[keep]).any():
                    raise RuntimeError("internal: a queued pass is not its block's next pass")
                rows = torch.from_numpy(j * m + keep).to(images.device)
                loop.step(ids[keep], [(images[rows], loop.pass_spp[own[keep]])])
                stepped += 1
        if self.budget is not None:   # decisions too: they spend the time
            self.budget.record(time.perf_counter() - t0, int(loop.pass_spp[passes[0]].sum()))
        self.state["pass_index"] = self.pass_index + stepped
        self.state["done"] = not loop.pending().any() if self.budget is None else self.budget.finished(loop)
        if self.done:
            self._ahead = None        # a step queued for blocks that have all stopped since
        return stepped

    def _submit(self, ids: np.ndarray, passes: list[np.ndarray]) -> Traced[torch.Tensor]:
        """Queue the launch of a step's passes: jobs (block, pass) pass-major."""
        jobs = np.concatenate([np.stack([ids, own], axis=1) for own in passes])
        return self.br.submit_passes(jobs, np.concatenate([self.loop.pass_spp[own] for own in passes]),
                                     self.spec.seed)

    def _queue_next(self, ids: np.ndarray, passes: list[np.ndarray]) -> tuple[np.ndarray, list[np.ndarray],
                                                                               Traced[torch.Tensor]] | None:
        """The step `plan` would give after this one if none of its blocks stopped, queued
        (None when there is none): this step's blocks still active (it is not judged yet)
        with passes left, each at its next pass, grown by their count."""
        after = passes[-1] + 1
        go = self.loop.active[ids] & (after < len(self.loop.schedule))
        if not go.any():
            return None
        nxt, ahead = ids[go], self._grown(ids[go], after[go])
        return nxt, ahead, self._submit(nxt, ahead)

    # -- what survives a crash ---------------------------------------------------------

    def counts(self) -> dict[str, int]:
        """What the render cost in Mitsuba calls and kernels, over every attempt."""
        br = self.br
        now = {"mitsuba_calls": br.mitsuba_calls, "kernel_launches": br.kernel_launches,
               "kernel_lanes": br.kernel_lanes, "kernel_compiles": br.kernel_compiles,
               "checkpoints": self.checkpoints_written, "samples_traced": br.samples_traced}
        return {k: self.done_before[k] + now[k] for k in RENDER_COUNTERS}

    def snapshot(self) -> dict[str, Any]:
        wall = self.timers["wall_s"] + (time.perf_counter() - self.t_start)
        return {**self.state, **self.loop.state(), "settings": self.settings,
                "budget": None if self.budget is None else {
                    **self.budget.state(), **dict(zip(("ratio_asked", "ratio"),
                                                      self.loop.ratios.take(np.arange(self.br.n_units))))},
                "counters": {**self.loop.counters, **self.counts()},
                "timers": {**self.loop.timers, "render_s": self.timers["render_s"],
                           "setup_s": self.timers["setup_s"], "wall_s": wall}}

    def drop_checkpoint(self) -> None:
        """A finished render that wrote no checkpoint: remove one an earlier run left, so
        that no stale state stays beside this render's outputs."""
        if self.ckpt_path is not None:
            self.ckpt_path.unlink(missing_ok=True)

    def checkpoint(self) -> None:
        """Write the checkpoint (in memory: nothing to resume from, so nothing)."""
        if self.ckpt_path is None:
            return
        self.checkpoints_written += 1
        save_checkpoint(self.ckpt_path, self.snapshot())
