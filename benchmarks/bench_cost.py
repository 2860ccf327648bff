"""`noisestop bench cost`: the adaptive render's cost per kept sample against the uniform
loop's, in parts (DESIGN "Cost per kept sample").

For each scene and reconstruction filter (the film's rfilter swapped in the scene's dict:
``box`` or ``gaussian``), in one process, kernels compiled first:

* **the renders**: the default adaptive render (``renderer.render``: flip, 16-px tiles) and
  the uniform loop (``criterion="uniform"``) at the same frame and max spp, interleaved
  `repeats` times (medians); each timed as a user times the call;
* **selection**: what the adaptive render's samples would cost traced densely.
  ``mi.render`` over each block's crop (`benchmarks.crop_cost.time_crop_renders`, the crop
  engine) gives each block's seconds per sample, as a ratio to the frame's mean (the
  blocks' total over their samples, so that uniform sampling is 1.00 by definition);
  weighted by the samples the adaptive render kept in each block (its per-pixel spp), that
  is the cost of its samples over a uniform sample's: work the samples need, not overhead;
* **trace per lane, dense against sparse**: our tracer (`BlockRenderer.render_passes`) over
  100, 50, 25, 10 and 5 % of the 16-px tiles a launch, the tiles dealt at random (seeded)
  into groups that together hold every tile once, so that cost does not choose them; one
  pass of `step` spp per launch, and grown passes (as many passes per launch as the loop
  traces for that many active tiles, `renderer.live.launches.grown_passes`); seconds per traced
  lane against 100 %;
* from the adaptive render's report: lanes traced per kept sample (``samples_traced`` over
  ``samples_spent``), the shares of wall time that are rendering (waiting for the tracer),
  decisions (criterion and features) and the rest, launches and lanes per launch.

The table's first rows are an identity: wall per kept sample = (wall / render time) x
(render time per lane) x (lanes per kept sample), each as adaptive over uniform. The
headline is the adaptive wall per kept sample over the uniform loop's, raw and with
selection divided out (goal: at most 1.05x on the CPU, 1.15x on the GPU).

    python -m benchmarks.bench_cost [--size 256] [--max-spp 1024] \\
        [--scenes studio_preview,cornell_box,spot_stage] [--filter box,gaussian] [--repeats 3] [--json F]

``cornell_box`` is Mitsuba's ``mi.cornell_box()``; other names are built-in scenes.
"""
from __future__ import annotations

import argparse
import json
import logging
import shlex
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .bench_native import device_name
from .timing import MachineLoad

log = logging.getLogger(__name__)

SCENES = ("studio_preview", "cornell_box", "spot_stage")
FILTERS = ("box", "gaussian")
#: the share of the 16-px tiles active in the sparse-trace rows
FRACTIONS = (1.0, 0.5, 0.25, 0.1, 0.05)
#: the sparse-trace rows' launch shapes: one pass per launch, or grown as the loop does
MODES = ("one", "grown")
#: the renders' defaults (renderer.spec): the selection grid and the sparse rows follow them
BLOCK, TILE, STEP = 64, 16, 16


def scene_with_filter(name: str, size: int, rfilter: str) -> Any:
    """`name` (Mitsuba's 'cornell_box' or a built-in scene) at size x size with the film's
    reconstruction filter `rfilter` ('box', 'gaussian', any Mitsuba rfilter type)."""
    import mitsuba as mi

    from learning.data.variant import select_variant

    select_variant()
    if name == "cornell_box":
        d = mi.cornell_box()
        d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = int(size)
    else:
        from renderer.scenes.catalog import scene_dict

        d = scene_dict(name, int(size))
    d["sensor"]["film"]["rfilter"] = {"type": rfilter}
    return mi.load_dict(d)


