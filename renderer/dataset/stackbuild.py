"""Build one labelled stack (dataset format v1) from a scene: levels, reference, quick images.

Level k is the cumulative mean of (k+1)*step spp, one independent `step`-sample pass per level;
the reference has its own seed stream, so its noise is independent of the levels it judges.
Mitsuba calls hold at most `max_lanes` samples. A rerun resumes from `<scene>/.build/accum.npz`
(the float64 sum, saved atomically after each level), adds missing EXTRA_QUICK images, and
relabels a complete stack whose virtual-observer labels are stale (human labels are kept).
"""
from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from learning.data.block_terms import observer_terms, poolings, stack_observer_errors
from learning.data.exr import read_exr
from learning.data.npz import read_npz
from learning.data.observer import VirtualObserver, thresholds_from_errors
from learning.data.relabel import relabel_if_stale
from learning.data.stack import read_stack
from learning.data.stack_format import EXTRA_QUICK, REFERENCE, level_name
from learning.data.stack_write import StackWriter, make_plan
from learning.data.variant import select_variant
from noisefeat.atomic import atomic_write
from noisefeat.extras import require
from noisefeat.pooling import POOLINGS

from ..live.blocks import BlockRenderer
from ..scenes.catalog import load_scene, scene_label
from ..settings import ROW

log = logging.getLogger(__name__)

BUILD_DIR = ".build"
QUICK_DESCRIPTION = "albedo aov, {spp} spp"


@dataclass(frozen=True)
class BuildSettings:
    """What a dataset build is made of; stored in meta.json so resumes can check it."""

    resolution: int = 256
    step: int = 16
    levels: int = 40
    reference_spp: int = 4096
    grid: tuple[int, int] = (4, 4)
    quick_spp: int = 16
    seed: int = 0
    tau: float = ROW["tau"].default        # the labels' observer: the render's noise target
    ppd: float = 67.0
    max_lanes: int = 1 << 22
    contact_sheet: bool = True
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("resolution", "step", "levels", "reference_spp", "quick_spp", "max_lanes"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if self.reference_spp <= self.step * self.levels:
            log.warning("reference_spp %d is not above the last level (%d spp): labels will be poor",
                        self.reference_spp, self.step * self.levels)

    @property
    def spp(self) -> list[int]:
        return [self.step * (k + 1) for k in range(self.levels)]

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "grid": list(self.grid)}


