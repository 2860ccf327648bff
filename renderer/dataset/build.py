"""`noisestop dataset build`: many scenes -> one labelled dataset, locally or on a farm."""
from __future__ import annotations

import json
import logging
import os
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from noisefeat.safeio import read_text

from ..farm import run_tasks
from .stackbuild import BuildSettings, build_stack

log = logging.getLogger(__name__)
BUILD_LOG = "build-log.jsonl"


def build_dataset(scenes: list[str], out: str | os.PathLike, settings: BuildSettings,
                  workers: int | None = None, scheduler: str | None = None,
                  progress: bool = True) -> dict[str, Any]:
    """Build every scene's stack under `out`; one task per scene. Returns a summary."""
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if not scenes:
        raise ValueError("no scenes to build")
    t0 = time.perf_counter()
    results: list[dict[str, Any]] = []
    errors: dict[str, str] = {}
    tasks = [(s, (s, str(out), settings, progress)) for s in scenes]
    for scene, r, error in run_tasks(build_stack, tasks, workers, scheduler, progress):
        if error:
            errors[scene] = error
            continue
        results.append(r)
        log.info("%s: %d levels, %d censored blocks, %.0f s", r["scene"], r["levels"], r["censored"], r["seconds"])
    summary = {"out": str(out), "wall_s": time.perf_counter() - t0,
               "scenes": sorted(results, key=lambda r: r["scene"]),
               "failed": errors, "settings": settings.to_dict(),
               "sub_images": sum(r["levels"] * r["blocks"] for r in results),
               "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
               "cpus": os.cpu_count(), "workers": workers, "scheduler": scheduler}
    append_build_log(out, summary)
    return summary


def append_build_log(out: Path, summary: dict[str, Any]) -> None:
    """One JSON line per build run in OUT/BUILD_LOG: a dataset's build time on record."""
    with open(out / BUILD_LOG, "a") as f:
        f.write(json.dumps(summary, default=str) + "\n")


def read_build_log(out: str | os.PathLike) -> list[dict[str, Any]]:
    path = Path(out) / BUILD_LOG
    if not path.is_file():
        return []
    runs = []
    for line in read_text(path, "build log").splitlines():
        try:
            runs.append(json.loads(line))
        except json.JSONDecodeError:      # a line cut short by an interrupted run
            log.warning("%s: skipped an unreadable line", path)
    return runs