def timed_render(scene: Any, max_spp: int, criterion: str | None) -> dict[str, Any]:
    """One ``renderer.render`` (`criterion` None: the default adaptive render), timed as a
    user times the call; its report's counters and timers, and the per-pixel spp."""
    import renderer

    t0 = time.perf_counter()
    r = renderer.render(scene, criterion=criterion, max_spp=max_spp, progress=False)
    wall = time.perf_counter() - t0
    rep, calls, t = r.report, r.report["render_calls"], r.report["timing"]
    render_s = float(t["render_s"])
    decisions_s = float(t["decisions_s"]) + float(t["features_s"])
    return {"wall_s": wall, "render_s": render_s, "decisions_s": decisions_s,
            "rest_s": wall - render_s - decisions_s,
            "samples_kept": int(rep["samples_spent"]), "samples_traced": int(calls["samples_traced"]),
            "lanes": int(calls["kernel_lanes"]), "launches": int(calls["kernel_launches"]),
            "mean_spp": float(rep["mean_spp"]), "tiles_converged": int(rep.get("tiles_converged", 0)),
            "tiles": len(rep.get("tiles", rep["blocks"])), "criterion": rep["criterion"].get("name"),
            "spp_map": r.spp}


def median_run(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The run of median wall time (its counters with it), all walls listed."""
    walls = [r["wall_s"] for r in runs]
    med = runs[int(np.argsort(walls)[len(walls) // 2])]
    return {k: v for k, v in med.items() if k != "spp_map"} | {"walls_s": walls}


def block_windows(size: int, block: int) -> list[tuple[int, int, int, int]]:
    """(x, y, w, h) of the selection grid's blocks (renderer.live.block_windows' geometry)."""
    from renderer.live.block_windows import BlockWindows

    bw = BlockWindows(size, size, block=block)
    return [tuple(int(v) for v in bw.window(b)) for b in range(bw.n_blocks)]   # type: ignore[misc]


def selection(scene: Any, size: int, block: int, spp: int, repeats: int) -> dict[str, Any]:
    """Each block's dense cost per sample as a ratio to the frame's mean (module docstring):
    ``mi.render`` over each block's crop, warm, interleaved with the full frame."""
    from renderer.live.blocks import BlockRenderer

    from .crop_cost import time_crop_renders

    with BlockRenderer(scene, block=block, engine="crop") as r:
        n = r.n_blocks
        t = time_crop_renders(r, [[b] for b in range(n)], spp, repeats)
        windows = [tuple(int(v) for v in r.window(b)) for b in range(n)]
    pixels = np.array([w * h for _, _, w, h in windows], np.float64)
    secs = np.array(t["groups_s"], np.float64)
    per_sample = secs / (pixels * spp)
    mean = secs.sum() / (pixels.sum() * spp)          # uniform sampling: every pixel alike
    return {"block": block, "spp": spp, "windows": [list(w) for w in windows],
            "block_s": secs.tolist(), "relative": (per_sample / mean).tolist(),
            "full_s": t["full_s"], "blocks_over_full": float(secs.sum() / t["full_s"])}


def weighted_selection(sel: dict[str, Any], spp_map: np.ndarray) -> float:
    """The cost of a render's kept samples over as many uniform ones: each block's relative
    cost weighted by the samples the render kept in it (1.0 for a uniform render)."""
    kept = np.array([float(spp_map[y:y + h, x:x + w].sum()) for x, y, w, h in sel["windows"]])
    return float((np.asarray(sel["relative"]) * kept).sum() / kept.sum())


