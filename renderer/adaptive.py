"""The adaptive progressive renderer (the paper's Figure 6): sample only the noisy blocks.

Loop, one *pass* at a time (pass p adds `step` samples per pixel to every active block):

1. render the active blocks only (`BlockRenderer.render_blocks`, pass_index = p, so the
   Mitsuba seed of (block, pass) is fixed whatever happened before);
2. accumulate them (`BlockAccumulator`: exact means, even/odd half buffers);
3. once spp >= min_spp, ask the criterion about the active blocks only; a block it calls
   converged leaves the active set for good: never rendered, featured or asked again;
4. checkpoint everything (accumulator, active set, verdict history, counters, timers, pass
   index) atomically into out/checkpoint.npz (`renderer.checkpoint`: digest-checked and
   validated against the settings before a resume trusts it), every `checkpoint_every`
   seconds, at the end, at the time limit and on SIGINT/SIGTERM (`renderer.signals`):
   a pass is never half-saved.

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
import torch
from tqdm import tqdm

from learning.data.stack import Stack
from learning.names import DEFAULT_TAU
from noisefeat.bounds import SizeBounds
from noisefeat.runtime import torch_threads

from .blocks import BlockRenderer, compose
from .argcheck import check_budget_buys_a_pass, check_reference_image, check_render_args
from .budget import Budget
from .checkpoint import CHECKPOINT, load_checkpoint, save_checkpoint
from .criteria import TIMER_NAMES, Criterion, build_criterion
from .outputs import prepare_output_dir
from .passloop import PassLoop
from .report import final_vs_reference, pass_sizes, render_report
from .result import RenderResult
from .settings import DEFAULT, NOT_USED, check_spp_settings, resolve_settings
from .settings import describe as describe_settings
from .signals import DeferredStop

#: what a render cost in Mitsuba, over every attempt (report.json "render_calls"); like the
#: timings these depend on the process (a resumed run compiles its kernel again)
RENDER_COUNTERS = ("mitsuba_calls", "kernel_launches", "kernel_lanes", "kernel_compiles", "checkpoints",
                   "samples_traced")

logger = logging.getLogger(__name__)



def scene_label(scene: str | os.PathLike) -> str:
    """Directory name of a scene: the built-in name, or an XML file's stem."""
    s = os.fspath(scene)
    return Path(s).stem if s.lower().endswith(".xml") else s


# ----------------------------------------------------------------------------- the loop


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


def pass_step(loop: PassLoop, br: BlockRenderer, ids: Sequence[int], jobs: Sequence[tuple[int, int]],
              sizes: Sequence[int], seed: int, timers: dict[str, float]) -> int:
    """One launch of `jobs` ((block, pass index) pairs, pass-major: k passes of `ids`, pass j
    of size ``sizes[j]``), then the loop's step after each pass for the blocks still
    active. Returns the passes stepped (fewer than k when every block stopped early)."""
    ids_a = np.asarray(ids, np.int64)
    m, k = len(ids_a), len(sizes)
    t0 = time.perf_counter()
    images = br.render_passes(jobs, [int(sizes[j]) for j in range(k) for _ in range(m)], seed)
    timers["render_s"] += time.perf_counter() - t0
    with torch_threads(1):
        for j in range(k):                     # the passes of one launch, in order
            keep = np.flatnonzero(loop.active[ids_a])
            if not keep.size:
                return j
            rows = torch.from_numpy(j * m + keep).to(images.device)
            loop.step(ids_a[keep], [(images[rows], int(sizes[j]))])
    return k


