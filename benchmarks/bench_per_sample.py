"""Where our loop's cost per sample goes against `mi.render`, on the CPU.

Why: `bench native` and `bench realscenes` compare whole renders; this splits the gap. On
one scene, in one process, interleaved runs of: one `mi.render` of all the samples;
`mi.render` in passes of `step` spp (Mitsuba's own price of a launch every `step` spp);
our tracer in the same passes, one launch each (`WavefrontTracer.trace`) and `grown` passes
a launch (`WavefrontTracer.trace_jobs`: what the loop launches while no decision is due);
our uniform loop; and the default render (flip, tau 0.02) on the same frame, whose wall is
taken per sample it kept (on a scene where nothing converges it keeps them all). Medians,
each as a ratio to the first.

    python -m benchmarks.bench_per_sample [--scene cornell_box|<real-scene name>] [--size 256]
        [--spp 256] [--step 16] [--grown 8] [--repeats 3] [--json F]

``cornell_box`` is Mitsuba's ``mi.cornell_box()`` (a Gaussian filter); other names are
scenes of the real-scene suite (`benchmarks.realscenes`).
"""
from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

ROWS = ("mi_render_once", "mi_render_passes", "tracer_passes", "tracer_grown", "uniform_loop", "default_loop")


def _scene(name: str, size: int) -> Any:
    from noisefeat.extras import require

    mi = require("mitsuba")
    if name == "cornell_box":
        d = mi.cornell_box()
        d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = int(size)
        return mi.load_dict(d)
    from renderer.scenes.catalog import load_scene

    from .realscenes import scene_path
    return load_scene(scene_path(name), size)


def per_sample(scene_name: str = "cornell_box", size: int = 256, spp: int = 256, step: int = 16, grown: int = 8,
               repeats: int = 3) -> dict[str, Any]:
    """{row: median seconds} and {row: ratio to one mi.render per sample} (module docstring)."""
    import torch

    import renderer
    from learning.data.variant import select_variant
    from noisefeat.extras import require
    from renderer.live.wavefront import WavefrontTracer

    variant = select_variant()
    mi = require("mitsuba")
    scene = _scene(scene_name, size)
    tracer = WavefrontTracer(scene, scene.sensors()[0], scene.integrator())
    everything = torch.ones((tracer.height, tracer.width), dtype=torch.bool)
    passes = spp // step
    kept: dict[str, float] = {}

    def adaptive(criterion: str) -> None:
        r = renderer.render(scene, criterion=criterion, max_spp=spp, step=step, progress=False)
        kept[criterion] = float(r.report["mean_spp"])

    runs: dict[str, Callable[[], Any]] = {
        "mi_render_once": lambda: np.asarray(mi.render(scene, spp=spp, seed=1)),
        "mi_render_passes": lambda: [np.asarray(mi.render(scene, spp=step, seed=k)) for k in range(passes)],
        "tracer_passes": lambda: [tracer.trace(everything, step, k) for k in range(passes)],
        "tracer_grown": lambda: [tracer.trace_jobs([(everything, k + j) for j in range(min(grown, passes - k))], step)
                                 for k in range(0, passes, grown)],
        "uniform_loop": lambda: adaptive("uniform"),
        "default_loop": lambda: adaptive("flip"),
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
    samples = {k: float(spp) for k in ROWS} | {"uniform_loop": kept["uniform"], "default_loop": kept["flip"]}
    per = {k: med[k] / samples[k] for k in ROWS}
    return {"variant": variant, "scene": scene_name, "size": size, "spp": spp, "step": step, "grown": grown,
            "repeats": repeats, "median_s": med, "mean_spp": samples,
            "ratio": {k: per[k] / per["mi_render_once"] for k in ROWS}, "walls": walls}


def md_per_sample(r: dict[str, Any]) -> str:
    """The markdown table of one run."""
    label = {"mi_render_once": f"`mi.render(spp={r['spp']})`, one launch",
             "mi_render_passes": f"`mi.render(spp={r['step']})` {r['spp'] // r['step']} times",
             "tracer_passes": f"our tracer, a launch a pass of {r['step']} spp",
             "tracer_grown": f"our tracer, {r['grown']} passes a launch (`trace_jobs`)",
             "uniform_loop": "our uniform loop (`criterion=\"uniform\"`)",
             "default_loop": "the default render (flip, tau 0.02), per sample kept"}
    lines = [f"**{r['scene']} {r['size']}x{r['size']}, {r['spp']} spp** (variant `{r['variant']}`, medians of "
             f"{r['repeats']} interleaved runs)", "", "| what | wall | mean spp | per sample vs one `mi.render` |",
             "|---|---|---|---|"]
    for k in ROWS:
        lines.append(f"| {label[k]} | {r['median_s'][k]:.3f} s | {r['mean_spp'][k]:.0f} | {r['ratio'][k]:.3f}x |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="cornell_box")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--step", type=int, default=16)
    p.add_argument("--grown", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", default=None, help="also write the result here")
    a = p.parse_args(argv)
    r = per_sample(a.scene, a.size, a.spp, a.step, a.grown, a.repeats)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(r, f, indent=1)
    print(md_per_sample(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
