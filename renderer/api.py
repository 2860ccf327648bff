"""`renderer.render`: the adaptive render as a Python call, a scene in and arrays out.

Mitsuba users expect ``mi.render(scene)`` semantics: a scene object in, an image out, no
files. `render` runs the very loop of `noisestop render` (`renderer.adaptive.run_adaptive`:
same seeds, same stops, same report) in memory and returns a `RenderResult`; its
`save` writes the command line's files. Checkpoints and resuming stay command-line
features (`noisestop render --resume`, `adaptive_render(resume=True)`): an in-memory
render has no folder to resume from, and a Python caller who wants to bound a render
gives `time_limit`.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.names import DEFAULT_TAU

from .names import criterion_name
from .result import RenderResult

if TYPE_CHECKING:
    from learning.data.stack import Stack

    from .criteria import Criterion


def render(scene: Any, *, criterion: Criterion | str | None = None, tau: float | None = None,
           block: int | None = None, min_spp: int | None = None, max_spp: int | None = None,
           step: int | None = None, time_limit: float | None = None, seed: int | None = None,
           progress: bool = True,
           grid: Sequence[int] | None = None, resolution: int | tuple[int, int] | str | None = None,
           defines: Mapping[str, str] | None = None,
           reference: Stack | str | os.PathLike[str] | np.ndarray | None = None,
           model: str | os.PathLike[str] | None = None, threshold: float | None = None,
           offset: float | None = None, exposure: float | None = None, quick_spp: int = 16,
           spp_budget: float | None = None) -> RenderResult:
    """Render `scene` adaptively: sample each block until it looks converged, in memory.

    Also registers the ``noisestop`` Mitsuba integrator for the current variant (as
    `renderer.register` does). Bad arguments raise ValueError with a one-line message.

    Parameters
    ----------
    scene : mitsuba.Scene or str or os.PathLike
        An ``mi.Scene`` (``mi.load_file``, ``mi.load_dict``, ``mi.load_string``), a Mitsuba
        XML file's path or a built-in scene name (``noisestop scenes``). A scene whose
        integrator is the ``noisestop`` plugin is traced with the plugin's nested one.
    criterion : str or Criterion or None
        When a block has converged: ``flip`` (training-free, the default), ``model`` (the
        learned model), ``variance`` (Cycles' rule), ``uniform`` (never: max_spp
        everywhere) or ``oracle`` (needs a labelled reference stack); or a Criterion object.
        None: the scene's ``noisestop`` integrator's, if it has one; else ``model`` when
        `model` or `offset` is given, as on the command line; else ``flip``.
    tau : float or None
        The noise target: the virtual observer's FLIP threshold the criterion is
        calibrated for (smaller: cleaner and more samples); None: the scene's
        ``noisestop`` integrator's, else 0.02.
    block : int or None
        Block side in pixels; None: 64 (the size the criteria were calibrated on), or the
        frame's short side if that is smaller. Edge windows are moved flush with the edge.
    min_spp : int or None
        Samples per pixel before the first decision; None: 16. Decisions come at the end
        of a pass, so the first one is at the first pass that reaches min_spp: a min_spp
        that is not a multiple of `step` (or below it) is not changed, it takes effect at
        the next pass boundary (``report["min_spp"]`` keeps the value given).
    max_spp : int or None
        Most samples per pixel of any block; None: 1024.
    step : int or None
        Samples per pixel added to every active block per pass; None: 16.
    time_limit : float or None
        Seconds: the pass under way when they run out is finished and the render returns
        (``report["time_limit"]["reached"]`` says so); once the time left cannot cover every
        active block, passes go to the blocks farthest from their target; None: no limit.
    seed : int or None
        Base seed: the samples of (pixel, pass) depend only on it, so the same call gives
        the same image bit for bit; None: the scene's ``noisestop`` integrator's, else 0.
    progress : bool
        Show a progress bar on stderr.
    grid : sequence of two ints or None
        Blocks as a (rows, columns) grid dividing the frame, instead of `block`.
    resolution : int or (int, int) or str or None
        Film size for a name or XML path: N scales the long side to N keeping the aspect,
        (W, H) or "WxH" sets both, framed as Mitsuba frames that film size. Refused for an
        already-loaded ``mi.Scene`` (set its film instead).
    defines : mapping or None
        An XML file's ``<default>`` parameters, as ``mitsuba -D key=value``. XML path only.
    reference : Stack or str or os.PathLike or numpy.ndarray or None
        A labelled dataset or stack directory of this scene (oracle thresholds, early-stop
        metrics, final_vs_reference), or a reference image, an EXR file or a float
        [H, W, 3] array of the render's size (final_vs_reference only).
    model : str or os.PathLike or None
        ``criterion="model"``: a model bundle directory; None: the bundled model.
    threshold : float or None
        ``flip``: c, the FLIP between half buffers a block must reach (None: c(tau));
        ``variance``: the noise threshold (None: 0.01).
    offset : float or None
        ``model``: the decision offset (None: the model's calibrated offset at tau).
    exposure : float or None
        Display exposure in stops the criteria judge the image at; None: the scene's
        ``noisestop`` integrator's, else 0.
    quick_spp : int
        Samples of the quick image a model criterion reads (rendered once).
    spp_budget : float or None
        Samples per pixel averaged over the frame that the render may spend: passes go to
        the blocks farthest from their target, and ``report["budget"]["above_target"]``
        lists the blocks still above it when the budget ends; None: no budget.

    Returns
    -------
    RenderResult
        ``image`` float32 [H, W, 3], ``spp`` int [H, W], ``converged`` bool [H, W] and
        ``report`` (the report.json dict); ``save(dir)`` writes the files.

    Notes
    -----
    An ``mi.Scene`` whose integrator is the ``noisestop`` plugin is rendered with the
    plugin's properties for every argument left None here (criterion, tau, block,
    min_spp, max_spp, step, seed, threshold, offset, exposure, model); arguments given
    here win.
    """
    from .adaptive import run_adaptive
    from .criteria import make_criterion
    from .plugin import register, scene_plugin_settings

    register()
    own = scene_plugin_settings(scene)        # the scene's own noisestop integrator, if any
    given = {"criterion": criterion, "tau": tau, "block": block, "min_spp": min_spp, "max_spp": max_spp,
             "step": step, "seed": seed, "threshold": threshold, "offset": offset, "model": model,
             "exposure": exposure}
    for key, value in given.items():
        if value is None and key in own:
            given[key] = own[key]
    criterion, tau, block, min_spp, max_spp, step, seed, threshold, offset, model, exposure = given.values()
    criterion = criterion_name(criterion, model=model, offset=offset)
    tau = DEFAULT_TAU if tau is None else tau
    seed = 0 if seed is None else seed
    exposure = 0.0 if exposure is None else exposure
    crit = make_criterion(criterion, tau=tau, model=model, threshold=threshold, offset=offset, exposure=exposure)
    return run_adaptive(scene, crit, resolution=resolution, grid=grid, block=block, step=step, min_spp=min_spp,
                        max_spp=max_spp, seed=seed, progress=progress, reference=reference,
                        quick_spp=quick_spp, defines=defines, time_limit=time_limit, tau=tau,
                        spp_budget=spp_budget)
