"""`noisestop render` for one scene or many (one Dask task each, `renderer.farm`)."""
from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import Any

from .live.adaptive import adaptive_render
from .live.outputs import prepare_output_dir
from .spec import COMMAND_LINE


def _render_one(scene: str | os.PathLike, out: str | os.PathLike, kwargs: dict[str, Any]) -> dict[str, Any]:
    """`adaptive_render`, with the ``noisestop`` integrator registered first if `scene` is a
    file (its integrator may be that one; the loop cannot import the plugin)."""
    from .api import register_for

    register_for(scene)
    return adaptive_render(scene, out, **kwargs)


def render_many(scenes: Sequence[str | os.PathLike], out: str | os.PathLike, *,
                workers: int | None = None, scheduler: str | None = None, progress: bool = True,
                **kwargs: Any) -> dict[str, Any]:
    """`adaptive_render` (`kwargs`: its keyword arguments) for many scenes into out/<scene>/,
    one task per scene, each resolving its own spec. A failing scene is listed under ``failed``."""
    from .farm import run_tasks
    from .scenes.catalog import scene_label

    if not scenes:
        raise ValueError("no scenes to render")
    labels = [scene_label(s) for s in scenes]
    dupes = sorted({x for x in labels if labels.count(x) > 1})
    if dupes:
        raise ValueError(f"scenes would share output directories: {', '.join(dupes)}")
    root = prepare_output_dir(out).resolve()
    t0 = time.perf_counter()
    reports: dict[str, Any] = {}
    failed: dict[str, str] = {}
    kwargs = {**kwargs, "progress": False}
    tasks = [(lab, (os.fspath(s), str(root / lab), kwargs)) for s, lab in zip(scenes, labels)]
    for lab, report, error in run_tasks(_render_one, tasks, workers, scheduler, progress):
        if error:
            failed[lab] = error
        else:
            reports[lab] = report
    return {"out": str(root), "wall_s": time.perf_counter() - t0,
            "scenes": dict(sorted(reports.items())), "failed": failed}


def render_command(scenes: str | Sequence[str], out: str | os.PathLike, given: dict[str, Any], *,
                   reference: str | None = None, workers: int | None = None, scheduler: str | None = None,
                   **kwargs: Any) -> dict[str, Any]:
    """What `noisestop render` runs: one scene -> its report; several -> `render_many`'s summary.

    `scenes`: a name, an XML path, or a comma-separated list; `given`: the settings the
    command line gave (None: not given), resolved per scene; `kwargs`: `adaptive_render`'s.
    """
    names = [s.strip() for s in scenes.split(",") if s.strip()] if isinstance(scenes, str) else list(scenes)
    if not names:
        raise ValueError("no scene given")
    prepare_output_dir(out)                 # a bad --out fails before any model or scene is loaded
    if len(names) > 1 and reference is not None and str(reference).lower().endswith(".exr"):
        raise ValueError("a reference image is one scene's: render one scene with it (or give a dataset "
                         "directory holding every scene)")
    kwargs = {**given, **kwargs, "reference": reference, "source": COMMAND_LINE}
    if len(names) == 1:
        return _render_one(names[0], out, kwargs)
    return render_many(names, out, workers=workers, scheduler=scheduler, **kwargs)
