"""The adaptive progressive renderer (the paper's Figure 6): sample only the noisy blocks.

`run_adaptive` is the loop, in memory: it resolves the render spec (`renderer.spec`: every
setting defaulted and checked there, once), builds the criterion (`make_criterion`), loads
the scene (a built-in name, an XML path or an already-loaded ``mi.Scene``), advances a
`renderer.live.session.RenderSession` launch by launch until it is done (`_run_session`; the
loop's words and a round: `renderer.live.passloop`) and returns a `RenderResult`. It stops when
no unit is active or max_spp is reached.

Checkpoints are taken only when it is given a `Checkpoints` (the command line's resumable
render, `adaptive_render`): the whole state (accumulator, active set, verdict history,
the ledger's counters and timers, history rows, quick image), atomically into
out/checkpoint.npz (`renderer.live.checkpoint`: digest-checked and validated against the
settings before a resume trusts it), every `checkpoint_every` seconds, at the end (unless
the render ended within its first period), at the time limit and on SIGINT/SIGTERM
(`renderer.live.signals`), between launches: a launch is never half-saved. Because samples depend
only on (seed, pixel, pass), ``resume=True`` after a crash gives the very image and report
(timings aside) of an uninterrupted run. A render with checkpoints removes the results an
earlier render left in its folder once it is under way (`_clear_previous`), so a killed one
never leaves them beside its own checkpoint. `renderer.render` and the ``noisestop`` Mitsuba
plugin run without checkpoints.
"""
from __future__ import annotations

import logging
import math
import os
import time
from contextlib import nullcontext
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learning.data.dataset_dir import find_stack
from learning.data.stack import Stack
from noisefeat.safeio import check_regular

from ..spec import ARGUMENT, file_load_settings, fit_frame, resolve
from .blocks import BlockRenderer
from .checkpoint import CHECKPOINT
from .outputs import clear_results, prepare_output_dir
from .report import render_result
from .result import RenderResult
from .session import RenderSession, run_settings
from .signals import DeferredStop

logger = logging.getLogger(__name__)



# ----------------------------------------------------------------------------- the loop


def _run_session(session: RenderSession, progress: bool, time_limit: float | None,
                 checkpoints: Checkpoints | None) -> bool:
    """Advance the session launch by launch until it is done, checkpointing on time, at the
    end, at the time limit and on a signal (the first SIGINT/SIGTERM finishes the launch,
    checkpoints and raises KeyboardInterrupt). A render that ends within its first period writes none (a
    1024x1024 checkpoint costs about half a second; resuming a render that short is
    rendering it again). Returns whether the time limit ended the render."""
    every = session.spec.checkpoint_every if checkpoints is not None else math.inf
    last_saved = time.perf_counter()
    bar = tqdm(total=len(session.loop.schedule), initial=session.rows, desc=f"{session.label} passes", unit="pass",
               disable=not progress, leave=False)
    stop = DeferredStop() if checkpoints is not None else None
    with stop if stop is not None else nullcontext(), bar:
        while not session.done:
            added = session.advance()
            bar.set_postfix(active=int(session.loop.active.sum()), refresh=False)
            bar.update(added)
            now = time.perf_counter()
            reached = time_limit is not None and not session.done and now - session.t_start >= time_limit
            requested = stop is not None and stop.requested
            if session.done and session.ledger.counters["checkpoints"] == 0 and now - session.t_start < every:
                session.drop_checkpoint()     # shorter than the period: nothing worth resuming (issue 43)
            elif session.done or reached or requested or now - last_saved >= every:
                session.checkpoint()
                last_saved = time.perf_counter()
            if requested and not session.done:
                raise KeyboardInterrupt(f"{stop.requested} after pass {session.rows}: checkpoint written to "
                                        f"{session.ckpt_path}, --resume continues")
            if reached:
                logger.info("%s: time limit of %gs reached after pass %d (%d units still active)%s",
                            session.label, time_limit, session.rows, int(session.loop.active.sum()),
                            "; --resume continues" if session.ckpt_path is not None else "")
                return True
    return False


@dataclass(frozen=True)
class Checkpoints:
    """Where and how often the loop checkpoints: the command line's resumable render.

    `out`: the output folder (checked writable before the scene is loaded; the checkpoint
    is out/checkpoint.npz); `resume`: continue from it if it exists. How often: the render
    spec's `checkpoint_every`. With checkpoints the first SIGINT/SIGTERM finishes the pass
    and checkpoints before stopping (`renderer.live.signals`).
    """

    out: str | os.PathLike[str]
    resume: bool = False


def is_scene_object(scene: Any) -> bool:
    """Whether `scene` is an already-loaded ``mi.Scene`` (without importing Mitsuba for a name)."""
    if isinstance(scene, (str, os.PathLike)):
        return False
    from noisefeat.extras import require

    return isinstance(scene, require("mitsuba").Scene)


