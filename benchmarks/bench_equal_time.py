"""`noisestop bench equaltime`: the default render against `mi.render` at equal wall time, to
max 4096 spp (on the CPU at 256x256; on a GPU at 1024x1024).

What a Mitsuba user asks is "do I get a better picture in the same time, and how much
sooner do I get `mi.render`'s picture". For each scene (studio_preview, Mitsuba's Cornell
box, spot_stage), warm, one run of each:

* the default adaptive render (`renderer.render`, every setting at its default but max spp)
  to max spp: its wall time A, mean spp and final frame;
* `mi.render` at max spp (wall M), and at the spp it traces in A and in 2A (its own rate
  from the max-spp run);
* each final frame judged against the scene's reference by DESIGN's observer: blocks (64
  px) above tau, the worst and mean block, 16-px tiles above tau.

Time to `mi.render`'s quality (its blocks above tau at max spp) is A / M when
the adaptive frame ends with no more blocks above tau than `mi.render`'s at max spp (an upper
bound: the adaptive render may have got there before its end), else "not reached"; the
worst blocks are shown beside it (an adaptive render stops a block once it is below tau, so
its worst block sits just under tau where `mi.render`'s oversampled blocks sit lower). `make run`'s goal (uniform
needs at least twice adaptive's time to match its blocks above tau and worst block) is the
showcase's own settings, adaptive against our uniform loop given 2A (`--time-limit`), as
`make run` compares them at A.

References: the shipped ones (8192 spp, a seed apart) where the scene has one, else
`mi.render` at `ref_spp` (seed apart), kept in `ref_dir` for the next run.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from .bench_native import Case, block_errors, load_case_scene, mi_render, rendered_reference

log = logging.getLogger(__name__)

SCENES = ("studio_preview", "cornell_box", "spot_stage")
#: the film side per device kind
SIZE = {"cpu": 256, "cuda": 1024}
#: BENCHMARKS' marked section per device kind
SECTION = {"cpu": "equaltime", "cuda": "equaltime_gpu"}


def kind_of(variant: str) -> str:
    """'cuda' for a CUDA variant, else 'cpu'."""
    return "cuda" if variant.startswith("cuda") else "cpu"


def tile_errors(image: np.ndarray, reference: np.ndarray, tau: float) -> dict[tuple[int, int, int, int], float]:
    """The observer's error (its tile mean FLIP) of each tile of `image` against `reference`,
    by window (x, y, w, h): the tiles are `noisefeat.pooling.tile_windows`', the rule the
    renderer cuts its units by, so a render's tiles are looked up by their windows."""
    from noisefeat.pooling import tile_windows
    from renderer.live.report import final_vs_reference

    windows = tile_windows(*image.shape[:2])
    errors = final_vs_reference(image, reference, (1, 1), tau, windows=windows)["errors"]
    return dict(zip(windows, errors))


