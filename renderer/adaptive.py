"""The adaptive progressive renderer (the paper's Figure 6): sample only the noisy blocks.

`run_adaptive` checks its arguments, then steps a `renderer.session.RenderSession` until
it is done, then builds the result. A step (a pass adds `step` samples per pixel):

1. trace the active blocks only, each at its next pass (`BlockRenderer.render_passes`:
   the samples of (pixel, pass) are fixed whatever happened before), several passes in one
   launch when few blocks remain (`renderer.session.grown_passes`), or in a budget render
   the blocks the budget picks;
2. accumulate them where they were traced (`BlockAccumulator`: exact means, even/odd half
   buffers, torch tensors on the variant's device);
3. once spp >= min_spp, ask the criterion about them in one batch, after each pass; a
   block it calls converged leaves the active set for good: never rendered, featured or
   asked again;
4. checkpoint everything (accumulator, active set, verdict history, counters, timers, pass
   index) atomically into out/checkpoint.npz (`renderer.checkpoint`: digest-checked and
   validated against the settings before a resume trusts it), every `checkpoint_every`
   seconds, at the end, at the time limit and on SIGINT/SIGTERM (`renderer.signals`):
   a step is never half-saved.

It stops when no block is active or max_spp is reached. Because samples depend only on
(seed, pixel, pass) and the checkpoint holds all state, ``resume=True`` after a crash
gives the very image and report (timings aside) of an uninterrupted run.

`run_adaptive` is the loop itself, in memory: it takes a scene name, an XML path or an
already-loaded ``mi.Scene`` and returns a `RenderResult`. Checkpoints (step 4) are taken
only when it is given a `Checkpoints` (the command line's resumable render,
`adaptive_render`); `renderer.render` and the ``noisestop`` Mitsuba plugin run without.

The quick image (the kind the model was trained with, `quick_spp` samples) is rendered once, and only if the
criterion needs it; it is stored in the checkpoint so a resume does not re-render it.
"""
from __future__ import annotations

import logging
import math
import os
import time
from contextlib import nullcontext
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learning.data.stack import Stack
from learning.names import DEFAULT_TAU
from noisefeat.bounds import SizeBounds

from .argcheck import check_budget_buys_a_pass, check_reference_image, check_render_args
from .blocks import BlockRenderer
from .budget import Budget
from .checkpoint import CHECKPOINT
from .criteria import Criterion, build_criterion
from .outputs import prepare_output_dir
from .report import pass_sizes
from .result import RenderResult
from .session import RenderSession
from .settings import DEFAULT, check_spp_settings, resolve_settings
from .settings import describe as describe_settings
from .signals import DeferredStop

logger = logging.getLogger(__name__)



def scene_label(scene: str | os.PathLike) -> str:
    """Directory name of a scene: the built-in name, or an XML file's stem."""
    s = os.fspath(scene)
    return Path(s).stem if s.lower().endswith(".xml") else s


# ----------------------------------------------------------------------------- the loop


def _run_steps(session: RenderSession, progress: bool, time_limit: float | None,
               checkpoints: Checkpoints | None) -> bool:
    """Step the session until it is done, checkpointing on time, at the end, at the time
    limit and on a signal (the first SIGINT/SIGTERM finishes the step, checkpoints and
    raises KeyboardInterrupt). Returns whether the time limit ended the render."""
    every = checkpoints.every if checkpoints is not None else math.inf
    last_saved = time.perf_counter()
    bar = tqdm(total=len(session.sizes), initial=session.pass_index, desc=f"{session.label} passes", unit="pass",
               disable=not progress, leave=False)
    stop = DeferredStop() if checkpoints is not None else None
    with stop if stop is not None else nullcontext(), bar:
        while not session.done:
            stepped = session.step()
            bar.set_postfix(active=int(session.loop.active.sum()), refresh=False)
            bar.update(stepped)
            now = time.perf_counter()
            reached = time_limit is not None and not session.done and now - session.t_start >= time_limit
            requested = stop is not None and stop.requested
            if session.done or reached or requested or now - last_saved >= every:
                session.checkpoint()
                last_saved = time.perf_counter()
            if requested and not session.done:
                raise KeyboardInterrupt(f"{stop.requested} after pass {session.pass_index}: checkpoint written to "
                                        f"{session.ckpt_path}, --resume continues")
            if reached:
                logger.info("%s: time limit of %gs reached after pass %d (%d blocks still active)%s",
                            session.label, time_limit, session.pass_index, int(session.loop.active.sum()),
                            "; --resume continues" if session.ckpt_path is not None else "")
                return True
    return False


