"""One adaptive render in progress (`RenderSession`): its renderer, loop, budget, the `Ledger`
they share, and the checkpoint that lets a crashed render go on (`progress`)."""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from learning.inputs.history import last_decided_spp
from noisefeat.runtime import torch_threads
from noisefeat.safeio import present

from ..criteria import COUNTER_NAMES, TIMER_NAMES
from .budget import Budget
from .checkpoint import load_checkpoint, save_checkpoint
from .checkpoint_checks import check_evidence, check_radiance
from .launches import LAUNCH_LANES, NEAR, ahead_passes, grown_passes
from .ledger import RENDER_COUNTERS, RENDER_TIMERS, Ledger
from .passloop import PassLoop, schedule
from .plan import RenderPlan
from .progress import Progress, RunSettings
from .wavefront import Traced

logger = logging.getLogger(__name__)
#: a queued launch: its units, each pass's pass indices, its images to come
Launch = tuple[np.ndarray, list[np.ndarray], Traced[torch.Tensor]]


class RenderSession:
    """One render between its set-up and its result. `br`, `spec`, `label`: the plan's renderer,
    spec and label; `settings`: what a resume must match; `quick`: the quick image (None when
    the criterion reads none); `resumed`: the render went on from a checkpoint."""

    def __init__(self, plan: RenderPlan, *, ckpt_path: Path | None, resume: bool, grow: bool,
                 t_start: float) -> None:
        br, crit, spec = plan.renderer, plan.criterion, plan.spec
        self.render_plan, self.br, self.spec, self.label = plan, br, spec, plan.label
        self.settings = RunSettings.of(plan)
        self.ckpt_path, self.grow, self.t_start = ckpt_path, grow, t_start
        self.ledger = Ledger(COUNTER_NAMES + RENDER_COUNTERS, TIMER_NAMES + RENDER_TIMERS)
        br.ledger = self.ledger                       # the renderer's Mitsuba calls, from now on
        sched = schedule(spec.step, spec.max_spp)
        restored = self._restored(resume, np.diff(sched, prepend=0).tolist())
        self.resumed = restored is not None
        self.done = restored is not None and restored.done
        self.quick = None if restored is None else restored.quick
        self.budget = Budget.for_spec(spec, self.ledger, resumed=restored is not None and restored.budget is not None)
        self.ledger.time("setup_s", time.perf_counter() - t_start)  # imports, scene load, checkpoint read
        quick_blocks = None
        if crit.needs_quick:
            if self.quick is None:
                t0 = time.perf_counter()
                self.quick = br.quick_image(spp=spec.quick_spp, seed=spec.seed, kind=crit.quick_kind)
                self.ledger.time("render_s", time.perf_counter() - t0)
            quick_blocks = br.cut_blocks(self.quick)
        every = self.budget is not None and self.budget.judges_every_unit(spec.max_spp)
        self.loop = PassLoop(crit, (br.n_blocks, br.tiles_per_block), br.tile_shape, sched, spec.min_spp, quick_blocks,
                             device=br.device, tiling=br, ledger=self.ledger,
                             decide_skip=0.0 if every else spec.decide_skip,
                             decide_growth=0.0 if every else spec.decide_growth)
        if restored is not None:                      # resumed: counters and timers go on from there
            self.loop.restore(restored.loop)
            check_evidence(self.ckpt_path, self.loop)   # what the file alone cannot vouch for
            self.ledger.restore(restored.counters, restored.timers)
            if self.budget is not None and restored.budget is not None:
                self.budget.restore(restored.budget)
                asked, ratio = restored.budget.ratio_asked, restored.budget.ratio
                taken = last_decided_spp(self.loop.history, self.loop.history_unit_spp)   # at the last decision
                self.loop.ratios.put(np.flatnonzero(asked), ratio[asked], taken[asked])   # what rounds are chosen by
        #: the next launch, queued on the device while this one is judged (`advance`)
        self._ahead: Launch | None = None

    def _restored(self, resume: bool, pass_spp: list[int]) -> Progress | None:
        """The progress of the checkpoint to resume (None: a fresh render)."""
        path, br = self.ckpt_path, self.br
        if path is not None and resume and present(path):      # a broken or looping link: refused there
            progress = load_checkpoint(path, self.settings, pass_spp=pass_spp,
                                       grid=(br.n_blocks, br.tiles_per_block), unit_shape=br.tile_shape,
                                       frame=(br.height, br.width), nonnegative=br.nonnegative)
            check_radiance(path, progress.loop.acc, self.br, pass_spp[0], self.spec.seed)
            logger.info("%s: resuming after pass %d (%d active units)", path, progress.rows,
                        int(progress.loop.active.sum()))
            return progress
        if path is not None and resume:
            logger.info("%s: no checkpoint, starting from the beginning", path)
        elif path is not None and path.exists():
            logger.warning("%s: existing checkpoint ignored and replaced (use resume to continue it)", path)
        return None

    # -- the launch ----------------------------------------------------------------------

    def plan(self) -> tuple[np.ndarray, list[np.ndarray]]:
        """The units of the next launch and, per pass, each unit's pass index ([]: the render is
        over): every pending unit at its own next pass, or the units a budget picks."""
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
        # a time limit: passes as a grown launch (a launch of a few blocks costs up to 2.6x a lane
        # of a full one: BENCHMARKS "cost per kept sample"), as many as the time left pays for
        grown = self._grown(ids, counts[ids])
        one = float(loop.pass_spp[counts[ids]].sum())
        left = self.budget.left(loop.acc.spp_all(), elapsed)      # inf: no rate known yet
        return ids, grown[:max(1, int(left // max(one, 1.0)) if math.isfinite(left) else 1)]

    def _grown(self, ids: np.ndarray, first: np.ndarray, stale: np.ndarray | None = None) -> list[np.ndarray]:
        """The pass indices of units `ids` in one launch from their next ones `first` (`grown_passes`,
        `ahead_passes`). `stale`: units whose next decision is not known yet, taken as due at `first`."""
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
        """One launch, then a round per pass; the history rows it added (0: done). Without a budget and
        with `grow`, the next launch is queued once this one's images are in, before they are judged
        (queued before the wait, the host's work slows the trace). Passes of units that stop are dropped."""
        ahead, self._ahead = self._ahead, None
        t0 = time.perf_counter()
        if ahead is None:
            ids, pass_ids = self.plan()
            if not ids.size:
                self.done = True
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
            for j, index in enumerate(pass_ids):      # a round each
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
        self.done = not loop.pending().any() if self.budget is None else self.budget.finished(loop)
        if self.done:
            self._ahead = None        # a launch queued for units that have all stopped since
        return added

    def _submit(self, ids: np.ndarray, pass_ids: list[np.ndarray]) -> Traced[torch.Tensor]:
        """Queue the launch of these passes: jobs (unit, pass index), pass-major."""
        jobs = np.concatenate([np.stack([ids, index], axis=1) for index in pass_ids])
        return self.br.submit_passes(jobs, np.concatenate([self.loop.pass_spp[index] for index in pass_ids]),
                                     self.spec.seed)

    def _queue_next(self, ids: np.ndarray, pass_ids: list[np.ndarray]) -> Launch | None:
        """The launch `plan` would give after this one if none of its units stopped, queued (None: none)."""
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
        """What every attempt cost in Mitsuba (report.json "render_calls"; waits for the device)."""
        self.br.count_kernels()
        return {k: self.ledger.counters[k] for k in RENDER_COUNTERS}

    def wall_s(self) -> float:
        """Seconds of every attempt so far: the earlier ones' (the ledger's) and this one's."""
        return self.ledger.timers["wall_s"] + (time.perf_counter() - self.t_start)

    @property
    def progress(self) -> Progress:
        """What the render has done, now (the loop's live arrays, not copies; kernels as last counted)."""
        timers = {**self.ledger.timers, "wall_s": self.wall_s()}
        return Progress(self.loop.state(), done=self.done, counters=dict(self.ledger.counters), timers=timers,
                        quick=self.quick, budget=None if self.budget is None else self.budget.state(self.loop.ratios))

    def drop_checkpoint(self) -> None:
        """Remove a checkpoint an earlier run left (a finished render that wrote none)."""
        if self.ckpt_path is not None:
            self.ckpt_path.unlink(missing_ok=True)

    def checkpoint(self) -> None:
        """Write the checkpoint (none for a render without a checkpoint path)."""
        if self.ckpt_path is None:
            return
        self.ledger.count("checkpoints")
        self.br.count_kernels()                      # waits for the device
        save_checkpoint(self.ckpt_path, self.progress, self.settings)
