"""`noisestop bench`: the speed figures of BENCHMARKS.md, measured on this machine.

Every figure is a median over repeats after a warm-up call; the accuracy cost of each
speed choice is reported beside it (e.g. the spectral feature route vs torch.conv2d).
"""
from __future__ import annotations

import dataclasses
import logging
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)


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
                 kinds: tuple[str, ...] | None = None, quick: str = "albedo",
                 plots_dir: str = "docs") -> dict[str, Any]:
    """The model comparison on held-out scenes; saved as OUT/models-QUICK.json (with each
    model's offset curve) so that `bench tradeoff` draws every model without retraining."""
    import json

    from learning.compare import TRANSFER_ARCHES, compare_models
    from learning.stack import dataset_fingerprint
    from learning.train import SVM_KINDS
    result = compare_models(data, plots_dir, arches=TRANSFER_ARCHES if arches is None else arches,
                            kinds=SVM_KINDS if kinds is None else kinds, quick=quick)
    result.pop("fitted")
    result.update(quick=quick, data=str(data), fingerprint=dataset_fingerprint(data))
    path = Path(out_dir) / f"models-{quick}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(result, default=float))
    tmp.replace(path)
    return result


def saved_comparisons(data: str, out_dir: Path) -> list[dict[str, Any]]:
    """The model comparisons `bench models` saved in out_dir for this very dataset."""
    import json

    from learning.stack import dataset_fingerprint
    fp = dataset_fingerprint(data)
    found = []
    for path in sorted(Path(out_dir).glob("models-*.json")):
        r = json.loads(path.read_text())
        if r.get("fingerprint") != fp:
            log.warning("%s: measured on another dataset; ignored", path)
            continue
        found.append(r)
    return found


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
                 step: int = 16, model: str | None = None, repeats: int = 3) -> dict[str, Any]:
    """Real renders: the model criterion against uniform sampling to the same max spp (warm).

    The two runs alternate `repeats` times and each reports its median run, so that a
    passing disturbance on the machine does not decide the speed-up.
    """
    import tempfile

    from learning.bundle import load_model
    from renderer.adaptive import adaptive_render
    from renderer.criteria import ModelCriterion, UniformCriterion
    runs: dict[str, list[dict]] = {"model": [], "uniform": []}
    m = load_model(model)
    with tempfile.TemporaryDirectory() as tmp:
        # warm-up: every block's kernel compiled once (Dr.Jit caches them), so neither timed
        # run pays compilation and their order does not matter
        adaptive_render(scene, Path(tmp) / "warm", UniformCriterion(), resolution=resolution,
                        step=step, min_spp=step, max_spp=step, progress=False)
        for i in range(repeats):
            for name, crit in (("model", ModelCriterion(m)), ("uniform", UniformCriterion())):
                rep = adaptive_render(scene, Path(tmp) / f"{name}{i}", crit, resolution=resolution,
                                      step=step, min_spp=step, max_spp=max_spp, progress=False)
                runs[name].append({"wall_s": rep["wall_s"], "saved_vs_uniform": rep["saved_vs_uniform"],
                                   "timing": rep.get("timing")})
    out = {name: {**sorted(r, key=lambda x: x["wall_s"])[len(r) // 2],
                  "walls_s": [x["wall_s"] for x in r]} for name, r in runs.items()}
    t = out["model"]["timing"] or {}
    decide = float(t.get("features_s", 0) + t.get("decisions_s", 0))
    return {"scene": scene, "resolution": resolution, "max_spp": max_spp, "repeats": repeats, **out,
            "speedup_vs_uniform": out["uniform"]["wall_s"] / out["model"]["wall_s"],
            "decision_share": decide / out["model"]["wall_s"]}


def bench_service(clients: tuple[int, ...] = (1, 8, 32)) -> dict[str, Any]:
    from .loadtest import bench
    return {str(c): bench(None, clients=c, requests_per_client=max(2, 64 // c), max_seconds=60)
            for c in clients}


#: the curves drawn on the Pareto chart (every kind of the comparison is in the table)
PARETO_KINDS = ("dsvm_as", "svm_as", "dsvm", "svm")


def bench_tradeoff(data: str, out_dir: str | Path = "out/bench", out_png: str = "docs/pareto.png",
                   model: str | None = None,
                   thresholds: tuple[float, ...] = (0.01, 0.02, 0.05, 0.07, 0.1, 0.15, 0.2)) -> dict[str, Any]:
    """Samples (vs oracle) against early stops on held-out scenes: one curve per criterion.

    The bundled model and every SVM kind of the saved model comparison (`bench models`,
    same dataset, same held-out scenes) are swept over their decision offset (per-sub-image
    verdicts on the stored levels, first +1 stops the block); the variance criterion over
    its threshold (the criterion simulation); the oracle is the point (1, 0).
    """
    from learning.bundle import load_model
    from learning.calibrate import DEFAULT_OFFSETS, sweep
    from learning.stack import list_stacks, read_stack
    from learning.table import load_table
    from renderer.criteria import VarianceCriterion
    from renderer.simulate import evaluate_criterion

    from . import charts

    bundled = load_model(model)
    test = list(bundled.manifest.get("training", {}).get("test_scenes") or [])
    if not test:
        raise ValueError("the model's manifest names no held-out scenes")
    comparisons = [c for c in saved_comparisons(data, Path(out_dir)) if sorted(c["test_scenes"]) == sorted(test)]
    if not comparisons:
        raise ValueError(f"bench tradeoff draws the models of the comparison on {data} with "
                         f"held-out scenes {test}: run `noisestop bench models --data {data} "
                         f"--out {out_dir}` first (or list models before tradeoff in one command)")
    table = load_table(data, quick=bundled.quick, progress=False)
    scores = np.full(len(table), np.nan)
    mask = table.scene_mask(test)
    scores[mask] = bundled.decision_function(table.X[mask])
    name = f"{bundled.name} quick {bundled.quick} (bundled)"
    curves: dict[str, list[dict]] = {name: sweep(scores, table, DEFAULT_OFFSETS)}
    default = sweep(scores, table, [bundled.offset])[0]
    for comp in comparisons:
        for row in comp["rows"]:
            if "offset_curve" in row:        # SVM kinds; raw-pixel ones use no quick image
                kind = row["model"]
                curves.setdefault(kind if kind.startswith("svm") else f"{kind} quick {comp['quick']}",
                                  row["offset_curve"])
    stacks = [read_stack(p) for p in list_stacks(data)]
    held = [s for s in stacks if s.scene in test]
    var = []
    for t in thresholds:
        r = evaluate_criterion(held, lambda st, t=t: VarianceCriterion(threshold=t))
        var.append({"threshold": t, **{k: r[k] for k in ("early_stop_rate", "spp_ratio_vs_oracle",
                                                          "precision")}})
    twin = f"{bundled.manifest['kind']} quick {bundled.quick}"     # the bundle's own kind, retrained
    drawn = {n: c for n, c in curves.items()
             if n == name or (n.split()[0] in PARETO_KINDS and n != twin)}
    path = charts.pareto(drawn, var, default, f"default (bundled, offset {bundled.offset:.2f})", test,
                         out_png)
    maps = spp_maps(bundled, table, test, Path(out_png).with_name("spp-maps.png"))
    return {"test_scenes": test, "curves": curves, "drawn": list(drawn), "bundled": name,
            "variance": var, "default": {"offset": bundled.offset, **default}, "plot": path, **maps}


def spp_maps(model, table, scenes: list[str], out_png: Path) -> dict[str, Any]:
    """Where the samples went, per held-out scene: the model's spp per block vs the oracle's."""
    from learning.evaluate import verdicts_by_scene
    from learning.metrics import stop_thresholds, true_thresholds

    from . import charts

    sub = table.subset(table.scene_mask(scenes))
    per = verdicts_by_scene(sub, model.predict(sub.X))
    maps, rows, top = {}, [], 0
    for scene, (v, _, th, spp) in sorted(per.items()):
        grid = tuple(sub.stacks[scene].grid)
        t_pred, t_true = stop_thresholds(v, spp), true_thresholds(th, spp)
        spent = np.minimum(t_pred, spp[-1]).reshape(grid)
        oracle = np.minimum(t_true, spp[-1]).reshape(grid)
        maps[scene] = {"model": spent, "oracle": oracle}
        top = max(top, int(spp[-1]))
        rows.append({"scene": scene, "model_spp": int(spent.sum()), "oracle_spp": int(oracle.sum()),
                     "uniform_spp": int(spp[-1]) * spent.size,
                     "early_blocks": int((t_pred < t_true).sum()),
                     "late_blocks": int((t_pred > t_true).sum())})
    png = charts.spp_maps(maps, top, f"spp per block, {model.name} (offset {model.offset:.2f}) vs oracle",
                          out_png)
    return {"spp_maps": png, "spp_by_scene": rows}


def bench_ablation(data: str, out_png: str = "docs/ablation.png") -> dict[str, Any]:
    """DSVM on held-out scenes with parts of the feature pipeline switched: quick image
    (albedo / direct lighting / none, with its render time once per frame), conv weights
    (smoothing / pre-trained), wavelet layer (on / off: its two features dropped).
    Accuracy next to the cost of classifying 101 sub-images."""
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
                block = tuple(next(iter(t.stacks.values())).block)
                if wavelet:
                    cost = on_cost = time_101_sub_images(model, block)
                else:   # the same pipeline without the wavelet layer's own (measured) time
                    cost = on_cost - wavelet_layer_s(block)
                rows.append({"weights": weights, "quick": quick, "wavelet": wavelet,
                             **{k: m[k] for k in ("precision", "f1", "early_stop_rate",
                                                  "spp_ratio_vs_oracle")}, "test_101_s": cost,
                             "quick_render_s": quick_s.get(quick, 0.0)})
    from . import charts
    return {"rows": rows, "quick_scene": QUICK_COST_SCENE, "plot": charts.ablation(rows, out_png)}


QUICK_COST_SCENE = ("cornell", 256, 16)      # scene, resolution, quick spp


def wavelet_layer_s(block: tuple[int, int], n: int = 101, repeats: int = 20) -> float:
    """Seconds the feature base spends in its wavelet layer for n blocks (what switching the
    layer off would save): the layer timed alone on the spectrum forward has computed."""
    from noisefeat import FeatureBase
    base = FeatureBase().eval()
    xs = torch.rand(n, *block, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        mu = xs.mean(dim=(-2, -1), keepdim=True)
        spec = torch.fft.rfft2(xs - mu)
        ops = base._operators(*block)
        return _median_s(lambda: base._wavelet_layer(xs, spec, ops, mu), repeats)


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
               model: str | None = None, resolution: int = 256, max_spp: int = 640,
               out_png: str = "docs/step.png") -> dict[str, Any]:
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
    from . import charts
    return {"test_scenes": test, "rows": rows, "plot": charts.step_size(rows, scene, out_png)}


def bench_knobs(data: str) -> dict[str, Any]:
    """Training's speed knobs (CV cap, active-learning batch) with their accuracy cost."""
    from learning.knobs import measure_knobs
    return measure_knobs(data)


def bench_dataset(data: str) -> dict[str, Any]:
    """The dataset's build time, from its build log: the latest run that rendered anything."""
    from renderer.dataset import BUILD_LOG, read_build_log
    runs = [r for r in read_build_log(data) if any(not s.get("already_built") for s in r["scenes"])]
    if not runs:
        raise ValueError(f"{data}: no build run on record ({BUILD_LOG}); build it with `make dataset`")
    return runs[-1]


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


def md_models(m: dict[str, Any]) -> str:
    from learning.compare import markdown_table
    text = (f"Quick image: {m['quick']}. Trained on {', '.join(m['train_scenes'])}; evaluated on the "
            f"held-out {', '.join(m['test_scenes'])}.\n\n" + markdown_table(m["rows"]))
    if m.get("curves"):
        text += f"\n\nHeld-out precision against labels queried (active kinds): ![learning curves]({m['curves']})"
    return text


def md_cost_accuracy(comparisons: list[dict[str, Any]], out_png: str = "docs/cost-accuracy.png") -> str:
    """One chart of every compared model: test time per 101 sub-images against precision."""
    from learning.plots import plot_cost_accuracy

    def label(row: dict, quick: str) -> str:      # only feature models use the quick image
        return f"{row['model']} ({quick})" if str(row["model"]).startswith("dsvm") else row["model"]
    rows = [{**r, "model": label(r, c["quick"])} for c in comparisons for r in c["rows"]]
    png = plot_cost_accuracy(rows, out_png, "decision cost vs precision on held-out scenes "
                             "(feature SVMs: quick image in brackets; * untrained conv base)")
    lines = [f"![cost vs accuracy]({png})", "", "| model | precision | test, 101 sub-images (s) |", "|---|---|---|"]
    for r in sorted((r for r in rows if r.get("test_101_s")), key=lambda r: r["test_101_s"]):
        lines.append(f"| {r['model']} | {r['precision']:.3f} | {r['test_101_s']:.4f} |")
    return "\n".join(lines)


def md_dataset(r: dict[str, Any]) -> str:
    st = r["settings"]
    resumed = [x["scene"] for x in r["scenes"] if x.get("resumed") and not x.get("already_built")]
    done = [x["scene"] for x in r["scenes"] if x.get("already_built")]
    minutes, seconds = divmod(round(r["wall_s"]), 60)
    where = (f"scheduler {r['scheduler']}" if r.get("scheduler") else
             f"{r['workers']} local workers" if r.get("workers") else "one local worker per core")
    lines = [f"{len(r['scenes'])} scenes at {st['resolution']}x{st['resolution']}, step {st['step']}, "
             f"{st['levels']} levels, reference {st['reference_spp']} spp, {where}, "
             f"{r.get('cpus')} CPUs, variant {r['scenes'][0]['variant'] if r['scenes'] else '-'}; "
             f"run finished {r.get('finished', '?')}: **{minutes} min {seconds} s** wall (goal <= 60 min), "
             f"{r['sub_images']:,} labelled sub-images.",
             "", "| scene | seconds | censored blocks (never converged) |", "|---|---|---|"]
    lines += [f"| {x['scene']} | {x['seconds']:.0f} | {x['censored']} |" for x in r["scenes"]]
    if resumed or done or r.get("failed"):
        lines += ["", f"Resumed scenes: {', '.join(resumed) or 'none'}; already built: "
                  f"{', '.join(done) or 'none'}; failed: {', '.join(r.get('failed') or {}) or 'none'}."]
    return "\n".join(lines)


def md_knobs(r: dict[str, Any]) -> str:
    lines = [f"Quick image {r['quick']}; held-out scenes; * = the default.", "",
             "| knob | model | setting | training (s) | precision | f1 | early_stop_rate | samples / oracle "
             "| C, gamma chosen |", "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        setting = f"{x['value']}{' *' if x['default'] else ''}"
        if x["knob"].startswith("cross") and x.get("cv_rows"):
            setting += f" ({x['cv_rows']:,} rows)"
        lines.append(f"| {x['knob']} | {x['kind']} | {setting} | {x['seconds']:.1f} | {x['precision']:.3f} "
                     f"| {x['f1']:.3f} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} "
                     f"| {x['C']:g}, {x['gamma']:.3g} |")
    return "\n".join(lines)


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

    def walls(x: dict) -> str:
        return ", ".join(f"{w:.1f}" for w in x.get("walls_s", [x["wall_s"]]))
    return "\n".join([
        f"{r['scene']} at {r['resolution']}x{r['resolution']}, max {r['max_spp']} spp:", "",
        f"| run | wall (s), median of {r.get('repeats', 1)} | all runs (s) | saved vs uniform |", "|---|---|---|---|",
        f"| model criterion | {m['wall_s']:.1f} | {walls(m)} | {m['saved_vs_uniform']:.3f} |",
        f"| uniform to max spp | {u['wall_s']:.1f} | {walls(u)} | 0 |", "",
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


def _best(rows: list[dict], max_early: float) -> str:
    """The fewest samples whose early-stop rate is within max_early, with its offset."""
    ok = [r for r in rows if r["early_stop_rate"] <= max_early + 1e-12]
    if not ok:
        return "never"
    r = min(ok, key=lambda r: (r["spp_ratio_vs_oracle"], r["offset"]))
    return f"{r['spp_ratio_vs_oracle']:.3f} (offset {r['offset']:.1f})"


def md_tradeoff(r: dict[str, Any]) -> str:
    d = r["default"]
    lines = [f"![samples vs early stops]({r['plot']})", "",
             f"Default (bundled, offset {d['offset']:.2f}): early stops {d['early_stop_rate']:.3f}, "
             f"samples {d['spp_ratio_vs_oracle']:.3f} x oracle. Drawn: {', '.join(r['drawn'])}; "
             "every model is in the table. Samples are relative to the oracle.", "",
             "| criterion | at offset 0: early stops | at offset 0: samples | fewest samples, early stops <= 5 % "
             "| fewest samples, no early stop |", "|---|---|---|---|---|"]
    for name, rows in r["curves"].items():
        zero = min(rows, key=lambda x: abs(x["offset"]))
        lines.append(f"| {name} | {zero['early_stop_rate']:.3f} | {zero['spp_ratio_vs_oracle']:.3f} "
                     f"| {_best(rows, 0.05)} | {_best(rows, 0.0)} |")
    lines += ["", "The bundled model along its offset, and the variance criterion along its threshold:", "",
              "| criterion | setting | early_stop_rate | samples / oracle |", "|---|---|---|---|"]
    for row in r["curves"][r["bundled"]]:
        if abs(round(row["offset"] * 2) - row["offset"] * 2) < 1e-9:  # every 0.5
            lines.append(f"| {r['bundled']} | offset {row['offset']:.1f} | {row['early_stop_rate']:.3f} "
                         f"| {row['spp_ratio_vs_oracle']:.3f} |")
    for row in r["variance"]:
        lines.append(f"| variance | threshold {row['threshold']} | {row['early_stop_rate']:.3f} "
                     f"| {row['spp_ratio_vs_oracle']:.3f} |")
    lines += ["", f"Where the samples went per held-out scene (default offset, spp per block, model "
              f"above oracle): ![spp maps]({r['spp_maps']})", "",
              "| scene | model spp (sum over blocks) | oracle spp | uniform spp | blocks stopped early "
              "| blocks stopped late |", "|---|---|---|---|---|---|"]
    for x in r["spp_by_scene"]:
        lines.append(f"| {x['scene']} | {x['model_spp']:,} | {x['oracle_spp']:,} | {x['uniform_spp']:,} "
                     f"| {x['early_blocks']} | {x['late_blocks']} |")
    return "\n".join(lines)


def md_ablation(r: dict[str, Any]) -> str:
    scene, res, spp = r["quick_scene"]
    lines = [f"![feature-pipeline ablation]({r['plot']})", "",
             "| conv weights | quick image | wavelet layer | precision | f1 | early_stop_rate "
             f"| samples / oracle | 101 sub-images (s; off: less the wavelet layer's time) "
             f"| quick image, {scene} {res}x{res} {spp} spp (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        cost = f"{x['test_101_s']:.4f}"
        lines.append(f"| {x['weights']} | {x['quick']} | {'on' if x['wavelet'] else 'off'} | "
                     f"{x['precision']:.3f} | {x['f1']:.3f} | {x['early_stop_rate']:.3f} | "
                     f"{x['spp_ratio_vs_oracle']:.3f} | {cost} | {x['quick_render_s']:.3f} |")
    return "\n".join(lines)


def md_step(r: dict[str, Any]) -> str:
    scene = r["rows"][0]["render_scene"]
    lines = [f"![step size]({r['plot']})", "",
             f"| step (spp per pass) | held-out early stops | held-out samples / oracle "
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
DATASET_SECTIONS = {"dataset": (bench_dataset, md_dataset), "criteria": (bench_criteria, md_criteria),
                    "tradeoff": (bench_tradeoff, md_tradeoff), "ablation": (bench_ablation, md_ablation),
                    "step": (bench_step, md_step), "knobs": (bench_knobs, md_knobs)}
SECTIONS = ("features", "crop", "models", "render", "service", "stability", *DATASET_SECTIONS)


def run_all(repeats: int = 30, only: tuple[str, ...] = ("features", "crop"), data: str | None = None,
            out_dir: str = "out/bench", arches: tuple[str, ...] | None = None,
            kinds: tuple[str, ...] | None = None, quick: tuple[str, ...] = ("albedo",),
            on_section: Callable[[str, str], None] | None = None) -> dict[str, Any]:
    """Measure the sections in `only`; `quick`: the quick images the models section compares
    (feature models are trained once per mode). `on_section(name, markdown)` is called as
    each section finishes, so an interrupted run keeps what it measured; a section that
    cannot run (e.g. no dataset build on record) is reported in results["failed"] and the
    others still run."""
    from learning.train import SVM_KINDS
    from renderer.variant import select_variant
    variant = select_variant()
    results: dict[str, Any] = {"variant": variant, "seconds": {}, "failed": {}}
    markdown: dict[str, str] = {}
    needs_data = {"models", *DATASET_SECTIONS} & set(only)
    if needs_data and not data:
        raise ValueError(f"bench {', '.join(sorted(needs_data))} needs --data DIR (a labelled dataset)")

    def measure(name: str, run: Callable[[], Any], md: Callable[[Any], str]) -> None:
        t0 = time.perf_counter()
        try:
            results[name] = run()
        except (ValueError, FileNotFoundError) as exc:   # one section's problem spares the others
            log.error("bench %s: %s", name, exc)
            results["failed"][name] = str(exc)
            return
        markdown[name] = md(results[name])
        results["seconds"][name] = time.perf_counter() - t0
        log.info("bench %s: %.0f s", name, results["seconds"][name])
        if on_section is not None:
            on_section(name, markdown[name])

    if "features" in only:
        measure("features", lambda: bench_features(repeats), lambda r: md_features(r, variant))
    if "crop" in only:
        measure("crop", lambda: bench_crop(repeats=max(1, min(repeats, 3))), md_crop)
    if "models" in only:
        for i, q in enumerate(quick):
            # raw-pixel and transfer models use no quick image: measured with the first mode only
            k, a = (kinds, arches) if i == 0 else (
                tuple(x for x in (kinds or SVM_KINDS) if x.startswith("dsvm")), ())
            measure("models" if q == "albedo" else f"models_quick_{q}",
                    lambda k=k, a=a, q=q: bench_models(data, Path(out_dir), a, k, q), md_models)
        measure("cost_accuracy", lambda: saved_comparisons(data, Path(out_dir)), md_cost_accuracy)
    if "render" in only:
        measure("render", bench_render, md_render)
    for name, (run, md) in DATASET_SECTIONS.items():
        if name in only:
            measure(name, lambda run=run, name=name: run(data, out_dir=out_dir) if name == "tradeoff"
                    else run(data), md)
    if "stability" in only:
        measure("stability", stability_section, md_stability)
    if "service" in only:
        measure("service", bench_service, md_service)
    results["markdown"] = markdown
    return results


def stability_section() -> dict[str, Any]:
    import tempfile

    from . import stability
    with tempfile.TemporaryDirectory() as tmp:
        return {"blocks": stability.matrix(), "other": stability.other_cells(tmp)}


def md_stability(r: dict[str, Any]) -> str:
    from . import stability
    return (stability.markdown(r["blocks"]) + "\n\n| other extreme | behaviour |\n|---|---|\n"
            + "\n".join(f"| {k} | {v} |" for k, v in r["other"].items()))


def format_results(r: dict[str, Any]) -> str:
    return "\n\n".join(f"## {name}\n{body}" for name, body in r["markdown"].items())
