"""The adaptive progressive renderer (the paper's Figure 6): sample only the noisy blocks,
until no unit is active or max_spp is reached. Only the command line's render
(`adaptive_render`) checkpoints, between launches; samples depend only on (seed, pixel,
pass), so a resume gives the very image and report (timings aside) of an uninterrupted run."""
from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..spec import ARGUMENT
from .checkpoint import CHECKPOINT
from .outputs import clear_results
from .plan import RenderPlan, prepare
from .report import render_result
from .result import RenderResult
from .session import RenderSession
from .signals import DeferredStop

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Checkpoints:
    """Where the loop checkpoints: out/checkpoint.npz (`out` checked writable before the
    scene loads); `resume`: continue from it if it exists."""

    out: str | os.PathLike[str]
    resume: bool = False


def run_adaptive(scene: Any, criterion: Any = None, *, progress: bool = True, reference: Any = None,
                 checkpoints: Checkpoints | None = None, sensor: Any = None, integrator: Any = None,
                 grow: bool = True, source: str = ARGUMENT, plugin: Mapping[str, Any] | None = None,
                 **settings: Any) -> RenderResult:
    """The adaptive loop, in memory. `criterion` and `settings`: the render spec's rows, the
    rest: `prepare`'s. `checkpoints`: None writes no file. `grow`: trace several passes per
    launch as units stop (same result, fewer launches)."""
    t_start = time.perf_counter()
    plan = prepare(scene, {"criterion": criterion, **settings}, reference=reference, source=source, plugin=plugin,
                   sensor=sensor, integrator=integrator, out=None if checkpoints is None else checkpoints.out)
    try:
        session = open_session(plan, checkpoints, grow, t_start)
        reached = drive(session, progress, checkpoints is not None)
        return render_result(session, time_limit_reached=reached)
    finally:
        plan.renderer.close()


def open_session(plan: RenderPlan, checkpoints: Checkpoints | None, grow: bool, t_start: float) -> RenderSession:
    """The session of `plan`, resumed when asked. An earlier render's results go once this one is
    under way (a refused resume leaves them), on a resume too: beside an unfinished checkpoint
    they are stale, beside a finished one they are written again at once."""
    ckpt = None if checkpoints is None else Path(checkpoints.out) / CHECKPOINT
    session = RenderSession(plan, ckpt_path=ckpt, resume=checkpoints is not None and checkpoints.resume, grow=grow,
                            t_start=t_start)
    if ckpt is not None and (removed := clear_results(ckpt.parent)):
        logger.info("%s: removed the previous render's %s (%s)", ckpt.parent, ", ".join(removed),
                    "the resumed render writes them" if session.resumed else "this render writes its own when it ends")
    return session


def drive(session: RenderSession, progress: bool, checkpointing: bool) -> bool:
    """Advance the session until it is done; whether the time limit ended it. `checkpointing`: every
    period and on a first signal (then KeyboardInterrupt), none for a render that ends within its
    first period (a 1024x1024 checkpoint costs about half a second; resuming it is rendering it again)."""
    spec = session.spec
    every, time_limit = spec.checkpoint_every if checkpointing else math.inf, spec.time_limit
    last_saved = time.perf_counter()
    bar = tqdm(total=len(session.loop.schedule), initial=session.loop.rows, desc=f"{session.label} passes", unit="pass",
               disable=not progress, leave=False)
    stop = DeferredStop() if checkpointing else None
    with stop if stop is not None else nullcontext(), bar:
        while not session.done:
            added = session.advance()
            bar.set_postfix(active=int(session.loop.active.sum()), refresh=False)
            bar.update(added)
            now = time.perf_counter()
            reached = time_limit is not None and not session.done and now - session.t_start >= time_limit
            requested = stop is not None and stop.requested
            if session.done and session.ledger.counters["checkpoints"] == 0 and now - session.t_start < every:
                session.drop_checkpoint()     # shorter than the period: nothing worth resuming
            elif session.done or reached or requested or now - last_saved >= every:
                session.checkpoint()
                last_saved = time.perf_counter()
            if requested and not session.done:
                raise KeyboardInterrupt(f"{stop.requested} after pass {session.loop.rows}: checkpoint written to "
                                        f"{session.ckpt_path}, --resume continues")
            if reached:
                logger.info("%s: time limit of %gs reached after pass %d (%d units still active)%s",
                            session.label, time_limit, session.loop.rows, int(session.loop.active.sum()),
                            "; --resume continues" if session.ckpt_path is not None else "")
                return True
    return False


def adaptive_render(scene: str | os.PathLike, out: str | os.PathLike, criterion: Any = None, *,
                    resume: bool = False, **kwargs: Any) -> dict[str, Any]:
    """Render `scene` adaptively into `out`, with checkpoints there (`resume`: continue from them);
    the report, also out/report.json (wall_s: every attempt's, to the end of the last pass).
    `kwargs`: `run_adaptive`'s (the render spec's settings, `reference`, `progress`, `source`)."""
    result = run_adaptive(scene, criterion, checkpoints=Checkpoints(out, resume), **kwargs)
    result.save(out)
    report = result.report
    logger.info("%s: %d passes, saved %.1f%% vs uniform, %.2f s", report["scene"], report["passes"],
                100 * report["saved_vs_uniform"], report["wall_s"])
    return report