def is_builtin(scene: str | os.PathLike) -> bool:
    """Whether `scene` names a built-in scene (the library's or a procedural one), not a file."""
    from ..scenes.procedural import procedural_seed
    from ..scenes.catalog import SCENES

    name = os.fspath(scene)
    return name in SCENES or procedural_seed(name) is not None


def scene_plugin_settings(scene: Any) -> dict[str, Any]:
    """The properties set on a loaded scene's ``noisestop`` integrator ({} for a scene with
    another integrator, or none): what every door honours under the settings it is given.
    Known by duck type (its `property_error`, as `renderer.live.blocks` knows it): importing
    `renderer.plugin` here would close an import circle."""
    integrator = scene.integrator() if hasattr(scene, "integrator") else None     # a stand-in scene: none
    if not hasattr(integrator, "property_error") or not hasattr(integrator, "settings"):
        return {}
    integrator.check()            # a bad property: its one line, here
    return dict(integrator.settings)


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
        from ..scenes.catalog import scene_label
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


def _clear_previous(out: Path, resumed: bool) -> None:
    """Remove the results an earlier render left in `out`, once this one is under way (its
    scene loaded, its checkpoint accepted: a refused resume leaves the folder as it was).

    Why: `clear_results`. On a resume the results go too: results are written only when a
    render ends, so those beside an unfinished checkpoint are an earlier render's, and those
    beside a finished one are this render's own, written again at once. The checkpoint
    itself is the session's: a fresh render replaces it at its first one."""
    removed = clear_results(out)
    if removed:
        logger.info("%s: removed the previous render's %s (%s)", out, ", ".join(removed),
                    "this render writes its own when it ends" if not resumed else "the resumed render writes them")


def load_reference(reference: Stack | str | os.PathLike[str] | np.ndarray,
                   label: str) -> tuple[Stack | None, np.ndarray | None]:
    """(stack, None) for a stack or dataset directory (not yet labelled: the observer's tau
    is the spec's); (None, image) for a reference image: an EXR file or a float [H, W, 3]
    array. An image gives the final-vs-reference check only: it has no per-level errors,
    so no oracle thresholds."""

    img = None
    if isinstance(reference, np.ndarray):
        img = np.asarray(reference, np.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"a reference image must be float [H, W, 3] linear RGB, got shape {img.shape}")
    elif isinstance(reference, (str, os.PathLike)) and (os.fspath(reference).lower().endswith(".exr")
                                                        or (os.path.exists(reference) and not os.path.isdir(reference))):
        from learning.data.exr import read_exr

        if not os.path.lexists(reference):
            raise FileNotFoundError(f"{os.fspath(reference)}: reference image not found")
        check_regular(reference, "reference image")     # a device, a FIFO, a folder: one line saying which
        img = read_exr(reference)
    if img is None:
        return find_stack(reference, label), None
    finite = np.isfinite(img)
    if not finite.all():       # every figure would be NaN
        raise ValueError(f"the reference image has {int(finite.size - np.count_nonzero(finite))} non-finite "
                         f"value(s) (NaN/Inf) of {img.size}: a reference must be finite")
    return None, img


def adaptive_render(scene: str | os.PathLike, out: str | os.PathLike, criterion: Any = None, *,
                    resume: bool = False, **kwargs: Any) -> dict[str, Any]:
    """Render `scene` adaptively into `out`; return the report (also out/report.json).

    The command line's render: `run_adaptive` with checkpoints in `out` (`resume`:
    continue from them; the setting `checkpoint_every`: seconds between them, 0: after
    every pass), then `RenderResult.save(out)`. wall_s in the report runs from the call to the end of
    the last pass (writing the output files is not in it); resumed runs add up the time of
    every attempt. `kwargs`: `run_adaptive`'s (the render spec's settings, `reference`,
    `progress`, `source`).
    """
    result = run_adaptive(scene, criterion, checkpoints=Checkpoints(out, resume), **kwargs)
    result.save(out)
    report = result.report
    logger.info("%s: %d passes, saved %.1f%% vs uniform, %.2f s", report["scene"], report["passes"],
                100 * report["saved_vs_uniform"], report["wall_s"])
    return report


