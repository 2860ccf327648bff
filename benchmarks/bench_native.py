"""`noisestop bench native`: our loops against `mi.render`, the renderer users already have.

Users compare us with ``mi.render(scene, spp=N)``, not with our own uniform loop. For each
case (Mitsuba's ``cornell_box()`` and the held-out ``spot_stage``), on the device of the
variant in use (the CPU with ``llvm_ad_rgb``, the GPU with ``cuda_ad_rgb``), one run gives:

* wall time to the same spp: ``mi.render`` in one call, our uniform loop, the adaptive loop
  (flip at tau) with grown passes and with a fixed step, and the share of the adaptive wall
  time that is not rendering (decisions + overhead);
* at equal wall time: ``mi.render`` with the samples it can trace in the adaptive render's
  wall time, against the adaptive image: worst and mean block error (DESIGN's observer:
  the largest 16x16-tile FLIP of each 64x64 block) against a reference, and the blocks
  above tau;
* time to target: the first wall time at which every block is at or below tau (``mi.render``:
  a sweep of spp, doubling; adaptive: its own stop, with max spp raised to the sweep's top).

Everything is warm (one small render of each kind first). Run it from a source checkout:
``noisestop bench native`` or, on a machine without the command, ``python -m
benchmarks.bench_native --json out.json``.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

BLOCK, STEP, MIN_SPP = 64, 16, 16
#: mi.render calls trace at most this many samples per pixel at once (larger counts are
#: split into calls of this size with their own seeds and averaged)
CHUNK_SPP = 1024


@dataclass(frozen=True)
class Case:
    """One comparison: `scene` 'cornell_box' (Mitsuba's) or a built-in name, its film size,
    the max spp both sides render to, the reference's spp (0: the shipped reference) and
    the top of the time-to-target sweep."""

    scene: str
    size: int
    max_spp: int
    ref_spp: int
    sweep_max: int


#: sized for 2 CPU cores (about 15 minutes in all) and for one H100/H200 (about 4 minutes)
CASES = {
    "cpu": (Case("cornell_box", 512, 256, 1024, 512), Case("spot_stage", 256, 256, 0, 1024)),
    "cuda": (Case("cornell_box", 1024, 1024, 8192, 4096), Case("spot_stage", 1024, 1024, 8192, 4096)),
}
#: the cold row's (size, max spp) per device
COLD = {"cpu": (256, 1024), "cuda": (1024, 1024)}


def load_case_scene(case: Case) -> Any:
    """The case's scene at its size (Mitsuba's cornell_box dict, or a built-in scene)."""
    import mitsuba as mi

    if case.scene == "cornell_box":
        d = mi.cornell_box()
        d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = case.size
        return mi.load_dict(d)
    from renderer.scenes.catalog import load_scene

    return load_scene(case.scene, case.size)


def mi_render(scene: Any, spp: int, seed: int) -> tuple[np.ndarray, float]:
    """(image [H, W, 3] float32, wall seconds) of ``mi.render`` to `spp`, in calls of at most
    CHUNK_SPP (averaged), the image read back to the host as users do."""
    import mitsuba as mi

    t0 = time.perf_counter()
    parts, left, k = [], int(spp), 0
    while left > 0:
        n = min(CHUNK_SPP, left)
        parts.append((np.asarray(mi.render(scene, spp=n, seed=seed * 7919 + k), np.float32)[..., :3], n))
        left -= n
        k += 1
    image = sum(img.astype(np.float64) * n for img, n in parts) / float(spp)
    return image.astype(np.float32), time.perf_counter() - t0


def _dots(x: dict[str, Any]) -> str:
    """The most dots a stopped block holds, and how many stopped blocks hold more than 16."""
    if "max_stopped_dots" not in x:
        return ""
    return f"{x['max_stopped_dots']} ({x['dotted_stopped_blocks']} over 16)"


def block_errors(image: np.ndarray, reference: np.ndarray, tau: float,
                 stopped: list[bool] | None = None) -> dict[str, Any]:
    """DESIGN's observer per 64x64 block of `image` against `reference`: worst, mean, above
    tau; with the blocks a criterion `stopped`, the most dots one of them holds and how many
    hold more than 16 (none may)."""
    from renderer.live.report import final_vs_reference

    h, w = image.shape[:2]
    grid = (h // BLOCK, w // BLOCK)
    r = final_vs_reference(image, reference, grid, tau, stopped=stopped)
    out = {"worst": r["worst_error"], "mean": r["mean_error"], "above_tau": r["visible_noise_blocks"],
           "blocks": len(r["errors"])}
    if stopped is not None:
        out.update(max_stopped_dots=r["max_stopped_dots"], dotted_stopped_blocks=r["dotted_stopped_blocks"])
    return out


def ours(scene: Any, criterion: str, max_spp: int, tau: float, grow: bool = True,
         tile: int | None = None) -> dict[str, Any]:
    """One render by our loop: wall, render time, mean spp, image. `tile`: the grain (None:
    the render's default, 16-pixel tiles; BLOCK: whole blocks, the block-grain loop)."""
    from renderer.live.adaptive import run_adaptive

    t0 = time.perf_counter()            # the whole call, as a user times it (report and image included)
    r = run_adaptive(scene, criterion, block=BLOCK, step=STEP, min_spp=MIN_SPP, max_spp=max_spp, progress=False,
                     tau=tau, grow=grow, tile=tile)
    wall = time.perf_counter() - t0
    t = r.report["timing"]
    return {"wall_s": wall, "render_s": float(t.get("render_s", 0.0)),
            "decisions_s": float(t.get("decisions_s", 0.0)) + float(t.get("features_s", 0.0)),
            "overhead_s": float(t.get("overhead_s", 0.0)) + float(t.get("setup_s", 0.0)),
            "mean_spp": float(r.report["mean_spp"]),
            "launches": int(r.report["render_calls"]["kernel_launches"]), "image": r.image,
            "stopped": [bool(b["converged"]) for b in r.report["blocks"]]}


def reference_image(case: Case, scene: Any) -> tuple[np.ndarray, str]:
    """The case's reference: the shipped one (ref_spp 0) or mi.render at ref_spp (seed apart)."""
    if case.ref_spp == 0:
        from examples.showcase import shipped_reference

        ref = shipped_reference(case.scene)
        if ref is None:
            raise ValueError(f"{case.scene}: no shipped reference; give the case a ref_spp")
        return ref.astype(np.float32), "shipped (8192 spp)"
    return rendered_reference(scene, case.ref_spp)


def rendered_reference(scene: Any, spp: int, keep: Path | None = None) -> tuple[np.ndarray, str]:
    """(image, where it came from): mi.render at `spp`, seed 1000, which no render it judges
    uses; with `keep` (an EXR path), read from there when a run before left it, else
    written there (minutes of rendering saved on the next run)."""
    from learning.data.exr import read_exr, write_exr

    if keep is not None and keep.is_file():
        return read_exr(keep).astype(np.float32), f"mi.render {spp} spp (cached {keep})"
    ref, secs = mi_render(scene, spp, seed=1000)
    if keep is not None:
        keep.parent.mkdir(parents=True, exist_ok=True)
        write_exr(keep, ref)
    return ref, f"mi.render {spp} spp ({secs:.0f} s)"


def measure_case(case: Case, tau: float, repeats: int = 3, walls_only: bool = False) -> dict[str, Any]:
    """Every figure of one case (see the module docstring); `walls_only`: the wall times to
    the same spp alone (no reference, no errors: a short run on a lent GPU)."""
    scene = load_case_scene(case)
    # warm: compile mi.render's kernel, our tracer's and FLIP's, at a small spp
    mi_render(scene, 16, seed=99)
    ours(scene, "uniform", 32, tau)
    ours(scene, "flip", 32, tau)
    ref, ref_source = (None, "none (wall times only)") if walls_only else reference_image(case, scene)
    out: dict[str, Any] = {"case": asdict(case), "tau": tau, "reference": ref_source}

    # wall time to the same spp: the four runs interleaved, `repeats` times, medians kept
    # (a machine's speed drifts by 10-20 % between minutes: one run each would measure that)
    runs: dict[str, list[dict[str, Any]]] = {"mi_render": [], "uniform": [], "adaptive": [], "adaptive_fixed_step": [],
                                             "adaptive_block": []}
    for _ in range(repeats):
        img, t_mi = mi_render(scene, case.max_spp, seed=1)
        runs["mi_render"].append({"wall_s": t_mi, "image": img})
        runs["uniform"].append(ours(scene, "uniform", case.max_spp, tau))
        runs["adaptive"].append(ours(scene, "flip", case.max_spp, tau, grow=True))
        runs["adaptive_fixed_step"].append(ours(scene, "flip", case.max_spp, tau, grow=False))
        runs["adaptive_block"].append(ours(scene, "flip", case.max_spp, tau, tile=BLOCK))     # the block-grain baseline
    for name, rs in runs.items():
        walls = [r["wall_s"] for r in rs]
        med = rs[int(np.argsort(walls)[len(walls) // 2])]
        out[name] = {k: v for k, v in med.items() if k not in ("image", "stopped")} | {"walls_s": walls} | \
            ({} if ref is None else block_errors(rs[0]["image"], ref, tau, rs[0].get("stopped")))
    if ref is None:
        return out
    t_mi = out["mi_render"]["wall_s"]
    ada, fixed = runs["adaptive"][0], runs["adaptive_fixed_step"][0]
    ada = {**ada, "wall_s": out["adaptive"]["wall_s"]}
    # grown passes change no sample: the images agree to float rounding (splat order)
    out["grown_vs_fixed_max_diff"] = float(np.abs(ada["image"] - fixed["image"]).max())

    # equal wall time: the samples mi.render traces in the adaptive render's time
    per_spp = t_mi / case.max_spp
    spp_eq = max(1, int(ada["wall_s"] / per_spp))
    eq, t_eq = mi_render(scene, spp_eq, seed=2)
    out["mi_render_equal_time"] = {"spp": spp_eq, "wall_s": t_eq, **block_errors(eq, ref, tau)}

    # time to target: mi.render progressively (calls adding samples, the estimates averaged),
    # read at every doubling of spp; then the adaptive render's own stop
    sweep, target = [], None
    total, wall, spp, acc = 0, 0.0, 64, None
    while spp <= case.sweep_max:
        img, t = mi_render(scene, spp - total, seed=3 + spp)
        acc = img.astype(np.float64) * (spp - total) + (0.0 if acc is None else acc)
        total, wall = spp, wall + t
        e = block_errors((acc / total).astype(np.float32), ref, tau)
        sweep.append({"spp": spp, "wall_s": wall, "worst": e["worst"], "above_tau": e["above_tau"]})
        if e["above_tau"] == 0:
            target = {"spp": spp, "wall_s": wall}
            break
        spp *= 2
    out["mi_render_sweep"] = sweep
    out["mi_render_time_to_target"] = target
    if out["adaptive"]["above_tau"] == 0:
        out["adaptive_time_to_target"] = {"max_spp": case.max_spp, "wall_s": ada["wall_s"],
                                          "mean_spp": ada["mean_spp"]}
    else:
        far = ours(scene, "flip", case.sweep_max, tau)
        e = block_errors(far["image"], ref, tau)
        out["adaptive_time_to_target"] = {"max_spp": case.sweep_max, "wall_s": far["wall_s"],
                                          "mean_spp": far["mean_spp"], "worst": e["worst"],
                                          "above_tau": e["above_tau"], "reached": e["above_tau"] == 0}
    return out


def bench_native(tau: float | None = None, cases: tuple[Case, ...] | None = None,
                 on_case: Any = None, repeats: int = 3, walls_only: bool = False, cold: bool = True) -> dict[str, Any]:
    """Every case of the variant's device (`CASES`), with the device named, then the cold row
    (`benchmarks.bench_cold`: fresh processes, `noisestop render` against a plain `mi.render`
    script); `on_case(result)` after each (so a run cut short keeps what it measured)."""
    from learning.data.variant import select_variant
    from learning.names import DEFAULT_TAU

    from renderer.plugin import register

    variant = select_variant()
    register()
    kind = "cuda" if variant.startswith("cuda") else "cpu"
    out = {"variant": variant, "device": device_name(kind), "tau": tau or DEFAULT_TAU, "cases": []}
    for c in cases or CASES[kind]:
        log.info("bench native: %s %dx%d on %s", c.scene, c.size, c.size, out["device"])
        out["cases"].append(measure_case(c, tau or DEFAULT_TAU, repeats, walls_only))
        if on_case is not None:
            on_case(out)
    if cold:
        from .bench_cold import cold_row

        log.info("bench native: cold start, Mitsuba's Cornell box %dx%d", *COLD[kind][:1] * 2)
        out["cold"] = cold_row(*COLD[kind], variant=variant, repeats=repeats)
        if on_case is not None:
            on_case(out)
    return out


def device_name(kind: str) -> str:
    """The GPU's name, or the CPU's model and core count (what BENCHMARKS labels figures by)."""
    if kind == "cuda":
        import torch

        return torch.cuda.get_device_name(0)
    import os

    model = "CPU"
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} cores"


def _f(x: float | None, fmt: str = "{:.1f} s") -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt.format(x)


def _runs(x: dict[str, Any]) -> str:
    walls = x.get("walls_s")
    return "" if not walls or len(walls) < 2 else "(" + ", ".join(f"{w:.2f}" for w in walls) + ")"


def _md_walls(c: dict[str, Any]) -> list[str]:
    """A walls-only case: wall time to the same spp, medians of interleaved runs."""
    case, m = c["case"], c["mi_render"]
    lines = ["", f"**{case['scene']} {case['size']}x{case['size']}**, max {case['max_spp']} spp, wall times only.", "",
             "| run | wall | vs mi.render | mean spp | launches | not rendering |", "|---|---|---|---|---|---|",
             f"| `mi.render`, {case['max_spp']} spp | {m['wall_s']:.2f} s {_runs(m)} | 1.00x | {case['max_spp']} | | |"]
    for name, key in (("our uniform loop", "uniform"), ("adaptive (flip), grown passes", "adaptive"),
                      ("adaptive (flip), fixed step", "adaptive_fixed_step"),
                      ("adaptive (flip), whole blocks", "adaptive_block")):
        if key not in c:
            continue
        x = c[key]
        other = max(0.0, x["wall_s"] - x["render_s"])
        lines.append(f"| {name} | {x['wall_s']:.2f} s {_runs(x)} | {x['wall_s'] / m['wall_s']:.2f}x "
                     f"| {x['mean_spp']:.0f} | {x['launches']} | {other:.2f} s "
                     f"({100 * other / max(x['wall_s'], 1e-9):.1f} %) |")
    return lines


def md_native(r: dict[str, Any]) -> str:
    """BENCHMARKS.md section: one table per case, labelled with the device."""
    cold = md_cold(r["cold"]) if "cold" in r else []
    lines = [f"Device: **{r['device']}**, variant `{r['variant']}`, tau {r['tau']:g}, {BLOCK}-px blocks, step "
             f"{STEP}, flip criterion. Errors: DESIGN's observer (largest 16x16-tile FLIP per block) against the "
             "reference. Wall times are warm; the first four rows are medians of runs interleaved with each "
             "other (all runs in brackets)."]
    for c in r["cases"]:
        if "mi_render_equal_time" not in c:
            lines += _md_walls(c)
            continue
        case, m = c["case"], c["mi_render"]
        ada, fixed, uni, eq = c["adaptive"], c["adaptive_fixed_step"], c["uniform"], c["mi_render_equal_time"]
        n = m["blocks"]
        lines += ["", f"**{case['scene']} {case['size']}x{case['size']}**, max {case['max_spp']} spp, reference: "
                  f"{c['reference']}.", "",
                  "| run | wall | vs mi.render | mean spp | launches | not rendering | worst block | mean block "
                  "| blocks above tau | most dots in a stopped block |", "|---|---|---|---|---|---|---|---|---|---|",
                  f"| `mi.render`, {case['max_spp']} spp | {m['wall_s']:.2f} s {_runs(m)} | 1.00x | {case['max_spp']} "
                  f"| | | {m['worst']:.4f} | {m['mean']:.4f} | {m['above_tau']} of {n} | |"]
        for name, x in (("our uniform loop", uni), ("adaptive (flip), 16-px tiles, grown passes", ada),
                        ("adaptive (flip), 16-px tiles, fixed step", fixed),
                        *((("adaptive (flip), whole 64-px blocks", c["adaptive_block"]),) if "adaptive_block" in c
                          else ())):
            other = max(0.0, x["wall_s"] - x["render_s"])
            lines.append(f"| {name} | {x['wall_s']:.2f} s {_runs(x)} | {x['wall_s'] / m['wall_s']:.2f}x "
                         f"| {x['mean_spp']:.0f} "
                         f"| {x['launches']} | {other:.2f} s ({100 * other / max(x['wall_s'], 1e-9):.1f} %) "
                         f"| {x['worst']:.4f} | {x['mean']:.4f} | {x['above_tau']} | {_dots(x)} |")
        lines.append(f"| `mi.render` at the adaptive wall time | {eq['wall_s']:.2f} s | | {eq['spp']} | | "
                     f"| {eq['worst']:.4f} | {eq['mean']:.4f} | {eq['above_tau']} | |")
        t_mi, t_ad = c["mi_render_time_to_target"], c["adaptive_time_to_target"]
        mi_txt = f"{t_mi['wall_s']:.1f} s ({t_mi['spp']} spp)" if t_mi else \
            f"not reached by {case['sweep_max']} spp"
        ad_ok = t_ad.get("reached", True)
        ad_txt = (f"{t_ad['wall_s']:.1f} s (max {t_ad['max_spp']}, mean {t_ad['mean_spp']:.0f} spp)" if ad_ok else
                  f"not reached by max {t_ad['max_spp']} spp ({t_ad['wall_s']:.1f} s, worst {t_ad['worst']:.4f}, "
                  f"{t_ad['above_tau']} above)")
        sweep = ", ".join(f"{s['spp']}: {s['wall_s']:.1f} s / {s['above_tau']} above" for s in c["mi_render_sweep"])
        lines += ["", f"Time to target (every block at or below tau): `mi.render` {mi_txt}; adaptive {ad_txt}. "
                  f"Sweep (progressive): {sweep}. Largest pixel difference between the grown and the "
                  f"fixed-step image: {c['grown_vs_fixed_max_diff']:.2g}."]
    return "\n".join(lines + cold)


def md_cold(c: dict[str, Any]) -> list[str]:
    """The cold row: each command from a fresh process to its files, broken down."""
    m, o = c["mi_render"], c["noisestop"]
    rest = o["wall_s"] - o["imports_s"] - o["report_wall_s"]
    return ["", f"**Cold start**: Mitsuba's Cornell box {c['size']}x{c['size']} as XML, max "
            f"{c['max_spp']} spp, each a fresh process from the command to its files written "
            f"(`benchmarks/bench_cold.py`); medians of {c.get('repeats', 1)} interleaved runs (walls: "
            + ", ".join(f"{r['noisestop']['wall_s']:.2f}/{r['mi_render']['wall_s']:.2f} s" for r in c.get("runs", []))
            + ", ours/the script).", "",
            "| command | wall | vs the script | breakdown |", "|---|---|---|---|",
            f"| plain `mi.render` script, {c['max_spp']} spp | {m['wall_s']:.2f} s | 1.00x | import "
            f"{m['import_s']:.2f}, variant {m['variant_s']:.2f}, load {m['load_s']:.2f}, render (compile "
            f"included) {m['render_s']:.2f}, write {m['write_s']:.2f} s |",
            f"| `noisestop render` (flip), mean {o['mean_spp']:.0f} spp | {o['wall_s']:.2f} s | {c['ratio']:.2f}x | "
            f"imports {o['imports_s']:.2f}; the render's own wall {o['report_wall_s']:.2f} (setup "
            f"{o.get('setup_s', 0):.2f}, render {o.get('render_s', 0):.2f}, decisions "
            f"{o.get('decisions_s', 0) + o.get('features_s', 0):.2f}, overhead {o.get('overhead_s', 0):.2f}); the "
            f"rest (variant, scene load, outputs, process) {rest:.2f} s; samples traced "
            f"{o.get('traced_vs_spent', 1.0):.3f}x those kept |"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", default=None, help="write the results here")
    p.add_argument("--tau", type=float, default=None)
    p.add_argument("--repeats", type=int, default=3, help="interleaved runs of each timed render (medians)")
    p.add_argument("--walls-only", action="store_true",
                   help="wall times to the same spp only (no reference, errors or sweep)")
    p.add_argument("--update", default=None, metavar="FILE",
                   help="rewrite FILE's section native (CPU) or native_gpu (GPU) with the results")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    def save(r: dict[str, Any]) -> None:
        if args.json:
            with open(args.json, "w", encoding="utf-8") as f:
                json.dump(r, f, indent=1)
        if args.update:
            from .marked_sections import update_markdown

            update_markdown(Path(args.update), {"native_gpu" if r["variant"].startswith("cuda") else "native":
                                                md_native(r)})
        print(md_native(r), flush=True)

    bench_native(args.tau, on_case=save, repeats=max(1, args.repeats), walls_only=args.walls_only)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
