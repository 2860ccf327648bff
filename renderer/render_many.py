"""`noisestop render` for one scene or many: the command facade, and many scenes as one
Dask task each (`renderer.farm.executor`: local processes or a cluster)."""
from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from concurrent.futures import as_completed
from pathlib import Path
from typing import Any

from tqdm import tqdm

from .live.adaptive import adaptive_render
from .live.outputs import prepare_output_dir
from .spec import COMMAND_LINE

logger = logging.getLogger(__name__)


def _register_for(scene: str | os.PathLike) -> None:
    """Register the ``noisestop`` integrator in this process if `scene` is a file: its
    integrator may be that one (the loop cannot import the plugin; a built-in needs none)."""
    from .plugin import register
    from .scenes.catalog import is_scene_file

    if is_scene_file(scene):
        register()


def _render_task(scene: str, out: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """What one worker runs: one scene, start to finish (or resume to finish)."""
    from .farm import configure_worker_threads

    configure_worker_threads()
    _register_for(scene)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return adaptive_render(scene, out, **kwargs)


def render_many(scenes: Sequence[str | os.PathLike], out: str | os.PathLike, *,
                workers: int | None = None, scheduler: str | None = None, progress: bool = True,
                **kwargs: Any) -> dict[str, Any]:
    """`adaptive_render` for many scenes, one task per scene, into out/<scene>/.

    Runs on `renderer.farm.executor` (local Dask processes or a cluster). Each task
    resolves its own render spec and builds its own criterion. A failing scene does not
    stop the others: it is listed under ``failed``. `kwargs` are `adaptive_render`'s
    keyword arguments (the render spec's settings included).
    """
    from .farm import executor
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
    with executor(workers, scheduler) as pool:
        futures = {pool.submit(_render_task, os.fspath(s), str(root / lab), kwargs): lab
                   for s, lab in zip(scenes, labels)}
        for fut in tqdm(as_completed(futures), total=len(futures), desc="scenes", unit="scene",
                        disable=not progress):
            lab = futures[fut]
            try:
                reports[lab] = fut.result()
            except Exception as exc:  # one bad scene must not lose the others' work
                failed[lab] = f"{type(exc).__name__}: {exc}"
                logger.error("scene %s failed: %s", lab, failed[lab])
    return {"out": str(root), "wall_s": time.perf_counter() - t0,
            "scenes": dict(sorted(reports.items())), "failed": failed}


def render_command(scenes: str | Sequence[str], out: str | os.PathLike, given: dict[str, Any], *,
                   reference: str | None = None, workers: int | None = None, scheduler: str | None = None,
                   **kwargs: Any) -> dict[str, Any]:
    """What `noisestop render` runs: one scene -> its report; several -> `render_many`'s summary.

    `scenes`: a name, an XML path, or a comma-separated list; `given`: the render spec's
    settings the command line gave (None: not given), resolved per scene (its reference
    stack may imply some); `kwargs`: `adaptive_render`'s (resume).
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
        _register_for(names[0])
        return adaptive_render(names[0], out, **kwargs)
    return render_many(names, out, workers=workers, scheduler=scheduler, **kwargs)
