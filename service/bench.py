"""`noisestop bench`: the speed figures of BENCHMARKS.md, measured on this machine.

Every figure is a median over repeats after a warm-up call; the accuracy cost of each
speed choice is reported beside it (e.g. the spectral feature route vs torch.conv2d).
"""
from __future__ import annotations

import dataclasses
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch


def _median_s(fn: Callable[[], Any], repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def direct_macs(n: int, h: int, w: int, wavelet_taps: int = 2) -> int:
    """Multiply-adds of the feature base computed by its definition, spatially.

    12 convolutions (3x3, 5x5 alternating: 204 per pixel) plus the wavelet layer's
    analysis and synthesis (taps per axis, both axes, for the approximation band only).
    """
    per_pixel = sum(k * k for k in (3, 5) * 6) + 2 * wavelet_taps
    return n * h * w * per_pixel


def matmul_rate(macs: int, repeats: int) -> float:
    """Dense float32 matmul multiply-adds per second for a cube of about `macs`."""
    side = max(64, round(macs ** (1 / 3)))
    a, b = torch.rand(side, side), torch.rand(side, side)
    with torch.inference_mode():
        t = _median_s(lambda: a @ b, repeats)
    return side ** 3 / t


def bench_features(repeats: int = 30, n: int = 101, size: int = 128) -> dict[str, Any]:
    from noisefeat import FeatureBase, extract_features
    from noisefeat.display import lightness

    rng = np.random.default_rng(0)
    rgb = (rng.random((n, size, size, 3)) ** 2).astype(np.float32)
    base = FeatureBase().eval()
    with torch.inference_mode():
        L = lightness(torch.from_numpy(rgb))[:, None]
        t_base = _median_s(lambda: base(L), repeats)
        t_lightness = _median_s(lambda: lightness(torch.from_numpy(rgb)), repeats)
        fast = base(L)
        # The definition's own route (torch.conv2d, circular padding): slow, so timed once.
        t0 = time.perf_counter()
        outs = base.layer_outputs(L)
        means = torch.stack([(L - o)[:, 0].mean((-2, -1)) for o in outs], 1)
        stds = torch.stack([(L - o)[:, 0].std((-2, -1), correction=0) for o in outs], 1)
        t_direct = time.perf_counter() - t0
    slow = torch.cat([means, stds], 1)
    t_extract = _median_s(lambda: extract_features(rgb, base=base), repeats)
    macs = direct_macs(n, size, size)
    rate = matmul_rate(macs, repeats)
    t_matmul = macs / rate
    return {
        "blocks": n, "block_size": size, "threads": torch.get_num_threads(),
        "feature_base_ms": t_base * 1e3,
        "lightness_ms": t_lightness * 1e3,
        "extract_features_ms": t_extract * 1e3,
        "direct_conv2d_ms": t_direct * 1e3,
        "direct_macs": macs,
        "matmul_gmacs": rate / 1e9,
        "matmul_same_macs_ms": t_matmul * 1e3,
        "feature_base_vs_matmul": t_base / t_matmul,
        "spectral_vs_conv2d_max_abs_diff": float((fast - slow).abs().max()),
        "spectral_vs_conv2d_max_rel_diff": float(((fast - slow).abs() / (slow.abs() + 1e-3)).max()),
        "goal_ms": 10.0, "goal_ratio": 3.0,
    }


def bench_crop(repeats: int = 3) -> dict[str, Any]:
    from renderer.blocks import measure_crop_cost
    return measure_crop_cost(repeats=repeats)


def bench_models(data: str, out_dir: Path, arches: tuple[str, ...] | None = None,
                 kinds: tuple[str, ...] | None = None, quick: str = "albedo") -> dict[str, Any]:
    from learning.compare import TRANSFER_ARCHES, compare_models
    from learning.train import SVM_KINDS
    result = compare_models(data, out_dir, arches=TRANSFER_ARCHES if arches is None else arches,
                            kinds=SVM_KINDS if kinds is None else kinds, quick=quick)
    result.pop("fitted")
    return result


def bench_criteria(data: str, model: str | None = None, max_early_stop: float = 0.05,
                   thresholds: tuple[float, ...] = (0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2)) -> dict[str, Any]:
    """Criteria simulated on held-out scenes; variance's threshold tuned on training scenes."""
    from learning.bundle import load_model
    from learning.stack import list_stacks, read_stack
    from renderer.criteria import ModelCriterion, OracleCriterion, UniformCriterion, VarianceCriterion
    from renderer.simulate import evaluate_criterion

    m = load_model(model)
    stacks = [read_stack(p) for p in list_stacks(data)]
    held = set(m.manifest.get("training", {}).get("test_scenes") or [])
    if not held:
        from learning.train import default_test_scenes
        held = set(default_test_scenes([s.scene for s in stacks]))
    train = [s for s in stacks if s.scene not in held]
    test = [s for s in stacks if s.scene in held]
    keys = ("precision", "early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform")

    def run(stk, factory):
        r = evaluate_criterion(stk, factory)
        return {k: r[k] for k in keys}
    sweep = [{"threshold": t, "train": run(train, lambda st, t=t: VarianceCriterion(threshold=t)),
              "test": run(test, lambda st, t=t: VarianceCriterion(threshold=t))} for t in thresholds]
    ok = [r for r in sweep if r["train"]["early_stop_rate"] <= max_early_stop]
    tuned = max(ok, key=lambda r: r["threshold"]) if ok else min(sweep, key=lambda r: r["train"]["early_stop_rate"])
    rows = {
        f"model ({m.name}, offset {m.offset:.2f})": run(test, lambda st: ModelCriterion(m)),
        f"variance (threshold {tuned['threshold']}, tuned on training scenes)": tuned["test"],
        "oracle": run(test, lambda st: OracleCriterion(st.thresholds)),
        "uniform": run(test, lambda st: UniformCriterion()),
    }
    return {"test_scenes": sorted(held), "rows": rows, "variance_sweep": sweep,
            "model_on_training_scenes": run(train, lambda st: ModelCriterion(m))}


def bench_render(scene: str = "env_spheres", resolution: int = 256, max_spp: int = 640,
                 step: int = 16, model: str | None = None) -> dict[str, Any]:
    """Real renders: the model criterion against uniform sampling to the same max spp (warm)."""
    import tempfile

    from learning.bundle import load_model
    from renderer.adaptive import adaptive_render
    from renderer.criteria import ModelCriterion, UniformCriterion
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        # warm-up: every block's kernel compiled once (Dr.Jit caches them), so neither timed
        # run pays compilation and their order does not matter
        adaptive_render(scene, Path(tmp) / "warm", UniformCriterion(), resolution=resolution,
                        step=step, min_spp=step, max_spp=step, progress=False)
        for name, crit in (("model", ModelCriterion(load_model(model))), ("uniform", UniformCriterion())):
            rep = adaptive_render(scene, Path(tmp) / name, crit, resolution=resolution, step=step,
                                  min_spp=step, max_spp=max_spp, progress=False)
            out[name] = {"wall_s": rep["wall_s"], "saved_vs_uniform": rep["saved_vs_uniform"],
                         "timing": rep.get("timing")}
    t = out["model"]["timing"] or {}
    decide = float(t.get("features_s", 0) + t.get("decisions_s", 0))
    return {"scene": scene, "resolution": resolution, "max_spp": max_spp, **out,
            "speedup_vs_uniform": out["uniform"]["wall_s"] / out["model"]["wall_s"],
            "decision_share": decide / out["model"]["wall_s"]}


def bench_service(clients: tuple[int, ...] = (1, 8, 32)) -> dict[str, Any]:
    from .loadtest import bench
    return {str(c): bench(None, clients=c, requests_per_client=max(2, 64 // c), max_seconds=60)
            for c in clients}


def bench_tradeoff(data: str, out_png: str = "docs/pareto.png", model: str | None = None,
                   thresholds: tuple[float, ...] = (0.01, 0.02, 0.05, 0.07, 0.1, 0.15, 0.2)) -> dict[str, Any]:
    """Samples (vs oracle) against early stops on held-out scenes: one curve per criterion.

    Models are swept over their decision offset (per-sub-image verdicts on the stored
    levels, first +1 stops the block), the variance criterion over its threshold (the
    criterion simulation); the oracle is the point (1, 0); the bundled default is marked.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from learning.bundle import load_model
    from learning.calibrate import DEFAULT_OFFSETS, sweep
    from learning.stack import list_stacks, read_stack
    from learning.table import load_table
    from learning.train import train_model
    from renderer.criteria import VarianceCriterion
    from renderer.simulate import evaluate_criterion

    bundled = load_model(model)
    test = list(bundled.manifest.get("training", {}).get("test_scenes") or [])
    if not test:
        raise ValueError("the model's manifest names no held-out scenes")
    curves: dict[str, list[dict]] = {}
    tables = {q: load_table(data, quick=q, progress=False) for q in ("none", "albedo")}
    entries = [(f"{bundled.name} quick {bundled.quick} (bundled)", bundled.estimator, bundled.quick)]
    for kind, quick in (("dsvm", "none"), ("dsvm_as", "albedo")):
        est, _ = train_model(kind, data, table=tables[quick], test_scenes=test, quick=quick,
                             progress=False)
        entries.append((f"{kind} quick {quick}", est, quick))
    for name, est, quick in entries:
        table = tables[quick]
        scores = np.full(len(table), np.nan)
        mask = table.scene_mask(test)
        scores[mask] = est.decision_function(table.X[mask])
        curves[name] = sweep(scores, table, DEFAULT_OFFSETS)
    stacks = [read_stack(p) for p in list_stacks(data)]
    held = [s for s in stacks if s.scene in test]
    var = []
    for t in thresholds:
        r = evaluate_criterion(held, lambda st, t=t: VarianceCriterion(threshold=t))
        var.append({"threshold": t, **{k: r[k] for k in ("early_stop_rate", "spp_ratio_vs_oracle",
                                                          "precision")}})
    default = next(r for r in curves[entries[0][0]] if abs(r["offset"] - bundled.offset) < 1e-9) \
        if any(abs(r["offset"] - bundled.offset) < 1e-9 for r in curves[entries[0][0]]) else None
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, rows in curves.items():
        ax.plot([r["spp_ratio_vs_oracle"] for r in rows], [r["early_stop_rate"] for r in rows],
                ".-", label=f"{name}, offset -1..3")
    ax.plot([r["spp_ratio_vs_oracle"] for r in var], [r["early_stop_rate"] for r in var], "s--",
            color="grey", label="variance (Cycles), threshold 0.01..0.2")
    ax.plot([1.0], [0.0], "k*", ms=14, label="oracle")
    if default is not None:
        ax.plot([default["spp_ratio_vs_oracle"]], [default["early_stop_rate"]], "o", ms=14,
                mfc="none", mec="red", mew=2, label=f"default (bundled, offset {bundled.offset:.2f})")
    ax.axhline(0.05, color="red", lw=0.6, ls=":")
    ax.set_xlabel("samples spent / oracle's samples (held-out scenes)")
    ax.set_ylabel("early-stop rate (blocks stopped with visible noise)")
    ax.set_title(f"speed / accuracy on held-out scenes: {', '.join(test)}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(out_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    tmp.replace(path)
    maps = spp_maps(bundled, tables[bundled.quick], test, path.with_name("spp-maps.png"))
    return {"test_scenes": test, "curves": curves, "variance": var, "default": default,
            "plot": str(path), "spp_maps": maps}


def spp_maps(model, table, scenes: list[str], out_png: Path) -> str:
    """Where the samples went, per held-out scene: the model's spp per block vs the oracle's."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from learning.evaluate import verdicts_by_scene
    from learning.metrics import stop_thresholds, true_thresholds

    sub = table.subset(table.scene_mask(scenes))
    per = verdicts_by_scene(sub, model.predict(sub.X))
    fig, axes = plt.subplots(2, len(per), figsize=(2.6 * len(per), 5.2), squeeze=False)
    for j, (scene, (v, _, th, spp)) in enumerate(sorted(per.items())):
        st = sub.stacks[scene]
        grid = tuple(st.grid)
        spent = np.minimum(stop_thresholds(v, spp), spp[-1]).reshape(grid)
        oracle = np.minimum(true_thresholds(th, spp), spp[-1]).reshape(grid)
        for i, (name, m) in enumerate((("model", spent), ("oracle", oracle))):
            ax = axes[i, j]
            ax.imshow(m, cmap="magma", vmin=0, vmax=spp[-1])
            for (r, c), val in np.ndenumerate(m):
                ax.text(c, r, str(int(val)), ha="center", va="center", fontsize=7,
                        color="white" if val < 0.6 * spp[-1] else "black")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{scene}: {name}, {int(m.sum())} spp", fontsize=8)
    fig.suptitle(f"spp per block, {model.name} (offset {model.offset:.2f}) vs oracle", fontsize=9)
    fig.tight_layout()
    tmp = out_png.with_name(out_png.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(out_png)
    return str(out_png)


def bench_ablation(data: str) -> dict[str, Any]:
    """DSVM on held-out scenes with parts of the feature pipeline switched: quick image
    (albedo / direct lighting / none, with its render time once per frame), conv weights (smoothing / pre-trained), wavelet layer (on / off: its
    two features dropped). Accuracy next to the cost of 101 sub-images' features."""
    from learning.bundle import Model
    from learning.evaluate import evaluate_model, time_101_sub_images
    from learning.table import QUICK_MODES, load_table
    from learning.train import train_model
    from noisefeat import FeatureBase

    rows = []
    wavelet_cols = [12, 25]                     # mean_13, std_13: the wavelet layer
    keep_no_wavelet = [i for i in range(26) if i not in wavelet_cols]
    quick_s = quick_image_cost()
    for weights in ("smoothing", "pretrained"):
        base = FeatureBase(weights).eval()
        for quick in QUICK_MODES:
            table = load_table(data, base=base, quick=quick, progress=False)
            for wavelet in (True, False):
                t = table if wavelet else dataclasses.replace(table, X=table.X[:, keep_no_wavelet])
                est, summary = train_model("dsvm", data, table=t, quick=quick, progress=False)
                model = Model(est, {"kind": "dsvm", "input": "features", "quick": quick})
                m = evaluate_model(model, t.subset(t.scene_mask(summary["test_scenes"])))
                cost = time_101_sub_images(model, tuple(next(iter(t.stacks.values())).block)) \
                    if wavelet else None
                rows.append({"weights": weights, "quick": quick, "wavelet": wavelet,
                             **{k: m[k] for k in ("precision", "f1", "early_stop_rate",
                                                  "spp_ratio_vs_oracle")}, "test_101_s": cost,
                             "quick_render_s": quick_s.get(quick, 0.0)})
    return {"rows": rows, "quick_scene": QUICK_COST_SCENE}


QUICK_COST_SCENE = ("cornell", 256, 16)      # scene, resolution, quick spp


def quick_image_cost() -> dict[str, float]:
    """Wall time of one warm quick image per kind (once per render, full frame)."""
    from renderer.blocks import QUICK_KINDS, BlockRenderer
    from renderer.scenes import load_scene
    scene, res, spp = QUICK_COST_SCENE
    br = BlockRenderer(load_scene(scene, res), (4, 4))
    out = {}
    for kind in QUICK_KINDS:
        br.quick_image(spp, kind=kind)                       # compile
        out[kind] = _median_s(lambda k=kind: br.quick_image(spp, kind=k), 3)
    return out


def bench_step(data: str, multiples: tuple[int, ...] = (1, 2, 4, 8), scene: str = "env_spheres",
               model: str | None = None, resolution: int = 256, max_spp: int = 640) -> dict[str, Any]:
    """Render step (spp per pass) against samples, early stops and wall time.

    Samples and early stops: the bundled model on the held-out stacks with a decision only
    every k-th level (step = k x the dataset's step). Wall time: real renders of `scene`.
    """
    import tempfile

    from learning.bundle import load_model
    from learning.evaluate import verdicts_by_scene
    from learning.metrics import evaluate_verdicts
    from learning.table import load_table
    from renderer.adaptive import adaptive_render
    from renderer.criteria import ModelCriterion

    m = load_model(model)
    test = list(m.manifest.get("training", {}).get("test_scenes") or [])
    table = load_table(data, quick=m.quick, progress=False)
    sub = table.subset(table.scene_mask(test))
    per = verdicts_by_scene(sub, m.predict(sub.X))
    rows = []
    for k in multiples:
        thinned = {s: (v[k - 1::k], lab[k - 1::k], th, list(spp)[k - 1::k]) for s, (v, lab, th, spp) in per.items()}
        r = evaluate_verdicts(thinned)
        step = list(next(iter(per.values()))[3])[0] * k
        with tempfile.TemporaryDirectory() as tmp:
            rep = adaptive_render(scene, Path(tmp), ModelCriterion(m), step=step, min_spp=step,
                                  max_spp=max_spp, resolution=resolution, progress=False)
        rows.append({"step": step, "early_stop_rate": r["early_stop_rate"],
                     "spp_ratio_vs_oracle": r["spp_ratio_vs_oracle"], "render_scene": scene,
                     "wall_s": rep["wall_s"], "saved_vs_uniform": rep["saved_vs_uniform"],
                     "passes": rep.get("passes")})
    return {"test_scenes": test, "rows": rows}


# --- markdown for BENCHMARKS.md --------------------------------------------------------
def md_features(f: dict[str, Any], variant: str) -> str:
    return "\n".join([
        f"Measured on this machine ({f['threads']} torch threads, Mitsuba variant {variant}), "
        f"{f['blocks']} sub-images of {f['block_size']}x{f['block_size']}, median of repeats:",
        "",
        "| what | time | goal |",
        "|---|---|---|",
        f"| feature base, L* blocks -> 26 features (spectral route) | {f['feature_base_ms']:.2f} ms | <= {f['goal_ms']:.0f} ms |",
        f"| display transform + L* (RGB -> L*) | {f['lightness_ms']:.2f} ms | |",
        f"| extract_features, linear RGB -> 26 features | {f['extract_features_ms']:.2f} ms | |",
        f"| the definition run with torch.conv2d (reference route) | {f['direct_conv2d_ms']:.0f} ms | |",
        f"| dense float32 matmul of the same {f['direct_macs'] / 1e6:.0f} M multiply-adds "
        f"({f['matmul_gmacs']:.1f} GMAC/s) | {f['matmul_same_macs_ms']:.2f} ms | |",
        f"| feature base time / matmul time | {f['feature_base_vs_matmul']:.2f} x | <= {f['goal_ratio']:.0f} x |",
        "",
        f"Accuracy cost of the spectral route against torch.conv2d: max abs difference "
        f"{f['spectral_vs_conv2d_max_abs_diff']:.1e}, max relative {f['spectral_vs_conv2d_max_rel_diff']:.1e} "
        "(float32 rounding; both compute the same circular convolutions).",
    ])


def md_crop(c: dict[str, Any]) -> str:
    rows = ["| key | value |", "|---|---|"]
    rows += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in c.items()]
    return "\n".join(rows)


def md_criteria(r: dict[str, Any]) -> str:
    lines = [f"Held-out scenes: {', '.join(r['test_scenes'])}; simulated on the stored stacks.", "",
             "| criterion | precision | early_stop_rate | samples / oracle | saved vs uniform |",
             "|---|---|---|---|---|"]
    for name, m in r["rows"].items():
        lines.append(f"| {name} | {m['precision']:.3f} | {m['early_stop_rate']:.3f} | "
                     f"{m['spp_ratio_vs_oracle']:.3f} | {m['saved_vs_uniform']:.3f} |")
    t = r["model_on_training_scenes"]
    lines += ["", f"The same model on its training scenes: early stops {t['early_stop_rate']:.3f}, "
              f"samples {t['spp_ratio_vs_oracle']:.3f} x oracle.", "",
              "Variance threshold sweep (training / held-out early stops and samples vs oracle):", "",
              "| threshold | train early stops | train samples | held-out early stops | held-out samples |",
              "|---|---|---|---|---|"]
    for row in r["variance_sweep"]:
        a, b = row["train"], row["test"]
        lines.append(f"| {row['threshold']} | {a['early_stop_rate']:.3f} | {a['spp_ratio_vs_oracle']:.3f} "
                     f"| {b['early_stop_rate']:.3f} | {b['spp_ratio_vs_oracle']:.3f} |")
    return "\n".join(lines)


def md_render(r: dict[str, Any]) -> str:
    m, u = r["model"], r["uniform"]
    return "\n".join([
        f"{r['scene']} at {r['resolution']}x{r['resolution']}, max {r['max_spp']} spp:", "",
        "| run | wall (s) | saved vs uniform |", "|---|---|---|",
        f"| model criterion | {m['wall_s']:.1f} | {m['saved_vs_uniform']:.3f} |",
        f"| uniform to max spp | {u['wall_s']:.1f} | 0 |", "",
        f"Speed-up {r['speedup_vs_uniform']:.2f}x (goal >= 2x); features + decisions "
        f"{100 * r['decision_share']:.2f} % of the model run's wall time (goal < 2 %)."])


def md_service(r: dict[str, Any]) -> str:
    lines = ["| clients | encoding | requests | req/s | blocks/s | p50 (ms) | p99 (ms) | errors |",
             "|---|---|---|---|---|---|---|---|"]
    for c, res in r.items():
        for enc in ("json", "binary"):
            x = res[enc]
            f = (lambda v: "-" if v is None else f"{v:.0f}")
            lines.append(f"| {c} | {enc} | {x['requests']} | {x['requests_per_s']:.2f} | "
                         f"{x['blocks_per_s']:.0f} | {f(x['p50_ms'])} | {f(x['p99_ms'])} | {x['errors']} |")
    first = next(iter(r.values()))
    return (f"16 blocks of 128x128 (+ quick) per request, model {first['model']}, loopback, "
            f"{first['cpus']} CPUs. Goal: p99 <= 25 ms at 8 clients with binary data, no errors "
            "at 32.\n\n" + "\n".join(lines))


def md_tradeoff(r: dict[str, Any]) -> str:
    lines = [f"![samples vs early stops]({r['plot']})", "",
             f"Where the samples went per held-out scene (default offset, spp per block): "
             f"![spp maps]({r['spp_maps']})", "",
             "| criterion | setting | early_stop_rate | samples / oracle |", "|---|---|---|---|"]
    for name, rows in r["curves"].items():
        for row in rows:
            if abs(round(row["offset"] * 2) - row["offset"] * 2) < 1e-9:  # every 0.5
                lines.append(f"| {name} | offset {row['offset']:.1f} | {row['early_stop_rate']:.3f} "
                             f"| {row['spp_ratio_vs_oracle']:.3f} |")
    for row in r["variance"]:
        lines.append(f"| variance | threshold {row['threshold']} | {row['early_stop_rate']:.3f} "
                     f"| {row['spp_ratio_vs_oracle']:.3f} |")
    return "\n".join(lines)


def md_ablation(r: dict[str, Any]) -> str:
    scene, res, spp = r["quick_scene"]
    lines = ["| conv weights | quick image | wavelet layer | precision | f1 | early_stop_rate "
             f"| samples / oracle | 101 sub-images (s) | quick image, {scene} {res}x{res} {spp} spp (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        cost = "-" if x["test_101_s"] is None else f"{x['test_101_s']:.4f}"
        lines.append(f"| {x['weights']} | {x['quick']} | {'on' if x['wavelet'] else 'off'} | "
                     f"{x['precision']:.3f} | {x['f1']:.3f} | {x['early_stop_rate']:.3f} | "
                     f"{x['spp_ratio_vs_oracle']:.3f} | {cost} | {x['quick_render_s']:.3f} |")
    return "\n".join(lines)


def md_step(r: dict[str, Any]) -> str:
    scene = r["rows"][0]["render_scene"]
    lines = [f"| step (spp per pass) | held-out early stops | held-out samples / oracle "
             f"| {scene}: wall (s) | {scene}: saved vs uniform | passes |", "|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(f"| {x['step']} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} "
                     f"| {x['wall_s']:.1f} | {x['saved_vs_uniform']:.3f} | {x['passes']} |")
    return "\n".join(lines)


def update_markdown(path: Path, sections: dict[str, str]) -> None:
    """Replace the text between <!-- bench:NAME --> and <!-- /bench:NAME --> markers."""
    text = path.read_text() if path.exists() else ""
    for name, body in sections.items():
        start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
        block = f"{start}\n{body}\n{end}"
        if start in text and end in text:
            i, j = text.index(start), text.index(end) + len(end)
            text = text[:i] + block + text[j:]
        else:
            text += f"\n{block}\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


# sections that need only a dataset: name -> (measure(data), markdown(result))
DATASET_SECTIONS = {"criteria": (bench_criteria, md_criteria), "tradeoff": (bench_tradeoff, md_tradeoff),
                    "ablation": (bench_ablation, md_ablation), "step": (bench_step, md_step)}
SECTIONS = ("features", "crop", "models", "render", "service", "stability", *DATASET_SECTIONS)


def run_all(repeats: int = 30, only: tuple[str, ...] = ("features", "crop"), data: str | None = None,
            out_dir: str = "out/bench", arches: tuple[str, ...] | None = None,
            kinds: tuple[str, ...] | None = None, quick: str = "albedo") -> dict[str, Any]:
    from renderer.variant import select_variant
    variant = select_variant()
    results: dict[str, Any] = {"variant": variant}
    markdown: dict[str, str] = {}
    if "features" in only:
        results["features"] = bench_features(repeats)
        markdown["features"] = md_features(results["features"], variant)
    if "crop" in only:
        results["crop"] = bench_crop(repeats=max(1, min(repeats, 3)))
        markdown["crop"] = md_crop(results["crop"])
    if "models" in only:
        if not data:
            raise ValueError("bench models needs --data DIR (a labelled dataset)")
        from learning.compare import markdown_table
        results["models"] = bench_models(data, Path(out_dir), arches, kinds, quick)
        m = results["models"]
        section = "models" if quick == "albedo" else f"models_quick_{quick}"
        from learning.plots import plot_cost_accuracy
        png = plot_cost_accuracy(m["rows"], f"docs/cost-accuracy-{quick}.png",
                                 f"decision cost vs precision, quick image {quick}, held-out scenes")
        markdown[section] = (f"Quick image: {quick}. Trained on {', '.join(m['train_scenes'])}; evaluated on the held-out "
                              f"{', '.join(m['test_scenes'])}.\n\n" + markdown_table(m["rows"])
                              + f"\n\nDecision cost against accuracy: ![cost vs accuracy]({png})")
    if "render" in only:
        results["render"] = bench_render()
        markdown["render"] = md_render(results["render"])
    for name, (run, md) in DATASET_SECTIONS.items():
        if name in only:
            if not data:
                raise ValueError(f"bench {name} needs --data DIR (a labelled dataset)")
            results[name] = run(data)
            markdown[name] = md(results[name])
    if "stability" in only:
        import tempfile

        from . import stability
        with tempfile.TemporaryDirectory() as tmp:
            results["stability"] = {"blocks": stability.matrix(), "other": stability.other_cells(tmp)}
        other = results["stability"]["other"]
        markdown["stability"] = (stability.markdown(results["stability"]["blocks"]) + "\n\n"
                                 + "| other extreme | behaviour |\n|---|---|\n"
                                 + "\n".join(f"| {k} | {v} |" for k, v in other.items()))
    if "service" in only:
        results["service"] = bench_service()
        markdown["service"] = md_service(results["service"])
    results["markdown"] = markdown
    return results


def format_results(r: dict[str, Any]) -> str:
    return "\n\n".join(f"## {name}\n{body}" for name, body in r["markdown"].items())