def sparse_trace(scene: Any, step: int, repeats: int, seed: int = 50,
                 fractions: Sequence[float] = FRACTIONS) -> dict[str, Any]:
    """Seconds per traced lane of our tracer over a random share of the tiles (module
    docstring). So that cost does not choose the tiles, each round deals every tile, in a
    random order (seeded), into round(1 / fraction) groups, and traces the groups one
    launch after another: every tile once, as the dense trace does, but a fraction at a
    time. Per mode and fraction: the median seconds of a round, its lanes and launches,
    seconds per lane and their ratio to 100 % (one pass)."""
    from renderer.live.blocks import BlockRenderer
    from renderer.live.launches import grown_passes

    size = int(scene.sensors()[0].film().crop_size()[0])
    block = min(BLOCK, size)
    rng = np.random.default_rng(seed)
    with BlockRenderer(scene, block=block, tile=min(TILE, block)) as br:
        n = br.n_units
        cases = [(mode, f) for mode in MODES for f in fractions if not (mode == "grown" and f == 1.0)]
        groups_of = {f: min(n, max(1, int(round(1 / f)))) for f in fractions}

        def run(mode: str, f: float, k: int, warm: bool = False) -> tuple[float, int, int, int]:
            groups = np.array_split(rng.permutation(n), groups_of[f])[:1 if warm else None]
            jobs = []
            for ids in groups:
                p = 1 if mode == "one" else grown_passes(n, len(ids), 1 << 20)
                jobs.append(np.concatenate([np.stack([ids, np.full_like(ids, k * 64 + j)], axis=1)
                                            for j in range(p)]))
            lanes0, launches0 = br.ledger.get("kernel_lanes"), br.ledger.get("kernel_launches")
            t0 = time.perf_counter()
            for j in jobs:
                br.render_passes(j, int(step), seed)
            return (time.perf_counter() - t0, br.ledger.get("kernel_lanes") - lanes0,
                    br.ledger.get("kernel_launches") - launches0, max(len(g) for g in groups))

        for mode, f in cases:            # compile first (one launch of each shape)
            run(mode, f, 1000, warm=True)
        got: dict[tuple[str, float], list[tuple[float, int, int, int]]] = {c: [] for c in cases}
        for k in range(max(1, int(repeats))):
            for c in cases:              # interleaved: every case sees the same load
                got[c].append(run(*c, k))
    rows = []
    for mode, f in cases:
        runs = got[(mode, f)]
        s = statistics.median(r[0] for r in runs)
        lanes, launches, tiles = runs[0][1], runs[0][2], runs[0][3]
        rows.append({"mode": mode, "fraction": f, "tiles": tiles, "groups": groups_of[f],
                     "passes_per_launch": 1 if mode == "one" else grown_passes(n, tiles, 1 << 20),
                     "seconds": s, "lanes": lanes, "launches": launches, "s_per_lane": s / max(lanes, 1)})
    dense = next(r["s_per_lane"] for r in rows if r["mode"] == "one" and r["fraction"] == 1.0)
    for r in rows:
        r["vs_dense"] = r["s_per_lane"] / dense
    return {"n_tiles": n, "step": step, "seed": seed, "rows": rows}


def ratios(a: dict[str, Any], u: dict[str, Any]) -> dict[str, float]:
    """The parts of the wall per kept sample, adaptive over uniform (an identity: the first
    equals the product of the next three)."""
    def per(x: dict[str, Any]) -> dict[str, float]:
        return {"wall_per_kept": x["wall_s"] / x["samples_kept"], "wall_over_render": x["wall_s"] / x["render_s"],
                "render_per_lane": x["render_s"] / x["lanes"], "lanes_per_kept": x["lanes"] / x["samples_kept"]}
    pa, pu = per(a), per(u)
    return {k: pa[k] / pu[k] for k in pa}


def measure_case(name: str, rfilter: str, size: int, max_spp: int, repeats: int, crop_spp: int,
                 block: int = BLOCK, step: int = STEP) -> dict[str, Any]:
    """Every figure of one scene with one filter (module docstring)."""
    scene = scene_with_filter(name, size, rfilter)
    phase_s: dict[str, float] = {}
    with MachineLoad() as load:
        t0 = time.perf_counter()
        timed_render(scene, min(max_spp, 2 * step), None)        # compile the tracer, FLIP and the loop
        timed_render(scene, min(max_spp, 2 * step), "uniform")
        runs: dict[str, list[dict[str, Any]]] = {"adaptive": [], "uniform": []}
        for _ in range(max(1, int(repeats))):                     # interleaved: the same load for both
            runs["adaptive"].append(timed_render(scene, max_spp, None))
            runs["uniform"].append(timed_render(scene, max_spp, "uniform"))
        t1 = time.perf_counter()
        sel = selection(scene, size, min(block, size), crop_spp, repeats)
        t2 = time.perf_counter()
        sparse = sparse_trace(scene, step, repeats)
        phase_s = {"renders": t1 - t0, "selection": t2 - t1, "sparse": time.perf_counter() - t2}
    ada, uni = median_run(runs["adaptive"]), median_run(runs["uniform"])
    spp_map = runs["adaptive"][0]["spp_map"]                      # the same stops in every run
    sel["adaptive"] = weighted_selection(sel, spp_map)
    sel["uniform"] = weighted_selection(sel, runs["uniform"][0]["spp_map"])
    parts = ratios(ada, uni)
    return {"scene": name, "filter": rfilter, "size": size, "max_spp": max_spp, "repeats": repeats,
            "others_cpu_share": load.share, "phase_s": phase_s, "adaptive": ada, "uniform": uni, "selection": sel, "sparse": sparse,
            "ratios": parts, "headline": {"raw": parts["wall_per_kept"],
                                          "selection_divided_out": parts["wall_per_kept"] / sel["adaptive"]}}


