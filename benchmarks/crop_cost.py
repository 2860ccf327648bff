"""The crop engine's cost: wall time of rendering some blocks alone against the full frame.

Why here, not in renderer.live.blocks: it is a measurement of the renderer, not part of it
(docs/benchmarks/speed.md, `bench crop`; `bench cost`'s selection part times every
block alone with `time_crop_renders`).
"""
from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Sequence
from typing import Any

from renderer.live.blocks import BlockRenderer

logger = logging.getLogger(__name__)


def time_crop_renders(r: BlockRenderer, groups: Sequence[Sequence[int]], spp: int, repeats: int = 3,
                      seed: int = 1) -> dict[str, Any]:
    """Wall seconds of `r` rendering the full frame and each group of blocks alone (the crop
    engine: one ``mi.render`` of each block's crop; the wavefront engine: one trace of the
    group's pixels), `spp` samples per pixel, both warm: the first call of each (which
    compiles) is timed apart, then `repeats` rounds, the full frame and every group in turn
    (interleaved: each sees the same load), medians kept. Returns ``full_s``,
    ``groups_s`` [len(groups)], and the first calls' ``first_full_s``, ``first_groups_s``."""
    def timed(run: Any) -> float:
        t0 = time.perf_counter()
        run()
        return time.perf_counter() - t0

    first_full = timed(lambda: r.render_full(spp, seed=0))
    first_groups = [timed(lambda g=g: r.render_units(list(g), spp, seed=0)) for g in groups]
    full_t: list[float] = []
    groups_t: list[list[float]] = [[] for _ in groups]
    for k in range(max(1, int(repeats))):
        full_t.append(timed(lambda k=k: r.render_full(spp, seed=seed, pass_index=k)))
        for g, out in zip(groups, groups_t):
            out.append(timed(lambda g=g, k=k: r.render_units(list(g), spp, seed=seed, pass_index=k)))
    return {"full_s": statistics.median(full_t), "groups_s": [statistics.median(t) for t in groups_t],
            "first_full_s": first_full, "first_groups_s": first_groups}


def measure_crop_cost(
    scene_name: str = "cornell",
    resolution: int = 256,
    spp: int = 64,
    repeats: int = 3,
    block_ids: Sequence[int] = (0, 5, 10, 15),
    grid: tuple[int, int] = (4, 4),
) -> dict[str, Any]:
    """Wall time of rendering a few blocks vs the full frame, both warm.

    The first render of each crop compiles its kernel; that time is reported apart
    (``compile_*_s`` = first call minus the warm median). The goal is
    ``ratio ~= len(block_ids) / n_blocks`` (a quarter for 4 of 16).
    """
    from renderer.scenes.catalog import load_scene
    from learning.data.variant import current_variant

    scene = load_scene(scene_name, resolution)
    r = BlockRenderer(scene, grid=grid)
    ids = list(block_ids)
    t = time_crop_renders(r, [ids], spp, repeats)
    full_s, blocks_s = t["full_s"], t["groups_s"][0]
    first_full, first_blocks = t["first_full_s"], t["first_groups_s"][0]
    result = {
        "variant": current_variant(),
        "scene": scene_name,
        "resolution": resolution,
        "spp": spp,
        "grid": list(r.grid),
        "blocks": ids,
        "full_s": full_s,
        "blocks_s": blocks_s,
        "ratio": blocks_s / full_s if full_s > 0 else float("nan"),
        "ideal_ratio": len(ids) / r.n_blocks,
        "compile_full_s": max(0.0, first_full - full_s),
        "compile_blocks_s": max(0.0, first_blocks - blocks_s),
        "full_mpaths_per_s": resolution * resolution * spp / full_s / 1e6 if full_s > 0 else float("nan"),
    }
    logger.info("crop cost: %s", result)
    return result
