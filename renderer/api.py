"""`renderer.render`: the adaptive render as a Python call (``mi.render`` style: a scene in,
arrays out, no files). It runs `noisestop render`'s very loop in memory; resuming stays a
command-line feature (an in-memory render has no folder to resume from).
"""
from __future__ import annotations

import os
import textwrap
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputNotFound, ServerUnavailable
from .live.result import RenderResult
from .setting_kinds import API
from .settings import ROWS
from .spec import ARGUMENT

if TYPE_CHECKING:
    from learning.data.stack import Stack

    from .criteria import Criterion


def render(scene: Any, *, criterion: Criterion | str | None = None, tau: float | None = None,
           threshold: float | None = None, offset: float | None = None, quantile: float | None = None,
           model: str | os.PathLike[str] | None = None, server: str | None = None,
           exposure: float | None = None, resolution: int | tuple[int, int] | str | None = None,
           grid: Sequence[int] | None = None, block: int | None = None, tile: int | None = None,
           min_spp: int | None = None, max_spp: int | None = None, step: int | None = None,
           decide_skip: float | None = None, decide_growth: float | None = None, seed: int | None = None,
           time_limit: float | None = None, spp_budget: float | None = None, quick_spp: int | None = None,
           defines: Mapping[str, str] | None = None,
           reference: Stack | str | os.PathLike[str] | np.ndarray | None = None, progress: bool = True) -> RenderResult:
    """Render `scene` adaptively: sample each block until it looks converged, in memory.

    A scene file is loaded with the ``noisestop`` integrator registered. Bad arguments raise
    ValueError, one line naming the argument; a missing model, scene file or reference raises
    `renderer.errors.InputNotFound` and a failing verdict server `ServerUnavailable` (also
    FileNotFoundError and ConnectionError). None means not given: the scene's ``noisestop``
    integrator's property, else what the reference stack implies, else the default
    (report.json ``settings_source`` says which).

    Parameters
    ----------
    scene : mitsuba.Scene or str or os.PathLike
        An ``mi.Scene`` (``mi.load_file``, ``mi.load_dict``, ``mi.load_string``), a Mitsuba
        XML file's path or a built-in scene name (``noisestop scenes``). A scene whose
        integrator is the ``noisestop`` plugin is traced with the plugin's nested one.
{rows}
    reference : Stack or str or os.PathLike or numpy.ndarray or None
        A labelled dataset or stack directory of this scene (oracle thresholds, early-stop
        metrics, final_vs_reference), or a reference image, an EXR file or a float
        [H, W, 3] array of the render's size (final_vs_reference only).
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    RenderResult
        ``image`` float32 [H, W, 3], ``spp`` int [H, W], ``converged`` bool [H, W] and
        ``report`` (the report.json dict); ``save(dir)`` writes the files.
    """
    from .live.adaptive import run_adaptive

    register_for(scene)
    try:
        return run_adaptive(scene, criterion, tau=tau, threshold=threshold, offset=offset, quantile=quantile,
                            model=model, server=server, exposure=exposure, resolution=resolution, grid=grid,
                            block=block, tile=tile, min_spp=min_spp, max_spp=max_spp, step=step,
                            decide_skip=decide_skip, decide_growth=decide_growth, seed=seed, time_limit=time_limit,
                            spp_budget=spp_budget, quick_spp=quick_spp, defines=defines, progress=progress,
                            reference=reference, source=ARGUMENT)
    except (InputNotFound, ServerUnavailable):
        raise
    except FileNotFoundError as exc:       # a model, scene or reference that is not there
        raise InputNotFound(str(exc)) from exc
    except ConnectionError as exc:         # the verdict server
        raise ServerUnavailable(str(exc)) from exc


def register_for(scene: Any) -> None:
    """`renderer.plugin.register` before `scene` loads if it is a scene file's path (its
    integrator may be ``noisestop``); a built-in scene's name or a loaded scene needs none."""
    from .plugin import register
    from .scenes.catalog import is_builtin

    if isinstance(scene, (str, os.PathLike)) and not is_builtin(scene):
        register()


_ROWS_DOC = "\n".join(f"    {row.name} : {row.type_doc} or None\n"
                      + textwrap.fill(f"{row.help_text()}.", 92, initial_indent=" " * 8, subsequent_indent=" " * 8)
                      for row in ROWS if API in row.doors)
render.__doc__ = (render.__doc__ or "").replace("{rows}", _ROWS_DOC)