def _resolve_criterion(criterion: Criterion | str, reference: Stack | None, tau: float) -> Criterion:
    if isinstance(criterion, Criterion):
        return criterion
    if isinstance(criterion, str):
        th = reference.thresholds if reference is not None else None
        return build_criterion(criterion, thresholds=th, tau=tau)
    from .names import CRITERIA

    raise ValueError(f"criterion must be a Criterion or one of {', '.join(CRITERIA)}, "
                     f"got {type(criterion).__name__}")


def _check_args(resolution: Any, grid: Sequence[int] | None, block: int | None, step: int, min_spp: int,
                max_spp: int) -> tuple[Any, tuple[int, int] | None]:
    """Documented ranges (renderer.settings, noisefeat.bounds), checked before the scene is
    loaded: resolution None (the scene's own) passes, else its frame and blocks must fit.
    Returns (resolution as N or (W, H), grid or None)."""
    from .scenes import parse_resolution

    check_spp_settings(step, min_spp, max_spp)
    bounds = SizeBounds.from_env()
    if grid is not None:
        if len(grid) != 2 or any(isinstance(g, bool) or not isinstance(g, (int, np.integer)) or g < 1
                                 for g in grid):
            raise ValueError(f"grid must be two positive integers (rows, columns), got {grid!r}")
        grid = (int(grid[0]), int(grid[1]))
    elif isinstance(block, bool) or not isinstance(block, (int, np.integer)):
        raise ValueError(f"block must be a whole number of pixels, got {block!r}")
    else:
        bounds.check_block(int(block), int(block), what="--block")
    if resolution is not None:
        resolution = parse_resolution(resolution)
        w, h = resolution if isinstance(resolution, tuple) else (resolution, resolution)
        bounds.check_frame(h, w, grid or (1, 1), block=None if grid else (int(block), int(block)))
    return resolution, grid


@dataclass(frozen=True)
class Checkpoints:
    """Where and how often the loop checkpoints: the command line's resumable render.

    `out`: the output folder (checked writable before the scene is loaded; the checkpoint
    is out/checkpoint.npz); `resume`: continue from it if it exists; `every`: seconds
    between checkpoints (0: after every pass). With checkpoints the first SIGINT/SIGTERM
    finishes the pass and checkpoints before stopping (`renderer.signals`).
    """

    out: str | os.PathLike[str]
    resume: bool = False
    every: float = 30.0


def is_scene_object(scene: Any) -> bool:
    """Whether `scene` is an already-loaded ``mi.Scene`` (without importing Mitsuba for a name)."""
    if isinstance(scene, (str, os.PathLike)):
        return False
    from noisefeat.extras import require

    return isinstance(scene, require("mitsuba").Scene)


def _scene_object_label(scene: Any) -> str:
    """A loaded scene's name in reports: its id when the file or dict gave one, else 'scene'."""
    try:
        sid = str(scene.id())
    except Exception:  # an id is cosmetic: never fail a render over it
        sid = ""
    return sid if sid and not sid.startswith("_unnamed") else "scene"


def _check_scene_arg(scene: Any, resolution: Any, defines: Mapping[str, str] | None) -> tuple[bool, str]:
    """(whether `scene` is a loaded mi.Scene, its label); one-line ValueError for what
    cannot be asked of a loaded scene or for a scene of another type."""
    if isinstance(scene, (str, os.PathLike)):
        return False, scene_label(scene)
    if not is_scene_object(scene):
        raise ValueError(f"scene must be an mi.Scene, an XML file path or a built-in scene name, "
                         f"got {type(scene).__name__}")
    if resolution is not None:
        raise ValueError("resolution cannot be changed on an already-loaded mi.Scene: set the film's "
                         "width and height in the scene, or pass the XML file's path")
    if defines:
        raise ValueError("defines (-D) set parameters while an XML file loads: pass the file's path, "
                         "not an already-loaded mi.Scene")
    return True, _scene_object_label(scene)


def load_reference(reference: Stack | str | os.PathLike[str] | np.ndarray, label: str,
                   tau: float) -> tuple[Stack | None, np.ndarray | None]:
    """(labelled stack, None) for a stack or dataset directory; (None, image) for a
    reference image: an EXR file or a float [H, W, 3] array. An image gives the
    final-vs-reference check only: it has no per-level errors, so no oracle thresholds."""
    from .simulate import find_reference

    if isinstance(reference, np.ndarray):
        img = np.asarray(reference, np.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"a reference image must be float [H, W, 3] linear RGB, got shape {img.shape}")
        check_reference_image(img)
        return None, img
    if isinstance(reference, (str, os.PathLike)) and (os.fspath(reference).lower().endswith(".exr")
                                                      or Path(reference).is_file()):
        from learning.data.exr import read_exr

        if not Path(reference).is_file():
            raise FileNotFoundError(f"{os.fspath(reference)}: reference image not found")
        img = read_exr(reference)
        check_reference_image(img)
        return None, img
    return find_reference(reference, label, tau), None