def _calls(br: BlockRenderer, spp: int, max_lanes: int) -> tuple[int, int]:
    """(samples per Mitsuba call, number of calls) for `spp` full-frame samples."""
    chunk = max(1, min(spp, max_lanes // (br.width * br.height)))
    return chunk, -(-spp // chunk)


def render_mean(br: BlockRenderer, spp: int, seed: int, first_pass: int, max_lanes: int) -> np.ndarray:
    """Mean (float64) of `spp` full-frame samples in calls of <= max_lanes samples, call i at
    pass index first_pass + i."""
    chunk, calls = _calls(br, spp, max_lanes)
    total = np.zeros((br.height, br.width, 3), np.float64)
    for i in range(calls):
        n = min(chunk, spp - i * chunk)
        total += br.render_full(n, seed, pass_index=first_pass + i).astype(np.float64) * n
    return total / spp


def _save_checkpoint(path: Path, level: int, total: np.ndarray) -> None:
    atomic_write(path, lambda tmp: np.savez(tmp, level=np.int64(level), sum=total))


def _load_checkpoint(path: Path, shape: tuple[int, ...]) -> tuple[int, np.ndarray] | None:
    if not path.exists():
        return None
    try:
        z = read_npz(path, kind="npz")
        level, total = int(z["level"]), np.array(z["sum"])
    except Exception as exc:  # a damaged checkpoint costs a re-render, not a wrong stack
        log.warning("%s: unreadable checkpoint (%s); levels will be re-rendered", path, exc)
        return None
    if total.shape != shape:
        log.warning("%s: checkpoint shape %s != %s; ignored", path, total.shape, shape)
        return None
    return level, total


def build_stack(scene: str, out_root: str | os.PathLike, settings: BuildSettings,
                progress: bool = True) -> dict[str, Any]:
    """Render and label one stack under out_root/<scene>; resumes an interrupted build."""
    t_start = time.perf_counter()
    variant = select_variant()
    mi = require("mitsuba")

    name = scene_label(scene)
    out = Path(out_root) / name
    br = BlockRenderer(load_scene(scene, resolution=settings.resolution), grid=tuple(settings.grid))
    plan = make_plan(scene=name, width=br.width, height=br.height, spp=settings.spp,
                     reference_spp=settings.reference_spp,
                     quick=QUICK_DESCRIPTION.format(spp=settings.quick_spp),
                     renderer=f"mitsuba {mi.__version__} {variant} path", grid=settings.grid,
                     build={k: v for k, v in settings.to_dict().items() if k != "contact_sheet"})
    writer = StackWriter(out, plan)
    for kind in EXTRA_QUICK:     # cheap, so added to stacks built before they existed too
        if not (out / EXTRA_QUICK[kind]).exists():
            writer.write_extra_quick(kind, br.quick_image(spp=settings.quick_spp, seed=settings.seed, kind=kind))
    observer = VirtualObserver(tau=settings.tau, ppd=settings.ppd)
    if writer.is_complete:
        _, relabelled = relabel_if_stale(read_stack(out), observer.pooling)
        log.info("%s: already built%s", out, ", relabelled by the current observer" if relabelled else "")
        return _summary(out, variant, time.perf_counter() - t_start, resumed=True, already_built=True)

    level_seed, reference_seed = 2 * settings.seed, 2 * settings.seed + 1
    if not writer.has_quick():
        writer.write_quick(br.quick_image(spp=settings.quick_spp, seed=settings.seed))
    if not writer.has_reference():
        ref = render_mean(br, settings.reference_spp, reference_seed, 0, settings.max_lanes)
        writer.write_reference(ref.astype(np.float32))

    build_dir = out / BUILD_DIR
    build_dir.mkdir(exist_ok=True)
    ckpt = build_dir / "accum.npz"
    state = _load_checkpoint(ckpt, (br.height, br.width, 3))
    done, total = state if state is not None else (0, np.zeros((br.height, br.width, 3), np.float64))
    # pass indices fixed by the level number: a resumed build renders an uninterrupted one's samples
    _, passes_per_level = _calls(br, settings.step, settings.max_lanes)
    for k in tqdm(range(done, settings.levels), total=settings.levels, initial=done, desc=f"{name} levels",
                  unit="lvl", disable=not progress, leave=False):
        mean = render_mean(br, settings.step, level_seed, k * passes_per_level, settings.max_lanes)
        total += mean * settings.step
        spp = settings.spp[k]
        writer.write_level(spp, (total / spp).astype(np.float32))
        _save_checkpoint(ckpt, k + 1, total)

    levels = (read_exr(out / level_name(s)) for s in settings.spp)   # one at a time
    terms = observer_terms(read_exr(out / REFERENCE), levels, settings.grid, observer.ppd, observer.exposure)
    thresholds = thresholds_from_errors(poolings(terms)[POOLINGS.index(observer.pooling)], settings.spp, observer.tau)
    stack = writer.finish(thresholds, observer.labeler)
    stack_observer_errors(stack, observer.ppd, observer.exposure, computed=terms)   # cached for relabelling
    stack, _ = relabel_if_stale(stack, observer.pooling)                            # and the tile truth
    shutil.rmtree(build_dir, ignore_errors=True)
    if settings.contact_sheet:
        from .contact import contact_sheet
        contact_sheet(stack, Path(out_root) / "contact" / f"{name}.png")
    return _summary(out, variant, time.perf_counter() - t_start, resumed=done > 0)


def _summary(out: Path, variant: str, seconds: float, resumed: bool,
             already_built: bool = False) -> dict[str, Any]:
    stack = read_stack(out)
    th = stack.thresholds or []
    return {"scene": stack.scene, "path": str(out), "variant": variant, "seconds": seconds,
            "levels": stack.n_levels, "blocks": stack.n_blocks, "resumed": resumed,
            "already_built": already_built,
            "thresholds": th, "censored": sum(t is None for t in th)}