def bench_cost(size: int = 256, max_spp: int = 1024, scenes: Sequence[str] = SCENES,
               filters: Sequence[str] = FILTERS, repeats: int = 3, crop_spp: int = 64, block: int = BLOCK,
               command: str = "noisestop bench cost",
               on_case: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Every (scene, filter) case on the variant's device; `on_case(result)` after each (a
    run cut short keeps what it measured)."""
    from learning.data.variant import select_variant
    from learning.names import DEFAULT_TAU

    variant = select_variant()
    out: dict[str, Any] = {"variant": variant, "device": device_name("cuda" if variant.startswith("cuda") else "cpu"),
                           "tau": DEFAULT_TAU, "command": command, "cases": []}
    for name in scenes:
        for f in filters:
            log.info("bench cost: %s, %s filter, %dx%d, max %d spp", name, f, size, size, max_spp)
            t0 = time.perf_counter()
            case = measure_case(name, f, size, max_spp, repeats, crop_spp, block)
            out["cases"].append(case | {"seconds": time.perf_counter() - t0})
            if on_case is not None:
                on_case(out)
    return out


def _x(v: float) -> str:
    return f"{v:.2f}x"


def _pct(part: float, whole: float) -> str:
    return f"{100 * part / whole:.1f} %"


def md_case(c: dict[str, Any]) -> list[str]:
    """One case's table: a row per part, adaptive | uniform | adaptive / uniform."""
    a, u, q, sel = c["adaptive"], c["uniform"], c["ratios"], c["selection"]
    ns = 1e9
    share = c.get("others_cpu_share")
    load = "" if share is None else f"; other processes used {100 * share:.0f} % of the CPUs meanwhile"
    lines = ["", f"**{c['scene']} {c['size']}x{c['size']}, {c['filter']} filter**, max {c['max_spp']} spp: adaptive "
             f"mean {a['mean_spp']:.0f} spp, {a['tiles_converged']} of {a['tiles']} tiles stopped; medians of "
             f"{c['repeats']} interleaved runs (walls adaptive " + ", ".join(f"{w:.2f}" for w in a["walls_s"])
             + " s, uniform " + ", ".join(f"{w:.2f}" for w in u["walls_s"]) + f" s){load}.", "",
             "| part | adaptive | uniform | adaptive / uniform |", "|---|---|---|---|",
             f"| **wall per kept sample** | {ns * a['wall_s'] / a['samples_kept']:.1f} ns "
             f"| {ns * u['wall_s'] / u['samples_kept']:.1f} ns | **{_x(q['wall_per_kept'])}** |",
             f"| = wall / render time | {a['wall_s'] / a['render_s']:.3f} | {u['wall_s'] / u['render_s']:.3f} "
             f"| {_x(q['wall_over_render'])} |",
             f"| x render time per lane | {ns * a['render_s'] / a['lanes']:.1f} ns "
             f"| {ns * u['render_s'] / u['lanes']:.1f} ns | {_x(q['render_per_lane'])} |",
             f"| x lanes per kept sample (samples traced / kept) | {a['lanes'] / a['samples_kept']:.3f} "
             f"| {u['lanes'] / u['samples_kept']:.3f} | {_x(q['lanes_per_kept'])} |",
             f"| selection: dense cost of the kept samples (`mi.render` per {sel['block']}-px block crop, "
             f"{sel['spp']} spp; blocks from {min(sel['relative']):.2f}x to {max(sel['relative']):.2f}x the mean) "
             f"| {_x(sel['adaptive'])} | {_x(sel['uniform'])} | {_x(sel['adaptive'] / sel['uniform'])} |",
             f"| render time per lane, selection divided out | | | {_x(q['render_per_lane'] / sel['adaptive'])} |"]
    sp = c["sparse"]
    dense = next(r for r in sp["rows"] if r["mode"] == "one" and r["fraction"] == 1.0)
    for r in sp["rows"]:
        if r is dense:
            continue
        how = "1 pass" if r["mode"] == "one" else f"grown, {r['passes_per_launch']} passes"
        lines.append(f"| trace per lane, {100 * r['fraction']:g} % of tiles a launch ({r['tiles']} of "
                     f"{sp['n_tiles']} at random, {r['launches']} launches), {how} | {ns * r['s_per_lane']:.1f} ns "
                     f"| {ns * dense['s_per_lane']:.1f} ns (100 %) | {_x(r['vs_dense'])} |")
    lines += [f"| decisions (criterion + features), share of wall | {_pct(a['decisions_s'], a['wall_s'])} "
              f"| {_pct(u['decisions_s'], u['wall_s'])} | |",
              f"| render (waiting for the tracer), share of wall | {_pct(a['render_s'], a['wall_s'])} "
              f"| {_pct(u['render_s'], u['wall_s'])} | |",
              f"| the rest (set-up, accumulation, report), share of wall | {_pct(a['rest_s'], a['wall_s'])} "
              f"| {_pct(u['rest_s'], u['wall_s'])} | |",
              f"| launches | {a['launches']} | {u['launches']} | {_x(a['launches'] / u['launches'])} |",
              f"| lanes per launch | {a['lanes'] / a['launches']:,.0f} | {u['lanes'] / u['launches']:,.0f} "
              f"| {_x((a['lanes'] / a['launches']) / (u['lanes'] / u['launches']))} |",
              f"| **overhead per kept sample** (wall per kept sample, selection divided out; goal <= 1.05x CPU, "
              f"1.15x GPU) | | | **{_x(c['headline']['selection_divided_out'])}** |"]
    return lines


