"""One adaptive render in progress: its renderer, loop, budget, checkpoint and report.

`renderer.adaptive.run_adaptive` checks its arguments, opens a `RenderSession`, calls
`step` until the session is done, and asks it for the result. What a step is, the same
for plain passes and budget rounds:

1. choose the blocks and their passes (`plan`): every active block at the next pass, as
   many passes per launch as `grown_passes` allows; or, in a budget render, the blocks
   `Budget.select` picks, each at its own pass;
2. trace them in one launch (`BlockRenderer.render_passes`: pass images stay on the
   renderer's device);
3. add each pass to the loop and judge the blocks still active (`PassLoop.step`: one
   batched criterion call, verdicts back to the host).

The session also keeps what survives a crash: `snapshot` is the state the checkpoint
holds, `checkpoint` writes it (`renderer.checkpoint`), and `counts` adds up what earlier
attempts cost.
"""
from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from learning.data.stack import Stack
from noisefeat.runtime import torch_threads

from .blocks import BlockRenderer, compose
from .budget import Budget
from .checkpoint import load_checkpoint, save_checkpoint
from .criteria import TIMER_NAMES, Criterion
from .passloop import PassLoop
from .report import final_vs_reference, render_report
from .result import RenderResult

#: what a render cost in Mitsuba, over every attempt (report.json "render_calls"); like the
#: timings these depend on the process (a resumed run compiles its kernel again)
RENDER_COUNTERS = ("mitsuba_calls", "kernel_launches", "kernel_lanes", "kernel_compiles", "checkpoints",
                   "samples_traced")

logger = logging.getLogger(__name__)

#: a pass of a step: (pass index of each block, spp of each block), int64 arrays
Pass = tuple[np.ndarray, np.ndarray]


def grown_passes(n_blocks: int, n_active: int, passes_left: int, grow: bool = True) -> int:
    """How many passes of the active blocks one launch traces (the rule that keeps the
    device busy): as blocks stop, the remaining ones get more passes per launch, so each
    launch holds about as many samples as the first (all blocks, one pass). The count is
    floor(n_blocks / n_active), made even (a pass goes to each half buffer in turn, so an
    even count keeps them balanced), capped by the passes left; 1 without `grow`.

    The passes keep their own pass indices (so their own random numbers) and are judged one
    after the other, so a grown launch changes neither the stops nor the image: a block
    still gets a decision every `step` samples, and the passes traced past its stop are
    dropped (`pass_step`)."""
    if not grow or n_active <= 0:
        return 1
    k = n_blocks // n_active
    if k >= 2:
        k -= k % 2
    return max(1, min(k, passes_left))


def pass_step(loop: PassLoop, br: BlockRenderer, ids: Sequence[int], passes: Sequence[Pass], seed: int,
              timers: dict[str, float]) -> int:
    """Trace `passes` of the blocks `ids` in one launch, then add each pass to the loop in
    order, judging the blocks still active after it. Returns the passes stepped (fewer than
    given when every block stopped early: the rest is dropped)."""
    ids_a = np.asarray(ids, np.int64)
    m = len(ids_a)
    jobs = np.concatenate([np.stack([ids_a, own], axis=1) for own, _ in passes])   # (block, pass), pass-major
    t0 = time.perf_counter()
    images = br.render_passes(jobs, np.concatenate([spp for _, spp in passes]), seed)
    timers["render_s"] += time.perf_counter() - t0
    with torch_threads(1):
        for j, (_, spp) in enumerate(passes):        # the passes of one launch, in order
            keep = np.flatnonzero(loop.active[ids_a])
            if not keep.size:
                return j
            rows = torch.from_numpy(j * m + keep).to(images.device)
            loop.step(ids_a[keep], [(images[rows], spp[keep])])
    return len(passes)


