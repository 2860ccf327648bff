"""`noisestop bench passes`: does wall time follow the samples?

Three measurements, all warm, on this machine:

* wall time of one block pass against the active pixels it traces (one kernel launch for
  any set of blocks, `renderer.live.wavefront`), with the crop-window engine (one Mitsuba call
  per block) beside it: a linear fit gives the constant per pass and the cost per pixel;
* the flip criterion's decision time against the number of blocks asked at once;
* adaptive renders (flip) against uniform sampling to the same max spp, at 256x256 and at
  1280x720: the wall-time speed-up next to the sample ratio (uniform samples / spent
  samples; ideal speed-up = ratio), and the share of wall time in features + decisions.
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .timing import median_s

PASS_SCENE = ("env_spheres", "640x384", 64, 32)          # scene, resolution, block, spp per pass
RENDERS = (("env_spheres", 256, 32, 512), ("studio_preview", "1280x720", 32, 1024))   # scene, res, step, max


def pass_cost(repeats: int = 3) -> dict[str, Any]:
    """Seconds per pass against active pixels, per engine, with a least-squares line."""
    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene

    scene, res, block, spp = PASS_SCENE
    out: dict[str, Any] = {"scene": scene, "resolution": res, "block": block, "spp": spp, "engines": {}}
    for engine in ("wavefront", "crop"):
        br = BlockRenderer(load_scene(scene, res), block=block, engine=engine)
        n = br.n_blocks
        rng = np.random.default_rng(0)
        order = rng.permutation(n).tolist()
        counts = sorted({1, 2, n // 8, n // 4, n // 2, n})
        br.render_units(order, spp, seed=0)                       # compile once (crop: every window)
        rows = []
        for k in counts:
            ids = sorted(order[:k])
            s = median_s(lambda ids=ids: br.render_units(ids, spp, seed=1, pass_index=k), repeats,
                          warm=False)
            rows.append({"blocks": k, "pixels": k * block * block, "seconds": s})
        x = np.array([r["pixels"] for r in rows], float)
        y = np.array([r["seconds"] for r in rows], float)
        slope, intercept = np.polyfit(x, y, 1)
        fit = slope * x + intercept
        r2 = 1.0 - float(((y - fit) ** 2).sum() / max(((y - y.mean()) ** 2).sum(), 1e-30))
        out["engines"][engine] = {"rows": rows, "constant_s": float(intercept),
                                  "ns_per_pixel_sample": float(slope / spp * 1e9), "r2": r2,
                                  "kernel_compiles": br.kernel_compiles}
    return out


COST_SCENE = ("cornell", 256, (4, 4), 32)                # scene, resolution, grid, spp per pass
STEPS_PER_LAUNCH = (1, 4)


def sample_cost(repeats: int = 3, steps: tuple[int, ...] = STEPS_PER_LAUNCH) -> dict[str, Any]:
    """Seconds per pixel-sample of a pass with one block of 16 active against all 16.

    Each block is traced alone in turn (so the figure is not one block's own cost: the
    mean over the blocks, as a render whose last active block could be any of them), and
    with k passes of it in one launch (`BlockRenderer.render_passes`: a k times larger
    wavefront). Repeats interleave every variant; medians per block.
    """
    import time

    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene

    scene, res, grid, spp = COST_SCENE
    br = BlockRenderer(load_scene(scene, res), grid=grid)
    n = br.n_blocks
    br.render_units(list(range(n)), spp, seed=0)                       # compile
    clocks = {"wall": time.perf_counter, "cpu": time.process_time}   # cpu: every thread of this process
    full = {c: [] for c in clocks}
    alone = {(c, k): np.zeros((repeats, n)) for c in clocks for k in steps}
    p = 1
    for r in range(repeats):
        t0 = {c: f() for c, f in clocks.items()}
        br.render_units(list(range(n)), spp, seed=1, pass_index=p)
        for c, f in clocks.items():
            full[c].append(f() - t0[c])
        p += 1
        for b in range(n):
            for k in steps:
                t0 = {c: f() for c, f in clocks.items()}
                br.render_passes([(b, p + j) for j in range(k)], spp, seed=1)
                for c, f in clocks.items():
                    alone[c, k][r, b] = (f() - t0[c]) / k
                p += k
    full_s = {c: float(np.median(v)) for c, v in full.items()}
    rows = [{"steps_per_launch": k, "lanes": br.block_h * br.block_w * spp * k,
             "one_block_s": float(np.median(alone["wall", k], axis=0).mean()),
             "ratio": float(np.median(alone["wall", k], axis=0).sum() / full_s["wall"]),
             "cpu_ratio": float(np.median(alone["cpu", k], axis=0).sum() / full_s["cpu"])} for k in steps]
    per_block = np.median(alone["cpu", steps[0]], axis=0)
    return {"scene": scene, "resolution": res, "grid": list(grid), "spp": spp, "repeats": repeats,
            "all_blocks_s": full_s["wall"], "all_blocks_cpu_s": full_s["cpu"], "rows": rows,
            "block_cost_spread": float(per_block.max() / per_block.min())}


def decision_cost(repeats: int = 5, counts: tuple[int, ...] = (1, 4, 16, 64, 256)) -> dict[str, Any]:
    """Seconds of one flip decision call against the number of 64x64 blocks it judges."""
    from renderer.criteria import UnitView, FlipCriterion
    from noisefeat.runtime import torch_threads

    rng = np.random.default_rng(0)
    crit = FlipCriterion()
    rows = []
    for n in counts:
        base = rng.random((n, 64, 64, 3)) * 0.5
        a = base + rng.normal(0, 0.02, base.shape)
        b = base + rng.normal(0, 0.02, base.shape)
        views = [UnitView(mean=(a[i] + b[i]) / 2, spp=64, nonfinite=0, halves=(a[i], b[i]), half_spp=(32, 32),
                           quick=None) for i in range(n)]
        with torch_threads(1):                                      # as the render loop decides
            crit.decide(list(range(n)), views)                      # warm
            s = median_s(lambda views=views, n=n: crit.decide(list(range(n)), views), repeats, warm=False)
        rows.append({"blocks": n, "seconds": s, "ms_per_block": 1e3 * s / n})
    return {"criterion": "flip", "block": 64, "rows": rows}


def block_costs(scene: str, resolution: Any, block: int | None = None, spp: int = 8,
                grid: tuple[int, int] | None = None, repeats: int = 1) -> np.ndarray:
    """Seconds per sample of each block traced alone (warm): samples are not equally dear
    (a sky pixel's ray escapes at once, a glass pixel's bounces), so the samples a render
    saves and the time it saves differ by where it saved them."""
    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene

    br = BlockRenderer(load_scene(scene, resolution), block=block, grid=grid)
    br.render_units([0], spp, seed=0)
    return np.array([median_s(lambda b=b: br.render_units([b], spp, seed=1, pass_index=b), repeats, warm=False)
                     / spp for b in range(br.n_blocks)])


#: oracle stops of the speed-up goal: thresholds spread over 192..2048 spp and two blocks
#: that never converge (censored), dealt to the 16 blocks in a fixed shuffled order
ORACLE_THRESHOLDS = (192, 256, 320, 384, 448, 512, 640, 768, 896, 1024, 1280, 1536, 1792, 2048, None, None)
ORACLE_RUNS = (("cornell", 256, 32, 2048), ("env_spheres", 256, 32, 2048))   # scene, res, step, max spp


def oracle_speedup(repeats: int = 3, runs: tuple = ORACLE_RUNS) -> list[dict[str, Any]]:
    """The oracle criterion against uniform to the same max spp, interleaved, medians.

    With the oracle the stops cost nothing to decide, so the wall-time speed-up against
    the sample ratio measures the loop itself: per-pass overhead and the wavefront of few
    blocks. The cost-weighted ratio weighs each block's samples by its own cost per
    sample (measured alone), the speed-up an ideal loop would reach.
    """
    import time

    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import OracleCriterion, UniformCriterion

    order = np.random.default_rng(28).permutation(len(ORACLE_THRESHOLDS))
    thresholds = [ORACLE_THRESHOLDS[i] for i in order]
    out = []
    for scene, res, step, max_spp in runs:
        opts = {"resolution": res, "grid": (4, 4), "step": step, "min_spp": step, "max_spp": max_spp,
                "progress": False, "checkpoint_every": 1e9}
        runs_: dict[str, list[dict[str, Any]]] = {"oracle": [], "uniform": []}
        with tempfile.TemporaryDirectory() as tmp:
            adaptive_render(scene, Path(tmp) / "warm", UniformCriterion(), **{**opts, "max_spp": step})
            for i in range(repeats):
                for name in ("oracle", "uniform") if i % 2 == 0 else ("uniform", "oracle"):
                    crit = OracleCriterion(thresholds) if name == "oracle" else UniformCriterion()
                    cpu = time.process_time()
                    rep = adaptive_render(scene, Path(tmp) / f"{name}{i}", crit, **opts)
                    runs_[name].append({**rep, "cpu_s": time.process_time() - cpu})
        o, u = (sorted(runs_[k], key=lambda r: r["wall_s"])[len(runs_[k]) // 2] for k in ("oracle", "uniform"))
        # each repeat's pair ran back to back: the median of the pairs' ratios shrugs off a
        # load change between repeats; CPU time (every thread of the process) off load at all
        pairs = {c: float(np.median([u_[c] / o_[c] for o_, u_ in zip(runs_["oracle"], runs_["uniform"])]))
                 for c in ("wall_s", "cpu_s")}
        sample_ratio = u["render_calls"]["samples_traced"] / o["render_calls"]["samples_traced"]
        cost = block_costs(scene, res, grid=(4, 4), spp=step, repeats=3)
        spent = np.array([b["spp"] for b in o["blocks"]], float)
        cost_ratio = float(cost.sum() * max_spp / (cost * spent).sum())
        speedup = pairs["wall_s"]
        out.append({"scene": scene, "resolution": res, "step": step, "max_spp": max_spp, "repeats": repeats,
                    "oracle_wall_s": [r["wall_s"] for r in runs_["oracle"]],
                    "uniform_wall_s": [r["wall_s"] for r in runs_["uniform"]],
                    "oracle_cpu_s": [r["cpu_s"] for r in runs_["oracle"]],
                    "uniform_cpu_s": [r["cpu_s"] for r in runs_["uniform"]], "cpu_speedup": pairs["cpu_s"],
                    "speedup": speedup, "sample_ratio": sample_ratio, "cost_weighted_ratio": cost_ratio,
                    "speedup_over_ratio": speedup / sample_ratio, "speedup_over_cost_ratio": speedup / cost_ratio,
                    "cpu_speedup_over_ratio": pairs["cpu_s"] / sample_ratio,
                    "cpu_speedup_over_cost_ratio": pairs["cpu_s"] / cost_ratio,
                    "block_cost_spread": float(cost.max() / cost.min()),
                    "render_calls": o["render_calls"]})
    return out


def render_scaling(repeats: int = 1) -> list[dict[str, Any]]:
    """Adaptive (flip) against uniform to the same max spp, per frame size."""
    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import FlipCriterion, UniformCriterion
    from renderer.settings import DEFAULT_BLOCK

    out = []
    for scene, res, step, max_spp in RENDERS:
        opts = {"resolution": res, "step": step, "min_spp": step, "max_spp": max_spp, "progress": False,
                "checkpoint_every": 30.0}
        runs: dict[str, list[dict[str, Any]]] = {"flip": [], "uniform": []}
        with tempfile.TemporaryDirectory() as tmp:
            adaptive_render(scene, Path(tmp) / "warm", UniformCriterion(), **{**opts, "max_spp": step})
            for i in range(repeats):
                for name, crit in (("flip", FlipCriterion()), ("uniform", UniformCriterion())):
                    runs[name].append(adaptive_render(scene, Path(tmp) / f"{name}{i}", crit, **opts))
        f, u = (sorted(runs[k], key=lambda r: r["wall_s"])[len(runs[k]) // 2] for k in ("flip", "uniform"))
        sample_ratio = u["render_calls"]["samples_traced"] / f["render_calls"]["samples_traced"]
        cost = block_costs(scene, res, DEFAULT_BLOCK)
        spent = np.array([b["spp"] for b in f["blocks"]], float)
        cost_ratio = float(cost.sum() * max_spp / (cost * spent).sum())
        t = f["timing"]
        out.append({"scene": scene, "resolution": f["resolution"], "step": step, "max_spp": max_spp,
                    "blocks": len(f["blocks"]), "saved_vs_uniform": f["saved_vs_uniform"],
                    "flip_wall_s": f["wall_s"], "uniform_wall_s": u["wall_s"],
                    "speedup": u["wall_s"] / f["wall_s"], "sample_ratio": sample_ratio,
                    "speedup_over_ratio": u["wall_s"] / f["wall_s"] / sample_ratio,
                    "cost_weighted_ratio": cost_ratio,
                    "render_speedup": u["timing"]["render_s"] / f["timing"]["render_s"],
                    "decision_share": (t["features_s"] + t["decisions_s"]) / f["wall_s"],
                    "timing": t, "render_calls": f["render_calls"],
                    "uniform_render_s": u["timing"]["render_s"]})
    return out


def bench_passes(repeats: int = 3) -> dict[str, Any]:
    return {"passes": pass_cost(repeats), "decisions": decision_cost(), "renders": render_scaling()}


def md_passes(r: dict[str, Any]) -> str:
    p = r["passes"]
    lines = [f"One pass of {p['spp']} spp on {p['scene']} at {p['resolution']}, {p['block']}-px blocks, "
             "against the active pixels it traces (median of 3, warm):", "",
             "| engine | " + " | ".join(f"{row['blocks']} blocks" for row in p["engines"]["wavefront"]["rows"])
             + " | constant per pass | per pixel-sample | R^2 of the line |",
             "|---|" + "---|" * (len(p["engines"]["wavefront"]["rows"]) + 3)]
    for name, e in p["engines"].items():
        lines.append(f"| {name} | " + " | ".join(f"{row['seconds']:.3f} s" for row in e["rows"])
                     + f" | {e['constant_s'] * 1e3:.1f} ms | {e['ns_per_pixel_sample']:.0f} ns | {e['r2']:.3f} |")
    d = r["decisions"]
    lines += ["", "The flip criterion's decision time against the blocks judged in one call (64x64 blocks):", "",
              "| blocks | " + " | ".join(str(row["blocks"]) for row in d["rows"]) + " |",
              "|---|" + "---|" * len(d["rows"]),
              "| ms per block | " + " | ".join(f"{row['ms_per_block']:.2f}" for row in d["rows"]) + " |"]
    lines += ["", "Adaptive renders (flip) against uniform sampling to the same max spp (goal: speed-up >= 0.9x "
              "the sample ratio; features + decisions < 2 % of wall time at 256x256, step 32):", "",
              "| scene | frame | blocks | step / max spp | saved | sample ratio | cost-weighted ratio | flip wall "
              "| uniform wall | speed-up | speed-up / sample ratio | render time only: speed-up / cost-weighted "
              "ratio | features + decisions |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["renders"]:
        w, h = x["resolution"]
        lines.append(f"| {x['scene']} | {w}x{h} | {x['blocks']} | {x['step']} / {x['max_spp']} "
                     f"| {100 * x['saved_vs_uniform']:.0f} % | {x['sample_ratio']:.2f}x | {x['cost_weighted_ratio']:.2f}x "
                     f"| {x['flip_wall_s']:.1f} s | {x['uniform_wall_s']:.1f} s | {x['speedup']:.2f}x "
                     f"| {x['speedup_over_ratio']:.2f} | {x['render_speedup'] / x['cost_weighted_ratio']:.2f} "
                     f"| {100 * x['decision_share']:.1f} % |")
    lines += ["", "Cost-weighted ratio: uniform's render time over the time of the samples the adaptive "
              "render spent, each block's samples weighted by that block's own cost per sample (measured "
              "alone): the speed-up the samples saved can buy when blocks differ in cost."]
    return "\n".join(lines)


def bench_render(scene: str = "env_spheres", resolution: int = 256, max_spp: int = 640,
                 step: int = 16, model: str | None = None, repeats: int = 3) -> dict[str, Any]:
    """Real renders: the model and flip criteria against uniform sampling to the same max
    spp (warm).

    The runs alternate `repeats` times and each reports its median run, so that a
    passing disturbance on the machine does not decide the speed-up.
    """
    import tempfile

    from learning.models.bundle import load_model
    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import FlipCriterion, ModelCriterion, UniformCriterion
    runs: dict[str, list[dict]] = {"model": [], "flip": [], "uniform": []}
    m = load_model(model)
    with tempfile.TemporaryDirectory() as tmp:
        # warm-up: every block's kernel compiled once (Dr.Jit caches them), so neither timed
        # run pays compilation and their order does not matter
        adaptive_render(scene, Path(tmp) / "warm", UniformCriterion(), resolution=resolution,
                        step=step, min_spp=step, max_spp=step, progress=False)
        for i in range(repeats):
            for name, crit in (("model", ModelCriterion(m)), ("flip", FlipCriterion()),
                               ("uniform", UniformCriterion())):
                rep = adaptive_render(scene, Path(tmp) / f"{name}{i}", crit, resolution=resolution,
                                      step=step, min_spp=step, max_spp=max_spp, progress=False)
                runs[name].append({"wall_s": rep["wall_s"], "saved_vs_uniform": rep["saved_vs_uniform"],
                                   "timing": rep.get("timing")})
    out = {name: {**sorted(r, key=lambda x: x["wall_s"])[len(r) // 2],
                  "walls_s": [x["wall_s"] for x in r]} for name, r in runs.items()}
    for name in ("model", "flip"):
        t = out[name]["timing"] or {}
        decide = float(t.get("features_s", 0) + t.get("decisions_s", 0))
        out[name]["speedup_vs_uniform"] = out["uniform"]["wall_s"] / out[name]["wall_s"]
        out[name]["decision_share"] = decide / out[name]["wall_s"]
    return {"scene": scene, "resolution": resolution, "max_spp": max_spp, "repeats": repeats, **out}


def md_render(r: dict[str, Any]) -> str:
    u = r["uniform"]

    def walls(x: dict) -> str:
        return ", ".join(f"{w:.1f}" for w in x.get("walls_s", [x["wall_s"]]))
    lines = [f"{r['scene']} at {r['resolution']}x{r['resolution']}, max {r['max_spp']} spp:", "",
             f"| run | wall (s), median of {r.get('repeats', 1)} | all runs (s) | saved vs uniform "
             "| speed-up vs uniform | features + decisions, share of wall time |", "|---|---|---|---|---|---|"]
    for name in ("model", "flip"):
        m = r[name]
        lines.append(f"| {name} criterion | {m['wall_s']:.1f} | {walls(m)} | {m['saved_vs_uniform']:.3f} "
                     f"| {m['speedup_vs_uniform']:.2f}x | {100 * m['decision_share']:.2f} % |")
    lines.append(f"| uniform to max spp | {u['wall_s']:.1f} | {walls(u)} | 0 | 1 | - |")
    return "\n".join(lines)


def bench_oracle(repeats: int = 3) -> dict[str, Any]:
    """Per-sample cost of a pass with one block active, and the oracle's speed-up over
    uniform (`sample_cost`, `oracle_speedup`), with the load average before and after."""
    import os

    load = [os.getloadavg()]
    cost = sample_cost(repeats)
    load.append(os.getloadavg())
    oracle = oracle_speedup(repeats)
    load.append(os.getloadavg())
    return {"sample_cost": cost, "oracle": oracle, "load": [list(x) for x in load]}


def md_oracle(r: dict[str, Any]) -> str:
    c = r["sample_cost"]
    load = ", ".join(f"{x[0]:.1f}" for x in r["load"])
    lines = [f"Load average (1 min) at the start, between and at the end: {load} (2 cores).", "",
             f"A pass of {c['spp']} spp on {c['scene']} at {c['resolution']}x{c['resolution']} ({c['grid'][0]}x"
             f"{c['grid'][1]} blocks): all blocks in one launch took {c['all_blocks_s']:.2f} s (median of "
             f"{c['repeats']}). One block alone, each block in turn, k passes of it per launch (interleaved, "
             "median per block, mean over the blocks); goal: time per pixel-sample with 1 of 16 blocks "
             "active <= 1.15x that with all 16:", "",
             "| passes per launch | lanes per launch | one block, per pass (wall) | per pixel-sample vs all 16 "
             "active: wall | CPU time |", "|---|---|---|---|---|"]
    for row in c["rows"]:
        lines.append(f"| {row['steps_per_launch']} | {row['lanes']:,} | {row['one_block_s'] * 1e3:.0f} ms "
                     f"| {row['ratio']:.2f}x | {row.get('cpu_ratio', float('nan')):.2f}x |")
    lines += ["", f"Blocks differ in cost: the dearest costs {c['block_cost_spread']:.1f}x the cheapest per sample.",
              "", "Oracle stops against uniform sampling to the same max spp (step 32, 4x4 blocks, the "
              "thresholds of `ORACLE_THRESHOLDS`; runs interleaved, speed-up = median over the repeats of "
              "uniform / oracle run back to back; CPU time counts every thread of the process, so load "
              "moves it little); goal: speed-up >= 0.9x the sample ratio on the Cornell box; env_spheres "
              "against the cost-weighted ratio:", "",
              "| scene | oracle wall (s) | uniform wall (s) | speed-up: wall | CPU time | sample ratio "
              "| speed-up / sample ratio: wall | CPU | cost-weighted ratio | speed-up / cost-weighted ratio: wall "
              "| CPU | block cost spread | launches | lanes per launch |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["oracle"]:
        rc = x["render_calls"]
        lines.append(f"| {x['scene']} {x['resolution']}x{x['resolution']}, max {x['max_spp']} "
                     f"| {', '.join(f'{w:.1f}' for w in x['oracle_wall_s'])} "
                     f"| {', '.join(f'{w:.1f}' for w in x['uniform_wall_s'])} | {x['speedup']:.2f}x "
                     f"| {x['cpu_speedup']:.2f}x | {x['sample_ratio']:.2f}x | {x['speedup_over_ratio']:.2f} "
                     f"| {x['cpu_speedup_over_ratio']:.2f} | {x['cost_weighted_ratio']:.2f}x "
                     f"| {x['speedup_over_cost_ratio']:.2f} | {x['cpu_speedup_over_cost_ratio']:.2f} "
                     f"| {x['block_cost_spread']:.1f}x "
                     f"| {rc['kernel_launches']} | {rc['kernel_lanes'] / max(rc['kernel_launches'], 1):,.0f} |")
    return "\n".join(lines)