def judged(image: np.ndarray, reference: np.ndarray, tau: float, stopped: list[bool] | None = None,
           tiles: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The observer's figures of one final frame (`bench_native.block_errors`), tiles added;
    with the render's `tiles` (report.json's), the tiles above tau that its criterion stopped
    (the others ran to max spp), and those of them near black (reference mean under 1e-3)."""
    e = tile_errors(image, reference, tau)
    out = {**block_errors(image, reference, tau, stopped), "tiles_above_tau": sum(x > tau for x in e.values())}
    if tiles is not None:
        above = [t for t in tiles if t["converged"] and e.get(tuple(t["window"]), 0.0) > tau]
        dark = [t for t in above if reference[t["window"][1]:t["window"][1] + t["window"][3],
                                              t["window"][0]:t["window"][0] + t["window"][2]].mean() < 1e-3]
        out.update(tiles_stopped_above_tau=len(above), dark_tiles_stopped_above_tau=len(dark))
    return out


def reference_for(scene_name: str, scene: Any, size: int, ref_spp: int, ref_dir: Path) -> tuple[np.ndarray, str]:
    """The shipped reference when it matches the film, else `mi.render` at `ref_spp`
    (`bench_native.rendered_reference`), kept in `ref_dir`."""
    from examples.showcase import shipped_reference

    ref = shipped_reference(scene_name)
    if ref is not None and ref.shape[:2] == (size, size):
        return ref.astype(np.float32), "shipped (8192 spp)"
    return rendered_reference(scene, ref_spp, keep=ref_dir / f"{scene_name}_{size}_{ref_spp}.exr")


def adaptive(scene: Any, max_spp: int, **settings: Any) -> dict[str, Any]:
    """The default render to `max_spp` (`renderer.render`), as a user times the call."""
    import renderer

    t0 = time.perf_counter()
    r = renderer.render(scene, max_spp=max_spp, progress=False, **settings)
    wall = time.perf_counter() - t0
    return {"wall_s": wall, "mean_spp": float(r.report["mean_spp"]), "image": np.asarray(r.image, np.float32),
            "stopped": [bool(b["converged"]) for b in r.report["blocks"]], "tiles": r.report.get("tiles"),
            "decisions_s": float(r.report["timing"].get("decisions_s", 0.0))}


def measure_scene(name: str, size: int, max_spp: int, tau: float, ref_spp: int, ref_dir: Path) -> dict[str, Any]:
    """Every row of one scene (the module docstring)."""
    scene = load_case_scene(Case(name, size, max_spp, ref_spp, max_spp))
    mi_render(scene, 16, seed=99)                     # warm: both kernels compiled
    adaptive(scene, 32, tau=tau)
    ref, source = reference_for(name, scene, size, ref_spp, ref_dir)
    a = adaptive(scene, max_spp, tau=tau)                  # judged at the tau it stops at
    img_m, t_m = mi_render(scene, max_spp, seed=1)
    per_spp = t_m / max_spp
    rows = {"adaptive": {"wall_s": a["wall_s"], "mean_spp": a["mean_spp"], "decisions_s": a["decisions_s"],
                         **judged(a["image"], ref, tau, a["stopped"], a["tiles"])},
            "mi_render_max": {"wall_s": t_m, "spp": max_spp, **judged(img_m, ref, tau)}}
    for k in (1, 2):
        spp = max(1, int(round(k * a["wall_s"] / per_spp)))
        img, t = mi_render(scene, spp, seed=1 + k)
        rows[f"mi_render_{k}x"] = {"wall_s": t, "spp": spp, **judged(img, ref, tau)}
    ad, mx = rows["adaptive"], rows["mi_render_max"]
    reached = ad["above_tau"] <= mx["above_tau"]
    return {"scene": name, "size": size, "max_spp": max_spp, "tau": tau, "reference": source, "rows": rows,
            "time_to_mi_quality": ad["wall_s"] / t_m if reached else None}


def measure_make_run(tau: float, **overrides: Any) -> dict[str, Any]:
    """`make run`'s settings (`overrides` on top: a test's shorter render): adaptive against
    our uniform loop given its time and twice it."""
    from renderer.live.adaptive import run_adaptive
    from renderer.scenes.catalog import load_scene
    from examples.showcase import SCENE, SETTINGS, shipped_reference
    from renderer.settings import DEFAULT_CRITERION

    settings = {**SETTINGS, **overrides}
    scene = load_scene(SCENE, settings["resolution"])
    opts = {k: v for k, v in settings.items() if k != "resolution"}
    run_adaptive(scene, DEFAULT_CRITERION, progress=False, tau=tau, **{**opts, "max_spp": 64})   # warm
    ref = shipped_reference(SCENE).astype(np.float32)
    out: dict[str, Any] = {"scene": SCENE, "settings": settings, "tau": tau}
    t0 = time.perf_counter()
    a = run_adaptive(scene, DEFAULT_CRITERION, progress=False, tau=tau, **opts)
    wall = time.perf_counter() - t0
    out["adaptive"] = {"wall_s": wall, "mean_spp": float(a.report["mean_spp"]),
                       **judged(np.asarray(a.image, np.float32), ref, tau)}
    for k in (1, 2):
        t0 = time.perf_counter()
        u = run_adaptive(scene, "uniform", progress=False, tau=tau, time_limit=k * wall, **opts)
        out[f"uniform_{k}x"] = {"wall_s": time.perf_counter() - t0, "mean_spp": float(u.report["mean_spp"]),
                                **judged(np.asarray(u.image, np.float32), ref, tau)}
    ad, u2 = out["adaptive"], out["uniform_2x"]
    out["uniform_2x_matches"] = u2["above_tau"] <= ad["above_tau"] and u2["worst"] <= ad["worst"]
    return out


def bench_equal_time(scenes: tuple[str, ...] = SCENES, size: int | None = None, max_spp: int = 4096,
                     tau: float | None = None, ref_spp: int = 8192, ref_dir: str | Path = "out/bench/references",
                     make_run: bool = True, on_scene: Any = None) -> dict[str, Any]:
    """Every scene (`measure_scene`), then `make run`'s comparison; `on_scene(result)` after
    each, so a run cut short keeps what it measured."""
    from learning.data.variant import select_variant
    from learning.names import DEFAULT_TAU

    from .bench_native import device_name

    variant = select_variant()
    kind = kind_of(variant)
    tau = tau or DEFAULT_TAU
    out: dict[str, Any] = {"variant": variant, "device": device_name(kind), "tau": tau, "scenes": []}
    for name in scenes:
        log.info("bench equaltime: %s", name)
        out["scenes"].append(measure_scene(name, size or SIZE[kind], max_spp, tau, ref_spp, Path(ref_dir)))
        if on_scene is not None:
            on_scene(out)
    if make_run:
        log.info("bench equaltime: make run's settings")
        out["make_run"] = measure_make_run(tau)
        if on_scene is not None:
            on_scene(out)
    return out


def _row(label: str, r: dict[str, Any]) -> str:
    spp = f"{r['mean_spp']:.0f} (mean)" if "mean_spp" in r else f"{r['spp']}"
    return (f"| {label} | {r['wall_s']:.1f} s | {spp} | {r['above_tau']} of {r['blocks']} | {r['worst']:.4f} | "
            f"{r['mean']:.4f} | {r['tiles_above_tau']} |")


def md_equal_time(r: dict[str, Any]) -> str:
    """A table per scene, a verdict line per goal."""
    head = ["| run | wall | spp | blocks above tau | worst block | mean block | 16-px tiles above tau |",
            "|---|---|---|---|---|---|---|"]
    lines = [f"Device: **{r['device']}**, variant `{r['variant']}`, tau {r['tau']}. One warm run of each; "
             "errors: DESIGN's observer (largest 16x16-tile FLIP per 64-px block) against the reference.", ""]
    for s in r["scenes"]:
        rows = s["rows"]
        a, m = rows["adaptive"], rows["mi_render_max"]
        lines += [f"**{s['scene']} {s['size']}x{s['size']}**, max {s['max_spp']} spp, default settings, reference: "
                  f"{s['reference']}.", "", *head,
                  _row("adaptive (default)", a), _row(f"`mi.render` {s['max_spp']} spp", m),
                  _row("`mi.render` at adaptive's wall time", rows["mi_render_1x"]),
                  _row("`mi.render` at twice adaptive's wall time", rows["mi_render_2x"]), ""]
        e = rows["mi_render_1x"]
        fewer = a["above_tau"] < e["above_tau"] or (a["above_tau"] == e["above_tau"] == 0)
        lines.append(f"- Equal wall time: adaptive {a['above_tau']} blocks above tau against {e['above_tau']}, worst "
                     f"{a['worst']:.4f} against {e['worst']:.4f}: "
                     f"**{'met' if fewer and a['worst'] < e['worst'] else 'missed'}**.")
        t = s["time_to_mi_quality"]
        lines.append(f"- Time to `mi.render`'s quality at {s['max_spp']} spp ({m['above_tau']} blocks above tau): "
                     + (f"at most **{t:.2f}x** its time ({a['wall_s']:.1f} s against {m['wall_s']:.1f} s; worst "
                        f"block {a['worst']:.4f} against {m['worst']:.4f}), goal 0.5x: "
                        f"**{'met' if t <= 0.5 else 'missed'}**" if t is not None else
                        "**not reached** by the adaptive render's end") + ".")
        if a.get("tiles_stopped_above_tau"):
            lines.append(f"- Of adaptive's {a['tiles_above_tau']} tiles above tau, its criterion stopped "
                         f"{a['tiles_stopped_above_tau']} ({a['dark_tiles_stopped_above_tau']} of them near black, "
                         "reference mean under 1e-3); the others ran to max spp.")
        lines.append("")
    if "make_run" in r:
        mr = r["make_run"]
        lines += [f"**`make run`** ({mr['scene']}, its settings {json.dumps(mr['settings'])}), against our uniform "
                  "loop given the adaptive render's time and twice it:", "", *head,
                  _row("adaptive", mr["adaptive"]), _row("uniform, same time", mr["uniform_1x"]),
                  _row("uniform, twice the time", mr["uniform_2x"]), "",
                  f"- Uniform at twice the time {'matches' if mr['uniform_2x_matches'] else 'does not match'} "
                  "adaptive's blocks above tau and worst block: the 2x goal is "
                  f"**{'missed' if mr['uniform_2x_matches'] else 'met'}**.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--size", type=int, default=None)
    p.add_argument("--max-spp", type=int, default=4096)
    p.add_argument("--ref-spp", type=int, default=8192)
    p.add_argument("--no-make-run", action="store_true")
    p.add_argument("--json", default=None, help="write the results here (after each scene)")
    p.add_argument("--update", default=None, metavar="FILE", help="rewrite FILE's marked section")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    def save(r: dict[str, Any]) -> None:
        if args.json:
            Path(args.json).write_text(json.dumps(r, indent=1))

    r = bench_equal_time(tuple(s for s in args.scenes.split(",") if s), args.size, args.max_spp,
                         ref_spp=args.ref_spp, make_run=not args.no_make_run, on_scene=save)
    print(md_equal_time(r))
    if args.update:
        from .marked_sections import update_markdown

        update_markdown(Path(args.update), {SECTION[kind_of(r["variant"])]: md_equal_time(r)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
