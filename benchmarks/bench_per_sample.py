"""Where our uniform loop's cost per sample goes against `mi.render` (issue 43), on the CPU.

Why: `bench native` compares whole renders; this splits the gap. On one Cornell box, in
one process, interleaved runs of: one `mi.render` of all the samples; `mi.render` in passes
of `step` spp (Mitsuba's own price of a decision every `step` spp); our tracer in the same
passes (`WavefrontTracer.trace`: keyed random numbers, the handover to torch); our uniform
loop (accumulators and the loop around them). Medians, each as a ratio to the first.

    python -m benchmarks.bench_per_sample [--size 256] [--spp 256] [--step 16] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

ROWS = ("mi_render_once", "mi_render_passes", "tracer_passes", "uniform_loop")


def per_sample(size: int = 256, spp: int = 256, step: int = 16, repeats: int = 3) -> dict[str, Any]:
    """{row: median seconds} and {row: ratio to one mi.render} (module docstring)."""
    import torch

    import renderer
    from learning.data.variant import select_variant
    from noisefeat.extras import require
    from renderer.live.wavefront import WavefrontTracer

    variant = select_variant()
    mi = require("mitsuba")
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = int(size)
    scene = mi.load_dict(d)
    tracer = WavefrontTracer(scene, scene.sensors()[0], scene.integrator())
    everything = torch.ones((size, size), dtype=torch.bool)
    passes = range(spp // step)
    runs: dict[str, Callable[[], Any]] = {
        "mi_render_once": lambda: np.asarray(mi.render(scene, spp=spp, seed=1)),
        "mi_render_passes": lambda: [np.asarray(mi.render(scene, spp=step, seed=k)) for k in passes],
        "tracer_passes": lambda: [tracer.trace(everything, step, k) for k in passes],
        "uniform_loop": lambda: renderer.render(scene, criterion="uniform", max_spp=spp, step=step, min_spp=step,
                                                progress=False),
    }
    for run in runs.values():        # compile every kernel first
        run()
    walls: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(max(1, int(repeats))):
        for name, run in runs.items():
            t0 = time.perf_counter()
            run()
            walls[name].append(time.perf_counter() - t0)
    med = {k: float(np.median(v)) for k, v in walls.items()}
    return {"variant": variant, "size": size, "spp": spp, "step": step, "repeats": repeats, "median_s": med,
            "ratio": {k: med[k] / med["mi_render_once"] for k in ROWS}, "walls": walls}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--step", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    r = per_sample(a.size, a.spp, a.step, a.repeats)
    print(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