def md_cost(r: dict[str, Any]) -> str:
    """BENCHMARKS.md section: the command and machine, then one table per scene and filter."""
    lines = [f"Command: `{r['command']}`. Device: **{r['device']}**, variant `{r['variant']}`, tau {r['tau']:g}; "
             "default adaptive render (flip, 16-px tiles, step 16, grown and queued passes) against the uniform "
             "loop at the same frame and max spp, kernels compiled first. The first row is the product of the "
             "next three."]
    for c in r["cases"]:
        lines += md_case(c)
    if r["cases"]:
        lines += ["", "| scene | filter | wall per kept sample | selection | overhead per kept sample |",
                  "|---|---|---|---|---|"]
        lines += [f"| {c['scene']} | {c['filter']} | {_x(c['headline']['raw'])} | {_x(c['selection']['adaptive'])} "
                  f"| {_x(c['headline']['selection_divided_out'])} |" for c in r["cases"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--max-spp", type=int, default=1024)
    p.add_argument("--scenes", default=",".join(SCENES), help="comma-separated: cornell_box (Mitsuba's) or "
                   "built-in scene names")
    p.add_argument("--filter", default=",".join(FILTERS), help="comma-separated film rfilters (box, gaussian)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved runs of each timed render (medians)")
    p.add_argument("--crop-spp", type=int, default=64, help="spp of the selection's per-block mi.render crops")
    p.add_argument("--block", type=int, default=BLOCK, help="side of the selection's blocks in pixels")
    p.add_argument("--json", default=None, help="write the results here")
    p.add_argument("--update", default=None, metavar="FILE", help="rewrite FILE's section cost with the results")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    scenes = tuple(s for s in a.scenes.split(",") if s)
    filters = tuple(f for f in a.filter.split(",") if f)
    command = ("python -m benchmarks.bench_cost " + " ".join(shlex.quote(x) for x in (
        "--size", str(a.size), "--max-spp", str(a.max_spp), "--scenes", ",".join(scenes), "--filter",
        ",".join(filters), "--repeats", str(a.repeats), "--crop-spp", str(a.crop_spp), "--block", str(a.block))))

    def save(r: dict[str, Any]) -> None:
        if a.json:
            with open(a.json, "w", encoding="utf-8") as f:
                json.dump(r, f, indent=1)
        if a.update:
            from pathlib import Path

            from .marked_sections import update_markdown

            update_markdown(Path(a.update), {"cost_gpu" if r["variant"].startswith("cuda") else "cost": md_cost(r)})

    r = bench_cost(a.size, a.max_spp, scenes, filters, repeats=max(1, a.repeats), crop_spp=a.crop_spp, block=a.block,
                   command=command, on_case=save)
    print(md_cost(r), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