def run_adaptive(scene: Any, criterion: Any = None, *, progress: bool = True,
                 reference: Stack | str | os.PathLike | np.ndarray | None = None,
                 checkpoints: Checkpoints | None = None, sensor: Any = None, integrator: Any = None,
                 grow: bool = True, source: str = ARGUMENT, plugin: Mapping[str, Any] | None = None,
                 **settings: Any) -> RenderResult:
    """The adaptive loop, in memory (see the module docstring).

    `criterion` and `settings`: the render spec's rows (`renderer.spec.ROWS`; None: not
    given), given by `source` ("argument", "command line" or "scene plugin"); `plugin`: a
    scene's ``noisestop`` integrator's properties, under them (None: the scene's own, of a
    loaded ``mi.Scene``, or of a scene file once it is loaded). `reference`: a labelled
    stack or dataset directory of this scene (its grid and levels become the defaults;
    early-stop metrics, oracle thresholds, final_vs_reference), or a reference image (EXR
    path or float [H, W, 3] array: final_vs_reference only). `scene`: a built-in name, an
    XML path or a loaded ``mi.Scene`` (then `resolution` and `defines` are refused).
    `sensor` / `integrator`: render from this sensor with this integrator instead of the
    scene's first sensor and own integrator (the plugin passes its nested one).
    `checkpoints`: None renders without any file. `grow`: trace several passes per launch
    as units stop (`renderer.live.launches.grown_passes`; same result, fewer launches).
    """
    from learning.data.relabel import observed
    from learning.data.variant import current_variant, select_variant

    from ..criteria import make_criterion
    from ..scenes.catalog import load_scene

    t_start = time.perf_counter()
    loaded, label = _check_scene_arg(scene, settings.get("resolution"), settings.get("defines"))
    ref_stack, ref_image = load_reference(reference, label) if reference is not None else (None, None)
    given = {"criterion": criterion, **settings}
    from_file = not loaded and not is_builtin(scene)
    if from_file:      # its noisestop integrator's settings are known once it is loaded: resolved then
        resolution, defines = file_load_settings(given, ref_stack)
    else:
        if loaded and plugin is None:
            plugin = scene_plugin_settings(scene)
        spec = resolve(given, source=source, plugin=plugin, reference=ref_stack)
        resolution, defines = spec.resolution, spec.defines
    ckpt_path = None
    if checkpoints is not None:
        ckpt_path = prepare_output_dir(checkpoints.out) / CHECKPOINT  # writable: before any pass

    variant = select_variant()
    scene_obj = scene if loaded else load_scene(scene, resolution, defines=defines)
    if from_file:      # given > the file's noisestop integrator > reference > default, as for an mi.Scene
        spec = resolve(given, source=source, plugin={**scene_plugin_settings(scene_obj), **(plugin or {})},
                       reference=ref_stack)
    if ref_stack is not None:
        ref_stack = observed(ref_stack, spec.tau)
    if loaded and sensor is None and not scene_obj.sensors():
        raise ValueError(f"{label}: the scene has no sensor (camera) to render from; add one")
    crop = (sensor if sensor is not None else scene_obj.sensors()[0]).film().crop_size()
    spec = fit_frame(spec, int(crop[0]), int(crop[1]))      # the frame as rendered, within the bounds
    given_objects = {k: v for k, v in (("sensor", sensor), ("integrator", integrator)) if v is not None}
    br = BlockRenderer(scene_obj, grid=spec.grid, block=spec.block, tile=spec.tile, **given_objects)
    try:
        crit = make_criterion(spec, None if ref_stack is None else ref_stack.thresholds)   # knows its grain now
        logger.info("%s: %s", label, spec.describe())
        if ref_stack is not None:
            if tuple(ref_stack.grid) != tuple(br.grid):
                raise ValueError(f"{ref_stack.path}: reference grid {list(ref_stack.grid)} differs from "
                                 f"the render's {list(br.grid)}: its thresholds are for other blocks")
            if (ref_stack.width, ref_stack.height) != (br.width, br.height):
                logger.warning("reference %s is %dx%d, the render %dx%d: thresholds compared anyway",
                               ref_stack.path, ref_stack.width, ref_stack.height, br.width, br.height)
        if ref_image is not None and ref_image.shape[:2] != (br.height, br.width):
            raise ValueError(f"the reference image is {ref_image.shape[1]}x{ref_image.shape[0]}, the render "
                             f"{br.width}x{br.height}: give a reference of the render's size")
        settings_run = run_settings(spec, br, crit, variant or current_variant(),
                                    os.fspath(scene) if not loaded else label)
        session = RenderSession(br, crit, spec, settings_run, label=label, ckpt_path=ckpt_path,
                                resume=checkpoints is not None and checkpoints.resume, grow=grow, t_start=t_start)
        if ckpt_path is not None:        # the folder's earlier results go before this render's first pass
            _clear_previous(ckpt_path.parent, resumed="acc" in session.state)
        time_limit_reached = _run_session(session, progress, spec.time_limit, checkpoints)
        return render_result(session, time_limit_reached=time_limit_reached, ref_stack=ref_stack,
                             ref_image=ref_image, reference=reference)
    finally:
        br.close()