def _resolve_criterion(criterion: Criterion | str, reference: Stack | None, tau: float) -> Criterion:
    if isinstance(criterion, Criterion):
        return criterion
    if isinstance(criterion, str):
        th = reference.thresholds if reference is not None else None
        return build_criterion(criterion, thresholds=th, tau=tau)
    raise ValueError(f"criterion must be a Criterion or one of model/variance/uniform/oracle, "
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
                    tau: float = DEFAULT_TAU, spp_budget: float | None = None) -> dict[str, Any]:
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
                          checkpoints=Checkpoints(out, resume, checkpoint_every), spp_budget=spp_budget)
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
    from .plugin import register
    register()         # a scene file whose integrator is `noisestop` loads (issue 34)
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
        n = br.n_blocks
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

        state: dict[str, Any] | None = None
        if checkpoints is not None and checkpoints.resume and ckpt_path.exists():
            state = load_checkpoint(ckpt_path, settings, sizes=sizes, grid=(gh, gw), block=br.block_shape,
                                    frame=(br.height, br.width))
            logger.info("%s: resuming after pass %d (%d active blocks)", ckpt_path, state["pass_index"],
                        int(state["active"].sum()))
        else:
            if checkpoints is not None and checkpoints.resume:
                logger.info("%s: no checkpoint, starting from the beginning", ckpt_path)
            elif ckpt_path is not None and ckpt_path.exists():
                logger.warning("%s: existing checkpoint ignored and replaced (use resume to continue it)", ckpt_path)
            state = {"pass_index": 0, "done": False, "counters": {}, "timers": {}, "quick": None}
        loop_timers = {"render_s": 0.0, "wall_s": 0.0, "setup_s": 0.0,
                       **{k: float(v) for k, v in state["timers"].items() if k in ("render_s", "wall_s", "setup_s")}}
        loop_timers["setup_s"] += time.perf_counter() - t_start  # imports, scene load, checkpoint read
        crit.reset_counters()
        quick_blocks = None
        if crit.needs_quick:
            if state["quick"] is None:
                t0 = time.perf_counter()
                state["quick"] = br.quick_image(spp=quick_spp, seed=seed, kind=crit.quick_kind)
                loop_timers["render_s"] += time.perf_counter() - t0
            quick_blocks = br.cut_blocks(state["quick"])
            crit.prepare(list(range(n)), quick_blocks)
        loop = PassLoop(crit, (gh, gw), br.block_shape, min_spp, quick_blocks, device=br.device)
        if "acc" in state:                       # resumed
            loop.restore(state)
        acc = loop.acc
        done_before = {k: int(state["counters"].pop(k, 0)) for k in RENDER_COUNTERS}   # earlier attempts
        if state["counters"]:  # resumed: continue the counts (this overrides what prepare counted)
            crit.restore_counters(state["counters"], {k: v for k, v in state["timers"].items() if k in TIMER_NAMES})
        written = {"checkpoints": 0}

        def render_counts() -> dict[str, int]:
            """What the render cost in Mitsuba calls and kernels, over every attempt."""
            now = {"mitsuba_calls": br.mitsuba_calls, "kernel_launches": br.kernel_launches,
                   "kernel_lanes": br.kernel_lanes,
                   "kernel_compiles": br.kernel_compiles, "checkpoints": written["checkpoints"],
                   "samples_traced": br.samples_traced}
            return {k: done_before[k] + now[k] for k in RENDER_COUNTERS}

        def checkpoint() -> None:
            if ckpt_path is None:            # in memory: nothing to resume from
                return
            if budget is not None and budget.prioritised_rounds:   # blocks out of step: not resumable
                return
            written["checkpoints"] += 1
            save_checkpoint(ckpt_path, snapshot())

        def snapshot() -> dict[str, Any]:
            wall = loop_timers["wall_s"] + (time.perf_counter() - t_start)
            return {**state, **loop.state(), "settings": settings,
                    "counters": {**dict(crit.counters), **render_counts()},
                    "timers": {**crit.timers, "render_s": loop_timers["render_s"], "setup_s": loop_timers["setup_s"],
                               "wall_s": wall}}

        every = checkpoints.every if checkpoints is not None else math.inf
        p = state["pass_index"]
        time_limit_reached = False
        last_saved = time.perf_counter()
        bar = tqdm(total=len(sizes), initial=p, desc=f"{label} passes", unit="pass",
                   disable=not progress, leave=False)
        stop = DeferredStop() if checkpoints is not None else None
        with stop if stop is not None else nullcontext():
            while not state["done"]:
                ids = loop.active_ids if budget is None else budget.select(loop, sizes, time.perf_counter() - t_start)
                if not ids or (budget is None and p >= len(sizes)):
                    state["done"] = True
                    checkpoint()
                    break
                if budget is None:
                    k = grown_passes(n, len(ids), len(sizes) - p, grow)
                    done_passes = pass_step(loop, br, ids, [(b, p + j) for j in range(k) for b in ids],
                                            sizes[p:p + k], seed, loop_timers)
                else:
                    done_passes = budget.run_round(loop, br, ids, sizes, seed, loop_timers)
                p += done_passes
                state["pass_index"] = p
                state["done"] = (not loop.active.any() or p >= len(sizes)) if budget is None else \
                    budget.finished(loop, sizes)
                bar.set_postfix(spp=int(loop.acc.spp_all()[ids].max()), active=int(loop.active.sum()), refresh=False)
                bar.update(done_passes)
                now = time.perf_counter()
                time_limit_reached = time_limit is not None and not state["done"] and now - t_start >= time_limit
                requested = stop is not None and stop.requested
                if state["done"] or time_limit_reached or requested or now - last_saved >= every:
                    checkpoint()
                    last_saved = time.perf_counter()
                if requested and not state["done"]:
                    bar.close()
                    raise KeyboardInterrupt(f"{stop.requested} after pass {p}: checkpoint written to {ckpt_path}, "
                                            "--resume continues")
                if time_limit_reached:
                    logger.info("%s: time limit of %gs reached after pass %d (%d blocks still active)%s",
                                label, time_limit, p, int(loop.active.sum()),
                                "; --resume continues" if ckpt_path is not None else "")
                    break
        bar.close()

        final = snapshot()
        report = render_report(label, br, settings, crit, {**state, **loop.state()}, acc, final["timers"],
                               variant or current_variant(), ref_stack)
        report["settings_source"] = {k: sources[k] for k in given if sources[k] != NOT_USED}
        if defines:
            report["defines"] = dict(defines)
        if time_limit is not None:
            report["time_limit"] = {"seconds": float(time_limit), "reached": time_limit_reached}
        if budget is not None:
            report["budget"] = budget.describe(loop, time_limit_reached)
        report["render_calls"] = render_counts()
        image, spp_px, owner = compose(acc.means(np.arange(n)).cpu().numpy(), [br.window(b) for b in range(n)],
                                       acc.spp_all(), (br.height, br.width))
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
                image, ref_img, (gh, gw), float(tau), float(settings["exposure"]), ~loop.active,
                windows=[br.window(b) for b in range(n)] if br.overlapping else None)
            if ref_stack is None:
                report["reference"] = {"image": os.fspath(reference) if isinstance(reference, (str, os.PathLike))
                                       else "array", "width": br.width, "height": br.height}
        return RenderResult(image=image, spp=spp_px, converged=(~loop.active)[owner], report=report,
                            reference=ref_img)
    finally:
        br.close()