def adaptive_render(scene: str | os.PathLike, out: str | os.PathLike, criterion: Criterion | str, *,
                    resolution: int | tuple[int, int] | str | None = None, grid: Sequence[int] | None = None,
                    block: int | None = None, step: int | None = None,
                    min_spp: int | None = None, max_spp: int | None = None, seed: int = 0, resume: bool = False,
                    progress: bool = True, reference: Stack | str | os.PathLike | None = None,
                    quick_spp: int = 16, defines: Mapping[str, str] | None = None,
                    time_limit: float | None = None, checkpoint_every: float = 30.0,
                    tau: float = DEFAULT_TAU, spp_budget: float | None = None,
                    grow: bool = True) -> dict[str, Any]:
    """Render `scene` adaptively into `out`; return the report (also out/report.json).

    The command line's render: `run_adaptive` with checkpoints in `out`, then
    `RenderResult.save(out)`. wall_s in the report runs from the call to the end of the
    last pass (writing the output files is not in it); resumed runs add up the time of
    every attempt.

    `criterion`: a `Criterion`, or its name ('oracle' takes the thresholds of `reference`).
    `reference`: a labelled Stack, or a dataset/stack directory holding this scene: adds
    early_stop_rate, spp_ratio_vs_oracle and per-block true thresholds to the report; or
    a reference image (an EXR file): adds final_vs_reference only.
    Settings left None come from the reference, the scene or the defaults
    (`renderer.settings`); the report's `settings_source` says which. `defines`: an XML
    scene's parameters, as `mitsuba -D key=value` (recorded in the report). `time_limit`:
    seconds this call may run; the pass under way when it is reached is finished, then the
    outputs and the checkpoint are written and `resume` continues from there.
    `checkpoint_every`: seconds between checkpoints (0: after every pass). `tau`: the
    noise target, recorded in the report; the reference's labels and the final-vs-reference
    check use the observer at it (a criterion given by name is built for it too).
    `spp_budget` (samples per pixel, averaged over the blocks) and `time_limit` make it a
    budget render (`renderer.budget`): passes go to the blocks farthest from their target.
    """
    result = run_adaptive(scene, criterion, resolution=resolution, grid=grid, block=block, step=step,
                          min_spp=min_spp, max_spp=max_spp, seed=seed, progress=progress, reference=reference,
                          quick_spp=quick_spp, defines=defines, time_limit=time_limit, tau=tau,
                          checkpoints=Checkpoints(out, resume, checkpoint_every), spp_budget=spp_budget,
                          grow=grow)
    result.save(out)
    report = result.report
    logger.info("%s: %d passes, saved %.1f%% vs uniform, %.2f s", report["scene"], report["passes"],
                100 * report["saved_vs_uniform"], report["wall_s"])
    return report