class RenderSession:
    """The state of one render between its set-up and its result (see the module docstring).

    `state` is what a checkpoint restores (pass index: the history rows so far, done,
    counters, timers, quick image, a budget's state; the loop's arrays come from
    `loop.state()`); `settings` are what a resume must match.
    """

    def __init__(self, br: BlockRenderer, crit: Criterion, settings: dict[str, Any], sizes: list[int], *,
                 label: str, seed: int, min_spp: int, quick_spp: int, budget: Budget | None,
                 ckpt_path: Path | None, resume: bool, grow: bool, t_start: float) -> None:
        self.br, self.crit, self.settings, self.sizes = br, crit, settings, sizes
        self.label, self.seed, self.budget, self.ckpt_path, self.grow = label, seed, budget, ckpt_path, grow
        self.t_start = t_start
        self.state = self._initial_state(resume)
        self.timers = {"render_s": 0.0, "wall_s": 0.0, "setup_s": 0.0,
                       **{k: float(v) for k, v in self.state["timers"].items()
                          if k in ("render_s", "wall_s", "setup_s")}}
        self.timers["setup_s"] += time.perf_counter() - t_start  # imports, scene load, checkpoint read
        crit.reset_counters()
        quick_blocks = None
        if crit.needs_quick:
            if self.state["quick"] is None:
                t0 = time.perf_counter()
                self.state["quick"] = br.quick_image(spp=quick_spp, seed=seed, kind=crit.quick_kind)
                self.timers["render_s"] += time.perf_counter() - t0
            quick_blocks = br.cut_blocks(self.state["quick"])
            crit.prepare(list(range(br.n_blocks)), quick_blocks)
        self.loop = PassLoop(crit, br.grid, br.block_shape, min_spp, quick_blocks, device=br.device)
        if "acc" in self.state:                       # resumed
            self.loop.restore(self.state)
            if budget is not None and self.state.get("budget") is not None:
                budget.restore(self.state["budget"])
                asked, ratio = self.state["budget"]["ratio_asked"], self.state["budget"]["ratio"]
                crit.ratios.put(np.flatnonzero(asked), ratio[asked])   # what the rounds are chosen by
        self.done_before = {k: int(self.state["counters"].pop(k, 0)) for k in RENDER_COUNTERS}
        if self.state["counters"]:  # resumed: continue the counts (this overrides what prepare counted)
            crit.restore_counters(self.state["counters"],
                                  {k: v for k, v in self.state["timers"].items() if k in TIMER_NAMES})
        self.checkpoints_written = 0

    def _initial_state(self, resume: bool) -> dict[str, Any]:
        path, br = self.ckpt_path, self.br
        if path is not None and resume and path.exists():
            state = load_checkpoint(path, self.settings, sizes=self.sizes, grid=br.grid, block=br.block_shape,
                                    frame=(br.height, br.width))
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

    def plan(self) -> tuple[list[int], list[Pass]]:
        """The blocks of the next step and their passes ([] when the render is over). Each
        block takes its own next pass: in a plain render they are all at the same one
        (unless it resumes a budget render whose rounds put them out of step)."""
        loop, sizes = self.loop, np.asarray(self.sizes, np.int64)
        passes = loop.acc.passes_all()
        if self.budget is None:
            ids = np.flatnonzero(loop.active & (passes < len(sizes)))
            if not ids.size:
                return [], []
            own = passes[ids]
            k = grown_passes(self.br.n_blocks, len(ids), len(sizes) - int(own.max()), self.grow)
            return ids.tolist(), [(own + j, sizes[own + j]) for j in range(k)]
        ids = self.budget.select(loop, self.sizes, time.perf_counter() - self.t_start)
        own = passes[np.asarray(ids, np.int64)]
        return ids, [(own, sizes[own])] if ids else []

    def step(self) -> int:
        """One step (see the module docstring); returns the passes it added (0: done)."""
        ids, passes = self.plan()
        if not ids:
            self.state["done"] = True
            return 0
        t0 = time.perf_counter()
        stepped = pass_step(self.loop, self.br, ids, passes, self.seed, self.timers)
        if self.budget is not None:   # decisions too: they spend the time
            self.budget.record(time.perf_counter() - t0, int(passes[0][1].sum()))
        self.state["pass_index"] = self.pass_index + stepped
        loop = self.loop
        self.state["done"] = not (loop.active & (loop.acc.passes_all() < len(self.sizes))).any() \
            if self.budget is None else self.budget.finished(loop, self.sizes)
        return stepped

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
                                                      self.crit.ratios.take(np.arange(self.br.n_blocks))))},
                "counters": {**dict(self.crit.counters), **self.counts()},
                "timers": {**self.crit.timers, "render_s": self.timers["render_s"],
                           "setup_s": self.timers["setup_s"], "wall_s": wall}}

    def checkpoint(self) -> None:
        """Write the checkpoint (in memory: nothing to resume from, so nothing)."""
        if self.ckpt_path is None:
            return
        self.checkpoints_written += 1
        save_checkpoint(self.ckpt_path, self.snapshot())

    # -- the result --------------------------------------------------------------------

    def result(self, *, variant: str, sources: dict[str, str], given: Sequence[str], tau: float,
               defines: dict[str, str] | None, time_limit: float | None, time_limit_reached: bool,
               ref_stack: Stack | None, ref_image: np.ndarray | None, reference: Any) -> RenderResult:
        """The image, per-pixel spp and stops, and the report (report.json)."""
        from .settings import NOT_USED

        br, loop, acc, n = self.br, self.loop, self.loop.acc, self.br.n_blocks
        final = self.snapshot()
        report = render_report(self.label, br, self.settings, self.crit, {**self.state, **loop.state()}, acc,
                               final["timers"], variant, ref_stack)
        report["settings_source"] = {k: sources[k] for k in given if sources[k] != NOT_USED}
        if defines:
            report["defines"] = dict(defines)
        if time_limit is not None:
            report["time_limit"] = {"seconds": float(time_limit), "reached": time_limit_reached}
        if self.budget is not None:
            report["budget"] = self.budget.describe(loop, time_limit_reached)
        report["render_calls"] = self.counts()
        windows = [br.window(b) for b in range(n)]
        image, spp_px, owner = compose(acc.means(np.arange(n)).cpu().numpy(), windows, acc.spp_all(),
                                       (br.height, br.width))
        image = image.astype(np.float32)
        ref_img = ref_image
        if ref_stack is not None:
            ref_img = ref_stack.reference()
            if ref_img.shape != image.shape:
                logger.warning("reference image %s differs from the render %s: no final-vs-reference check",
                               ref_img.shape, image.shape)
                ref_img = None
        if ref_img is not None:
            report["final_vs_reference"] = final_vs_reference(
                image, ref_img, br.grid, float(tau), float(self.settings["exposure"]), ~loop.active,
                windows=windows if br.overlapping else None)
            if ref_stack is None:
                report["reference"] = {"image": os.fspath(reference) if isinstance(reference, (str, os.PathLike))
                                       else "array", "width": br.width, "height": br.height}
        return RenderResult(image=image, spp=spp_px, converged=(~loop.active)[owner], report=report,
                            reference=ref_img)

