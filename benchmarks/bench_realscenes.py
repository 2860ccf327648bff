"""`noisestop bench realscenes`: the default render against `mi.render` on published scenes
that took no part in training, calibration or any other benchmark (benchmarks/realscenes/).

A Mitsuba user judges noisestop one way: render the same scene with `mi.render` and with
noisestop, for the same wall time, and look; or ask how long `mi.render` needs to match our
picture. For each suite scene, at 256x256 on the CPU (1024x1024 on a GPU), every frame
judged by DESIGN's observer (the largest 16x16-tile FLIP of each 64-px block) against an
8192-spp `mi.render` reference (seed 1000, cached outside git):

* `mi.render`'s quality curve, for two seeds: its picture every `chunk` spp (64) to max spp
  (4096), and on while it is short of the default render's wall time, as a user renders
  progressively, each point with the render seconds spent so far (the observer's own time
  not counted);
* the default render (`renderer.render`, every setting at its default but max spp): wall
  time A, mean spp, its final frame;
* equal wall time: each seed's curve point at A (the last point traced within A);
* speed-up at equal quality: per seed, the time of the first curve point with no more blocks
  above tau and no worse a worst block than ours, over A (a lower bound where the curve ends
  first);
* the time limit: `renderer.render(time_limit=T)` with T the seed-1 curve's time at 1024
  spp, against that curve point;
* where the default render traces most samples (mean spp at least 90 % of max), its wall
  time per sample against `mi.render` in one call per 1024 spp ("same samples").

Verdicts call a difference within the two seeds' spread a tie: worse is more blocks above
tau than either seed, or a worst block over 1.02x the larger seed's; better is fewer blocks
than either seed, or (as many) a worst block under the smaller seed's.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from .bench_equal_time import adaptive, judged, kind_of
from .bench_native import block_errors, mi_render, rendered_reference

log = logging.getLogger(__name__)

#: the film side per device kind
SIZE = {"cpu": 256, "cuda": 1024}
#: BENCHMARKS' marked section per device kind
SECTION = {"cpu": "realscenes", "cuda": "realscenes_gpu"}
#: a worst block this much over the larger seed's is worse, not a tie (2 %)
WORST_SLACK = 1.02
#: the time limit's T is the seed-1 curve's time at this spp
LIMIT_SPP = 1024
#: the same-samples row is measured where the default render traces at least this share of max spp
MOST_SAMPLES = 0.9


def quality_curve(scene: Any, reference: np.ndarray, tau: float, max_spp: int, chunk: int,
                  seed: int, until_s: float = 0.0) -> list[dict[str, Any]]:
    """`mi.render` progressively: a call of `chunk` spp at a time (its own seed), the running
    mean judged after each, to `max_spp` and on until `until_s` render seconds (so that the
    curve holds `mi.render`'s picture at a wall time longer than its max-spp render); `t`
    counts only the calls and their read-back."""
    import mitsuba as mi

    total = np.zeros(reference.shape[:2] + (3,), np.float64)
    spent, points, k = 0.0, [], 0
    while k < max_spp // chunk or spent < until_s:
        t0 = time.perf_counter()
        img = np.asarray(mi.render(scene, spp=chunk, seed=seed * 7919 + k), np.float32)[..., :3]
        spent += time.perf_counter() - t0
        total += img
        e = block_errors((total / (k + 1)).astype(np.float32), reference, tau)
        points.append({"spp": (k + 1) * chunk, "t": spent, "above_tau": e["above_tau"], "worst": e["worst"]})
        k += 1
    return points


def at_time(points: list[dict[str, Any]], t: float) -> dict[str, Any]:
    """The curve's picture at wall time `t`: its last point traced within `t` (its first if none)."""
    within = [p for p in points if p["t"] <= t]
    return within[-1] if within else points[0]


def time_to_match(points: list[dict[str, Any]], above: int, worst: float) -> tuple[float, bool]:
    """(seconds, reached): the first curve point with at most `above` blocks above tau and a
    worst block at most `worst`; the curve's end (not reached) otherwise."""
    for p in points:
        if p["above_tau"] <= above and p["worst"] <= worst:
            return p["t"], True
    return points[-1]["t"], False


def compare(ours: dict[str, Any], seeds: list[dict[str, Any]]) -> str:
    """'win', 'tie' or 'loss' of our frame against the seeds' frames (the module docstring)."""
    hi_above, lo_above = max(s["above_tau"] for s in seeds), min(s["above_tau"] for s in seeds)
    hi_worst, lo_worst = max(s["worst"] for s in seeds), min(s["worst"] for s in seeds)
    if ours["above_tau"] > hi_above or ours["worst"] > WORST_SLACK * hi_worst:
        return "loss"
    if ours["above_tau"] < lo_above or (ours["above_tau"] <= lo_above and ours["worst"] < lo_worst):
        return "win"
    return "tie"


def measure_scene(name: str, size: int, max_spp: int, tau: float, ref_spp: int, ref_dir: Path,
                  chunk: int = 64, seeds: tuple[int, ...] = (1, 2), criterion: str | None = None) -> dict[str, Any]:
    """Every row of one suite scene (the module docstring); `criterion`: ours with another
    criterion than the default (every other setting at its default)."""
    import mitsuba as mi

    from renderer.scenes.catalog import load_scene

    from .realscenes import scene_path

    scene = load_scene(scene_path(name), size)
    mi.render(scene, spp=16, seed=99)                  # warm: both kernels compiled
    ours_settings = {"tau": tau, **({"criterion": criterion} if criterion else {})}
    adaptive(scene, 32, **ours_settings)
    ref, source = rendered_reference(scene, ref_spp, keep=ref_dir / f"realscene_{name}_{size}_{ref_spp}.exr")
    a = adaptive(scene, max_spp, **ours_settings)
    ours = {"wall_s": a["wall_s"], "mean_spp": a["mean_spp"], "decisions_s": a["decisions_s"],
            **judged(a["image"], ref, tau, a["stopped"], a["tiles"])}
    # each curve runs on past max spp while it is short of our wall time: its picture there
    curves = {s: quality_curve(scene, ref, tau, max_spp, chunk, s, until_s=a["wall_s"]) for s in seeds}
    first = curves[seeds[0]]
    limit_t = next(p["t"] for p in first if p["spp"] >= min(LIMIT_SPP, max_spp))
    lim = adaptive(scene, max_spp, time_limit=limit_t, **ours_settings)
    limited = {"wall_s": lim["wall_s"], "mean_spp": lim["mean_spp"], **judged(lim["image"], ref, tau)}
    matches = {s: time_to_match(c, ours["above_tau"], ours["worst"]) for s, c in curves.items()}
    out: dict[str, Any] = {
        "scene": name, "size": size, "max_spp": max_spp, "tau": tau, "reference": source, "adaptive": ours,
        "curves": {str(s): c for s, c in curves.items()},
        "equal_time": {str(s): at_time(c, ours["wall_s"]) for s, c in curves.items()},
        "speedup": {str(s): {"t": t, "reached": ok, "ratio": t / ours["wall_s"]} for s, (t, ok) in matches.items()},
        "time_limit": {"T": limit_t, "ours": limited, **{str(s): at_time(c, limit_t) for s, c in curves.items()}},
        "max_spp_mi": {str(s): next(p for p in c if p["spp"] >= max_spp) for s, c in curves.items()},
    }
    out["equal_time_verdict"] = compare(ours, [out["equal_time"][str(s)] for s in seeds])
    out["time_limit_verdict"] = compare(limited, [out["time_limit"][str(s)] for s in seeds])
    if ours["mean_spp"] >= MOST_SAMPLES * max_spp:
        _, t_same = mi_render(scene, int(round(ours["mean_spp"])), seed=seeds[0] + 100)
        out["same_samples"] = {"mi_render_s": t_same, "ratio": ours["wall_s"] / t_same}
    return out


def bench_realscenes(scenes: tuple[str, ...] | None = None, size: int | None = None, max_spp: int = 4096,
                     tau: float | None = None, ref_spp: int = 8192, ref_dir: str | Path = "out/bench/references",
                     chunk: int = 64, refs_only: bool = False, on_scene: Any = None,
                     criterion: str | None = None) -> dict[str, Any]:
    """Every suite scene (`measure_scene`); `on_scene(result)` after each, so a run cut short
    keeps what it measured. `refs_only`: render (or find cached) the references and stop;
    `criterion`: ours with that criterion instead of the default."""
    from learning.data.variant import select_variant
    from learning.names import DEFAULT_TAU
    from renderer.scenes.catalog import load_scene

    from .bench_native import device_name
    from .realscenes import SCENES, scene_path

    names = tuple(scenes or SCENES)
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise ValueError(f"unknown suite scene(s) {', '.join(unknown)}; the suite: {', '.join(SCENES)}")
    variant = select_variant()
    kind = kind_of(variant)
    size = size or SIZE[kind]
    tau = tau or DEFAULT_TAU
    out: dict[str, Any] = {"variant": variant, "device": device_name(kind), "tau": tau, "size": size,
                           "max_spp": max_spp, "criterion": criterion, "scenes": []}
    for name in names:
        if refs_only:
            scene = load_scene(scene_path(name), size)
            _, source = rendered_reference(scene, ref_spp, keep=Path(ref_dir) / f"realscene_{name}_{size}_{ref_spp}.exr")
            log.info("bench realscenes: %s reference: %s", name, source)
            continue
        log.info("bench realscenes: %s", name)
        out["scenes"].append(measure_scene(name, size, max_spp, tau, ref_spp, Path(ref_dir), chunk,
                                           criterion=criterion))
        if on_scene is not None:
            on_scene(out)
    return out


def _frame(r: dict[str, Any]) -> str:
    return f"{r['above_tau']} / {r['worst']:.4f}"


def _seeds(d: dict[str, Any], keys: list[str]) -> str:
    return ", ".join(_frame(d[k]) for k in keys)


ORDER = {"loss": 0, "tie": 1, "win": 2}


def md_realscenes(r: dict[str, Any]) -> str:
    """One row per scene, losses first; then the goals."""
    from .realscenes import SCENES

    ours = f"ours with `--criterion {r['criterion']}`" if r.get("criterion") else "the default render"
    lines = [f"Device: **{r['device']}**, variant `{r['variant']}`, {r['size']}x{r['size']}, max {r['max_spp']} "
             f"spp, tau {r['tau']}, {ours}; each tool warm, one run of ours, `mi.render` with two seeds (a curve point "
             "every 64 spp). Frames as *blocks above tau / worst block* (DESIGN's observer, 64-px blocks) against "
             "`mi.render` at 8192 spp.", "",
             "| scene | kind | ours: wall, mean spp | ours | `mi.render` at our wall (2 seeds) | equal time | "
             "speed-up at equal quality | time limit T | ours at T | `mi.render` at T | at T | same samples |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in sorted(r["scenes"], key=lambda s: (ORDER[s["equal_time_verdict"]], s["scene"])):
        keys = list(s["equal_time"])
        a = s["adaptive"]
        sp = [s["speedup"][k] for k in keys]
        speed = ", ".join(f"{x['ratio']:.2f}x" if x["reached"] else f"> {x['ratio']:.2f}x" for x in sp)
        tl = s["time_limit"]
        same = f"{s['same_samples']['ratio']:.3f}x" if "same_samples" in s else "-"
        kind = ", ".join(SCENES[s["scene"]].kinds) if s["scene"] in SCENES else ""
        lines.append(f"| {s['scene']} | {kind} | {a['wall_s']:.1f} s, {a['mean_spp']:.0f} | {_frame(a)} | "
                     f"{_seeds(s['equal_time'], keys)} | **{s['equal_time_verdict']}** | {speed} | {tl['T']:.1f} s | "
                     f"{_frame(tl['ours'])} ({tl['ours']['mean_spp']:.0f} spp) | {_seeds(tl, keys)} | "
                     f"**{s['time_limit_verdict']}** | {same} |")
    scenes = r["scenes"]
    n = len(scenes)
    worse = [s["scene"] for s in scenes if s["equal_time_verdict"] == "loss"]
    wins = [s["scene"] for s in scenes if s["equal_time_verdict"] == "win"]
    converging = [s for s in scenes if s["adaptive"]["mean_spp"] < MOST_SAMPLES * s["max_spp"]]
    fast = [s["scene"] for s in converging if all(x["reached"] and x["ratio"] >= 2.0 for x in s["speedup"].values())]
    lim_w = [s["scene"] for s in scenes if s["time_limit_verdict"] == "win"]
    same = [s for s in scenes if "same_samples" in s]
    lines += ["", f"- Equal wall time: **{len(wins)} wins, {n - len(wins) - len(worse)} ties, {len(worse)} losses** "
              f"of {n}" + (f" (losses: {', '.join(worse)})" if worse else "") + ".",
              f"- Speed-up at equal quality of at least 2x (both seeds) on {len(fast)} of the {len(converging)} scenes "
              "where tiles stop" + (f": {', '.join(fast)}" if fast else "") + ".",
              f"- Time limit: better than `mi.render` at T on {len(lim_w)} of {n}.",
              f"- Where {ours} traces most samples: " + (", ".join(
                  f"{s['scene']} {s['same_samples']['ratio']:.3f}x `mi.render`'s wall for the same samples"
                  for s in same) if same else "no scene") + " (goal 1.02x)."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="", help="comma-separated suite scenes (default: all)")
    p.add_argument("--size", type=int, default=None)
    p.add_argument("--max-spp", type=int, default=4096)
    p.add_argument("--ref-spp", type=int, default=8192)
    p.add_argument("--refs-only", action="store_true", help="render the missing references and stop")
    p.add_argument("--json", default=None, help="write the results here (after each scene)")
    p.add_argument("--update", default=None, metavar="FILE", help="rewrite FILE's marked section")
    p.add_argument("--plot", default=None, metavar="PNG", help="draw each scene's curves and our renders here")
    p.add_argument("--criterion", default=None, help="ours with this criterion (default: the default render's); "
                   "its table goes to the section realscenes-CRITERION")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    def save(r: dict[str, Any]) -> None:
        if args.json:
            Path(args.json).write_text(json.dumps(r, indent=1))

    r = bench_realscenes(tuple(s for s in args.scenes.split(",") if s) or None, args.size, args.max_spp,
                         ref_spp=args.ref_spp, refs_only=args.refs_only, on_scene=save, criterion=args.criterion)
    if args.refs_only:
        return 0
    print(md_realscenes(r))
    if args.plot:
        from .charts import realscenes

        realscenes(r["scenes"], args.plot, r["tau"])
    if args.update:
        from .marked_sections import update_markdown

        key = SECTION[kind_of(r["variant"])] + (f"-{args.criterion}" if args.criterion else "")
        update_markdown(Path(args.update), {key: md_realscenes(r)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