def run_adaptive(scene: Any, criterion: Criterion | str, *,
                 resolution: int | tuple[int, int] | str | None = None, grid: Sequence[int] | None = None,
                 block: int | None = None, step: int | None = None,
                 min_spp: int | None = None, max_spp: int | None = None, seed: int = 0,
                 progress: bool = True, reference: Stack | str | os.PathLike | np.ndarray | None = None,
                 quick_spp: int = 16, defines: Mapping[str, str] | None = None,
                 time_limit: float | None = None, tau: float = DEFAULT_TAU,
                 checkpoints: Checkpoints | None = None, sensor: Any = None,
                 integrator: Any = None, spp_budget: float | None = None, grow: bool = True) -> RenderResult:
    """The adaptive loop, in memory (see the module docstring and `adaptive_render`).

    `scene`: a built-in name, an XML path or a loaded ``mi.Scene`` (then `resolution` and
    `defines` are refused: the scene is already built). `sensor` / `integrator`: render
    from this sensor with this integrator instead of the scene's first sensor and own
    integrator (the Mitsuba plugin passes its nested one). `checkpoints`: None renders
    without any file; given, the loop checkpoints into its folder and can resume from it.
    `spp_budget` (samples per pixel, averaged over the blocks) and `time_limit` make it a
    budget render (`renderer.budget`): passes go to the blocks farthest from their target.
    `grow`: trace several passes per launch as blocks stop (`grown_passes`; same result,
    fewer launches); False keeps one pass per launch (the benchmark's fixed step).
    """
    check_render_args(step=step, min_spp=min_spp, max_spp=max_spp, quick_spp=quick_spp,
                      time_limit=time_limit, spp_budget=spp_budget)       # each error names its own argument
    if checkpoints is not None and not (math.isfinite(checkpoints.every) and checkpoints.every >= 0):
        raise ValueError(f"checkpoint interval must be 0 or more seconds, got {checkpoints.every!r}")
    budget = Budget(spp_budget, time_limit) if spp_budget is not None or time_limit is not None else None
    from .scenes import load_scene
    from learning.data.variant import current_variant, select_variant

    t_start = time.perf_counter()
    loaded, label = _check_scene_arg(scene, resolution, defines)
    ref_stack, ref_image = load_reference(reference, label, tau) if reference is not None else (None, None)
    given = {"resolution": resolution, "grid": grid, "block": block, "step": step, "min_spp": min_spp,
             "max_spp": max_spp}
    values, sources = resolve_settings(given, ref_stack)
    resolution, grid, block, step, min_spp, max_spp = (values[k] for k in given)
    resolution, grid = _check_args(resolution, grid, block, step, min_spp, max_spp)
    check_budget_buys_a_pass(spp_budget, step)
    crit = _resolve_criterion(criterion, ref_stack, tau)
    ckpt_path = None
    if checkpoints is not None:
        ckpt_path = prepare_output_dir(checkpoints.out) / CHECKPOINT  # writable: before any pass

    variant = select_variant()
    scene_obj = scene if loaded else load_scene(scene, resolution, defines=defines)
    if loaded and sensor is None and not scene_obj.sensors():
        raise ValueError(f"{label}: the scene has no sensor (camera) to render from; add one")
    if block is not None and sources["block"] == DEFAULT:     # a frame smaller than the default block
        crop = (sensor if sensor is not None else scene_obj.sensors()[0]).film().crop_size()
        if block > min(int(crop[0]), int(crop[1])):
            block = min(int(crop[0]), int(crop[1]))
            sources["block"] = f"{DEFAULT} (the frame's short side)"
    given_objects = {k: v for k, v in (("sensor", sensor), ("integrator", integrator)) if v is not None}
    br = BlockRenderer(scene_obj, grid=grid, block=block, **given_objects)
    try:
        SizeBounds.from_env().check_frame(br.height, br.width, br.grid, block=br.block_shape)  # an XML film's own size
        gh, gw = br.grid
        values["resolution"] = [br.width, br.height]
        logger.info("%s: %s, exposure %g", label, describe_settings(values, sources), getattr(crit, "exposure", 0.0))
        if ref_stack is not None:
            if tuple(ref_stack.grid) != (gh, gw):
                raise ValueError(f"{ref_stack.path}: reference grid {list(ref_stack.grid)} differs from "
                                 f"the render's {[gh, gw]}: its thresholds are for other blocks")
            if (ref_stack.width, ref_stack.height) != (br.width, br.height):
                logger.warning("reference %s is %dx%d, the render %dx%d: thresholds compared anyway",
                               ref_stack.path, ref_stack.width, ref_stack.height, br.width, br.height)
        if ref_image is not None and ref_image.shape[:2] != (br.height, br.width):
            raise ValueError(f"the reference image is {ref_image.shape[1]}x{ref_image.shape[0]}, the render "
                             f"{br.width}x{br.height}: give a reference of the render's size")
        settings = {"scene": os.fspath(scene) if not loaded else label, "resolution": [br.width, br.height],
                    "grid": [gh, gw], "block": [br.block_h, br.block_w],
                    "exposure": float(getattr(crit, "exposure", 0.0)),
                    "step": int(step), "min_spp": int(min_spp), "max_spp": int(max_spp), "seed": int(seed),
                    "quick_spp": int(quick_spp), "quick": crit.quick_kind if crit.needs_quick else "none",
                    "criterion": crit.describe(), "variant": variant, "defines": dict(defines or {}),
                    "tau": float(tau), **({} if spp_budget is None else {"spp_budget": float(spp_budget)})}
        sizes = pass_sizes(step, max_spp)
        session = RenderSession(br, crit, settings, sizes, label=label, seed=seed, min_spp=min_spp,
                                quick_spp=quick_spp, budget=budget, ckpt_path=ckpt_path,
                                resume=checkpoints is not None and checkpoints.resume, grow=grow, t_start=t_start)
        time_limit_reached = _run_steps(session, progress, time_limit, checkpoints)
        return session.result(variant=variant or current_variant(), sources=sources, given=list(given), tau=tau,
                              defines=defines, time_limit=time_limit, time_limit_reached=time_limit_reached,
                              ref_stack=ref_stack, ref_image=ref_image, reference=reference)
    finally:
        br.close()
