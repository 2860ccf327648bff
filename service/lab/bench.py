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

from .bench_decisions import bench_criteria, bench_step, bench_tradeoff, md_criteria, md_step, md_tradeoff

log = logging.getLogger(__name__)


def _median_s(fn: Callable[[], Any], repeats: int, warm: bool = True) -> float:
    """Median seconds of `repeats` calls of `fn`, after one untimed call unless `warm` is False
    (the caller has warmed it already)."""
    if warm:
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


class MachineLoad:
    """CPU time other processes used while a measurement ran, as a share of all CPUs
    (Linux /proc/stat less this process and the processes in `mine`, e.g. a server under
    test): BENCHMARKS says when a figure was taken on a busy machine. None without /proc."""

    def __init__(self, mine: tuple[int, ...] = ()) -> None:
        self.mine = mine
        self.share: float | None = None

    def __enter__(self) -> "MachineLoad":
        self._t0, self._busy0, self._own0 = time.perf_counter(), _busy_jiffies(), self._own()
        return self

    def _own(self) -> float:
        return time.process_time() + sum(_process_cpu(p) or 0.0 for p in self.mine)

    def __exit__(self, *exc: Any) -> None:
        busy1 = _busy_jiffies()
        if self._busy0 is None or busy1 is None:
            return
        import os
        wall = time.perf_counter() - self._t0
        others = (busy1 - self._busy0) / os.sysconf("SC_CLK_TCK") - (self._own() - self._own0)
        self.share = max(0.0, others / (wall * (os.cpu_count() or 1)))


def _busy_jiffies() -> int | None:
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return sum(v) - v[3] - v[4]          # all but idle and iowait


def _process_cpu(pid: int) -> float | None:
    """CPU seconds (user + system) of a process, all its threads (Linux)."""
    import os
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_features(repeats: int = 30, n: int = 101, size: int = 128) -> dict[str, Any]:
    """The feature path against a dense matmul of the same multiply-adds, measured in
    interleaved rounds (each a median of `repeats` // 5 calls; the ratio is taken per round
    and its median reported), so that a change in the machine's load moves both sides."""
    from noisefeat import FeatureBase, extract_features
    from noisefeat.display import lightness

    rng = np.random.default_rng(0)
    rgb = (rng.random((n, size, size, 3)) ** 2).astype(np.float32)
    base = FeatureBase().eval()
    macs = direct_macs(n, size, size)
    side = max(64, round(macs ** (1 / 3)))
    a, b = torch.rand(side, side), torch.rand(side, side)
    per = max(3, repeats // 5)
    rounds: dict[str, list[float]] = {"matmul": [], "extract": [], "base": [], "lightness": []}
    with torch.inference_mode(), MachineLoad() as load:
        L = lightness(torch.from_numpy(rgb))[:, None]
        calls = {"matmul": lambda: a @ b, "extract": lambda: extract_features(rgb, base=base),
                 "base": lambda: base(L), "lightness": lambda: lightness(torch.from_numpy(rgb))}
        for _ in range(5):
            for name, fn in calls.items():
                rounds[name].append(_median_s(fn, per) * (macs / side ** 3 if name == "matmul" else 1.0))
        fast = base(L)
        # The definition's own route (torch.conv2d, circular padding): slow, so timed once.
        t0 = time.perf_counter()
        outs = base.layer_outputs(L)
        means = torch.stack([(L - o)[:, 0].mean((-2, -1)) for o in outs], 1)
        stds = torch.stack([(L - o)[:, 0].std((-2, -1), correction=0) for o in outs], 1)
        t_direct = time.perf_counter() - t0
    slow = torch.cat([means, stds], 1)
    med = {k: statistics.median(v) for k, v in rounds.items()}
    ratio = {k: statistics.median(x / m for x, m in zip(rounds[k], rounds["matmul"])) for k in ("extract", "base")}
    return {
        "blocks": n, "block_size": size, "threads": torch.get_num_threads(),
        "feature_base_ms": med["base"] * 1e3,
        "lightness_ms": med["lightness"] * 1e3,
        "extract_features_ms": med["extract"] * 1e3,
        "direct_conv2d_ms": t_direct * 1e3,
        "direct_macs": macs,
        "matmul_gmacs": macs / med["matmul"] / 1e9,
        "matmul_same_macs_ms": med["matmul"] * 1e3,
        "feature_base_vs_matmul": ratio["base"],
        "extract_vs_matmul": ratio["extract"],
        "extract_vs_matmul_rounds": [x / m for x, m in zip(rounds["extract"], rounds["matmul"])],
        "other_load": load.share,
        "spectral_vs_conv2d_max_abs_diff": float((fast - slow).abs().max()),
        "spectral_vs_conv2d_max_rel_diff": float(((fast - slow).abs() / (slow.abs() + 1e-3)).max()),
        "goal_ms": 10.0, "goal_ratio": 3.0,
    }


def _flip_evaluator_threads(n: int) -> bool:
    """Set flip-evaluator's OpenMP threads (its own bundled libgomp, which torch's
    set_num_threads does not reach); False if that library cannot be found."""
    import ctypes
    import glob
    import os

    import flip_evaluator
    libs = glob.glob(os.path.join(os.path.dirname(flip_evaluator.__file__), os.pardir,
                                  "flip_evaluator.libs", "libgomp*"))
    try:
        ctypes.CDLL(libs[0]).omp_set_num_threads(int(n))
    except (IndexError, OSError, AttributeError):
        return False
    return True


def flip_bench_halves(n: int, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n pairs of half buffers [size, size, 3]: smooth coloured shading with an edge, and
    two independent noisy estimates of it (what a render's half buffers look like)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    base = rng.random((n, 1, 1, 3)) * 0.6 * (0.3 + x + 0.5 * (y > 0.6))[None, ..., None]
    a, b = (base * (1 + 0.1 * rng.standard_normal(base.shape[:3] + (3,))) for _ in range(2))
    return np.clip(a, 0, None).astype(np.float32), np.clip(b, 0, None).astype(np.float32)


def flip_agreement(root: str) -> dict[str, Any]:
    """Both routes on every (level, block) of the labelled stacks under `root` whose
    calibration and bundled-model figures are on record: how far e differs, and whether any
    decision does, at every candidate c of the flip criterion and for the bundled model at
    its offset (only blocks flip would be asked about: not flat, level >= 1). Reads the
    stacks, writes nothing (no cache)."""
    from learning.models.bundle import load_model
    from learning.evaluation.calibrate import FLIP_CANDIDATES
    from learning.inputs.halves import halves_flip, halves_flip_evaluator
    from learning.inputs.noise_input import compose
    from learning.data.stack import list_stacks, read_stack
    from learning.stoprule import flat_blocks
    from learning.inputs.table import iter_stack_halves

    old, new = [], []
    for path in list_stacks(root):
        stack = read_stack(path)
        for k, even, odd in iter_stack_halves(stack):
            ask = np.flatnonzero(~flat_blocks(stack.blocks(k)))
            if ask.size:
                old.append(halves_flip_evaluator(even[ask], odd[ask]))
                new.append(halves_flip(even[ask], odd[ask]))
    if not old:
        raise ValueError(f"{root}: no blocks to compare (no stacks, or every block flat)")
    e_old, e_new = np.concatenate(old), np.concatenate(new)
    model = load_model(None)
    s_old, s_new = (model.decision_function(compose(None, e, model.composition or "f")) for e in (e_old, e_new))
    resolved = e_old >= 1e-3
    rel = np.abs(e_new - e_old) / np.maximum(e_old, 1e-300)
    return {"root": root, "values": int(e_old.size), "below_1e-3": int((~resolved).sum()),
            "max_rel_diff": float(rel[resolved].max()) if resolved.any() else None,
            "median_rel_diff": float(np.median(rel)), "max_abs_diff": float(np.abs(e_new - e_old).max()),
            "flip_candidates": len(FLIP_CANDIDATES),
            "flip_verdict_changes": int(sum(((e_old <= c) != (e_new <= c)).sum() for c in FLIP_CANDIDATES)),
            "model": model.name, "model_composition": model.composition, "model_offset": model.offset,
            "model_max_score_diff": float(np.abs(s_new - s_old).max()),
            "model_max_score_diff_resolved": float(np.abs(s_new - s_old)[resolved].max()) if resolved.any() else None,
            "model_verdict_changes": int(((s_old > model.offset) != (s_new > model.offset)).sum())}


def _interleaved_medians(fast: Callable[[], Any], slow: Callable[[], Any], repeats: int,
                         slow_repeats: int) -> tuple[float, float]:
    """Median seconds of `fast` (repeats) and `slow` (slow_repeats), their runs interleaved
    so that both see the same load when other work shares the machine."""
    fast(), slow()
    every = max(1, repeats // slow_repeats)
    t_fast, t_slow = [], []
    for i in range(repeats):
        t0 = time.perf_counter()
        fast()
        t_fast.append(time.perf_counter() - t0)
        if i % every == 0 and len(t_slow) < slow_repeats:
            t0 = time.perf_counter()
            slow()
            t_slow.append(time.perf_counter() - t0)
    return statistics.median(t_fast), statistics.median(t_slow)


def bench_flip(repeats: int = 30, shapes: tuple[tuple[int, int], ...] = ((16, 64), (16, 128)),
               threads: tuple[int, ...] = (1, 2), datasets: tuple[str, ...] = ()) -> dict[str, Any]:
    """FLIP between the half buffers (the flip criterion's score, the bundled model's input
    `f`), warm, median of repeats: flip-evaluator one block per call (the reference) against
    noisefeat.flip, all blocks at once, at each thread count; how closely they agree, here
    and on every block of the labelled `datasets` (`flip_agreement`)."""
    import os

    from learning.inputs.halves import halves_flip, halves_flip_evaluator

    load = [os.getloadavg()[0]]
    before = torch.get_num_threads()
    rows = []
    try:
        for t in threads:
            torch.set_num_threads(t)
            set_old = _flip_evaluator_threads(t)
            for n, size in shapes:
                a, b = flip_bench_halves(n, size)
                new, old = halves_flip(a, b), halves_flip_evaluator(a, b)
                t_new, t_old = _interleaved_medians(lambda: halves_flip(a, b), lambda: halves_flip_evaluator(a, b),
                                                    repeats, max(3, repeats // 6))
                rows.append({"threads": t, "evaluator_threads_set": set_old, "blocks": n, "size": size,
                             "evaluator_ms": t_old * 1e3, "torch_ms": t_new * 1e3, "speedup": t_old / t_new,
                             "max_rel_diff": float(np.max(np.abs(new - old) / old)), "mean_e": float(old.mean())})
    finally:
        torch.set_num_threads(before)
        _flip_evaluator_threads(os.cpu_count() or 1)
    load.append(os.getloadavg()[0])
    return {"rows": rows, "cpus": os.cpu_count(), "load_avg": load, "repeats": repeats,
            "datasets": [flip_agreement(d) for d in datasets]}


def bench_crop(repeats: int = 3) -> dict[str, Any]:
    from renderer.blocks import measure_crop_cost
    return measure_crop_cost(repeats=repeats)


def bench_models(data: str, out_dir: Path, arches: tuple[str, ...] | None = None,
                 kinds: tuple[str, ...] | None = None, quick: str = "albedo",
                 plots_dir: str = "docs", heldout: str | None = None) -> dict[str, Any]:
    """The model comparison on held-out scenes; saved as OUT/models-QUICK.json (with each
    model's offset curve) so that `bench tradeoff` draws every model without retraining."""
    import json

    from learning.training.compare import TRANSFER_ARCHES, compare_models
    from learning.training.train import SVM_KINDS
    result = compare_models(data, plots_dir, arches=TRANSFER_ARCHES if arches is None else arches,
                            kinds=SVM_KINDS if kinds is None else kinds, quick=quick, heldout=heldout)
    result.pop("fitted")
    result.update(quick=quick, data=str(data), fingerprint=_fingerprints(data, heldout))
    path = Path(out_dir) / f"models-{quick}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(result, default=float))
    tmp.replace(path)
    return result


def _fingerprints(data: str, heldout: str | None) -> str:
    from learning.data.stack import dataset_fingerprint
    return dataset_fingerprint(data) + ("" if heldout is None else "+" + dataset_fingerprint(heldout))


def saved_comparisons(data: str, out_dir: Path, heldout: str | None = None) -> list[dict[str, Any]]:
    """The model comparisons `bench models` saved in out_dir for these very datasets."""
    import json

    fp = _fingerprints(data, heldout)
    found = []
    for path in sorted(Path(out_dir).glob("models-*.json")):
        r = json.loads(path.read_text())
        if r.get("fingerprint") != fp:
            log.warning("%s: measured on another dataset; ignored", path)
            continue
        found.append(r)
    return found


def bench_render(scene: str = "env_spheres", resolution: int = 256, max_spp: int = 640,
                 step: int = 16, model: str | None = None, repeats: int = 3) -> dict[str, Any]:
    """Real renders: the model and flip criteria against uniform sampling to the same max
    spp (warm).

    The runs alternate `repeats` times and each reports its median run, so that a
    passing disturbance on the machine does not decide the speed-up.
    """
    import tempfile

    from learning.models.bundle import load_model
    from renderer.adaptive import adaptive_render
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


def bench_ablation(data: str, heldout: str | None = None, out_png: str = "docs/ablation.png") -> dict[str, Any]:
    """DSVM on held-out scenes with parts of the feature pipeline switched: quick image
    (albedo / direct lighting / none, with its render time once per frame), conv weights
    (smoothing / pre-trained), wavelet layer (on / off: its two features dropped).
    Accuracy next to the cost of classifying 101 sub-images."""
    from learning.models.bundle import Model
    from learning.evaluation.evaluate import evaluate_model, time_101_sub_images
    from learning.evaluation.generalisation import split_tables
    from learning.inputs.table import QUICK_MODES
    from learning.training.train import train_model
    from noisefeat import FeatureBase

    rows = []
    wavelet_cols = [12, 25]                     # mean_13, std_13: the wavelet layer
    keep_no_wavelet = [i for i in range(26) if i not in wavelet_cols]
    quick_s = quick_image_cost()
    for weights in ("smoothing", "pretrained"):
        base = FeatureBase(weights).eval()
        for quick in (q for q in QUICK_MODES if q != "halves"):   # the paper's quick images: 26 features each
            train, test = split_tables(data, heldout, base=base, quick=quick)
            for wavelet in (True, False):
                t, h = (train, test) if wavelet else (dataclasses.replace(train, X=train.X[:, keep_no_wavelet]),
                                                      dataclasses.replace(test, X=test.X[:, keep_no_wavelet]))
                est, _ = train_model("dsvm", data, table=t, test_scenes=[], quick=quick, progress=False)
                model = Model(est, {"kind": "dsvm", "input": "features", "quick": quick})
                m = evaluate_model(model, h)
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
        if "analysis12" in ops:
            return _median_s(lambda: base._wavelet_even(spec, ops, mu.reshape(n)), repeats)
        return _median_s(lambda: base._wavelet_odd(xs, spec, ops, mu.reshape(n)), repeats)


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


def bench_knobs(data: str, heldout: str | None = None) -> dict[str, Any]:
    """Training's speed knobs (CV cap, active-learning batch) with their accuracy cost."""
    from learning.training.knobs import measure_knobs
    return measure_knobs(data, heldout)


def bench_inputs(data: str, heldout: str | None = None) -> dict[str, Any]:
    """Every composition of the half-buffer input, and the paper's quick inputs, on held-out scenes."""
    from learning.training.compare_inputs import compare_inputs
    if not heldout:
        raise ValueError("bench inputs needs --heldout DIR (scenes no composition was chosen on)")
    return compare_inputs(data, heldout)


def md_inputs(r: dict[str, Any]) -> str:
    from learning.training.compare_inputs import md_inputs as md
    return md(r)


def bench_dataset(data: str, heldout: str | None = None) -> dict[str, Any]:
    """The dataset's build time, from its build log: the latest run that rendered anything."""
    from renderer.dataset import BUILD_LOG, read_build_log
    out = {}
    for name, where in (("training", data), ("heldout", heldout)):
        if where is None:
            continue
        runs = [r for r in read_build_log(where) if any(not s.get("already_built") for s in r["scenes"])]
        if not runs:
            raise ValueError(f"{where}: no build run on record ({BUILD_LOG}); build it with `make dataset` "
                             "or `make heldout`")
        out[name] = runs[-1]
    return out


# --- markdown for BENCHMARKS.md --------------------------------------------------------
def md_features(f: dict[str, Any], variant: str) -> str:
    busy = "" if f.get("other_load") is None else \
        f"; other processes used {100 * f['other_load']:.0f} % of the CPUs meanwhile"
    rounds = ", ".join(f"{r:.2f}" for r in f.get("extract_vs_matmul_rounds", []))
    return "\n".join([
        f"Measured on this machine ({f['threads']} torch threads, Mitsuba variant {variant}), "
        f"{f['blocks']} sub-images of {f['block_size']}x{f['block_size']}, medians of 5 interleaved "
        f"rounds{busy}:",
        "",
        "| what | time | goal |",
        "|---|---|---|",
        f"| extract_features, linear RGB -> 26 features (fused path) | {f['extract_features_ms']:.2f} ms | |",
        f"| feature base alone, L* blocks -> 26 features (spectral route) | {f['feature_base_ms']:.2f} ms | <= {f['goal_ms']:.0f} ms |",
        f"| display transform + L* alone (RGB -> L*) | {f['lightness_ms']:.2f} ms | |",
        f"| the definition run with torch.conv2d (reference route) | {f['direct_conv2d_ms']:.0f} ms | |",
        f"| dense float32 matmul of the same {f['direct_macs'] / 1e6:.0f} M multiply-adds "
        f"({f['matmul_gmacs']:.1f} GMAC/s) | {f['matmul_same_macs_ms']:.2f} ms | |",
        f"| **extract_features time / matmul time** (per round: {rounds}) | **{f['extract_vs_matmul']:.2f} x** "
        f"| <= {f['goal_ratio']:.0f} x |",
        f"| feature base time / matmul time | {f['feature_base_vs_matmul']:.2f} x | |",
        "",
        f"Accuracy cost of the spectral route against torch.conv2d: max abs difference "
        f"{f['spectral_vs_conv2d_max_abs_diff']:.1e}, max relative {f['spectral_vs_conv2d_max_rel_diff']:.1e} "
        "(float32 rounding; both compute the same circular convolutions).",
    ])


def md_flip(r: dict[str, Any]) -> str:
    lines = [f"Median of {r['repeats']} warm calls (flip-evaluator: of {max(3, r['repeats'] // 6)}, interleaved), "
             f"{r['cpus']} CPUs, load average {r['load_avg'][0]:.1f} before and {r['load_avg'][1]:.1f} after "
             "(above the thread count means other work shared the CPUs).", "",
             "| threads | blocks per call | flip-evaluator, per call (ms) | per block (ms) | noisefeat.flip, "
             "per call (ms) | per block (ms) | speed-up | max relative difference of e |",
             "|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(f"| {x['threads']} | {x['blocks']} of {x['size']}x{x['size']} | {x['evaluator_ms']:.1f} | "
                     f"{x['evaluator_ms'] / x['blocks']:.2f} | {x['torch_ms']:.1f} | {x['torch_ms'] / x['blocks']:.3f} | "
                     f"{x['speedup']:.1f}x | {x['max_rel_diff']:.1e} |")
    if r.get("datasets"):
        lines += ["", "The two routes on every block the flip criterion is asked about (not flat, level >= 1) of "
                  "the labelled stacks, and the decisions taken from them:", "",
                  "| stacks | values of e | max relative difference (e >= 1e-3) | median relative difference "
                  "| max absolute difference | flip verdicts changed, over every candidate c "
                  "| bundled model: max score difference (e >= 1e-3 / all) | its verdicts changed |",
                  "|---|---|---|---|---|---|---|---|"]
        for d in r["datasets"]:
            def g(v: float | None) -> str:
                return "-" if v is None else f"{v:.1e}"
            lines.append(f"| {d['root']} | {d['values']} ({d['below_1e-3']} below 1e-3) | {g(d['max_rel_diff'])} | "
                         f"{g(d['median_rel_diff'])} | {g(d['max_abs_diff'])} | {d['flip_verdict_changes']} "
                         f"({d['flip_candidates']} values of c) | {g(d['model_max_score_diff_resolved'])} / "
                         f"{g(d['model_max_score_diff'])} | {d['model_verdict_changes']} (offset "
                         f"{d['model_offset']:g}) |")
    return "\n".join(lines)


def md_crop(c: dict[str, Any]) -> str:
    rows = ["| key | value |", "|---|---|"]
    rows += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in c.items()]
    return "\n".join(rows)


def md_models(m: dict[str, Any]) -> str:
    from learning.training.compare import markdown_table
    conv = ", ".join((m.get("groups") or {}).get("converging") or []) or "none"
    text = (f"Quick image: {m['quick']}. Trained on {', '.join(m['train_scenes'])}; evaluated on the "
            f"held-out {', '.join(m['test_scenes'])} (converging inside their stacks: {conv}). Offset 0 "
            "(the hyperplane), through the stop rule.\n\n" + markdown_table(m["rows"]))
    if m.get("curves"):
        text += f"\n\nHeld-out precision against labels queried (active kinds): ![learning curves]({m['curves']})"
    return text


def md_cost_accuracy(comparisons: list[dict[str, Any]], out_png: str = "docs/cost-accuracy.png") -> str:
    """One chart of every compared model: test time per 101 sub-images against precision."""
    from learning.evaluation.plots import plot_cost_accuracy

    def label(row: dict, quick: str) -> str:      # only feature models use the quick image
        return f"{row['model']} ({quick})" if str(row["model"]).startswith("dsvm") else row["model"]
    rows = [{**r, "model": label(r, c["quick"])} for c in comparisons for r in c["rows"]]
    png = plot_cost_accuracy(rows, out_png, "decision cost vs precision on held-out scenes "
                             "(feature SVMs: quick image in brackets; * untrained conv base)")
    lines = [f"![cost vs accuracy]({png})", "", "| model | precision | test, 101 sub-images (s) |", "|---|---|---|"]
    for r in sorted((r for r in rows if r.get("test_101_s")), key=lambda r: r["test_101_s"]):
        lines.append(f"| {r['model']} | {r['precision']:.3f} | {r['test_101_s']:.4f} |")
    return "\n".join(lines)


def md_dataset(runs: dict[str, Any]) -> str:
    titles = {"training": "Training scenes (`make dataset`)", "heldout": "Held-out scenes (`make heldout`)"}
    return "\n\n".join(f"{titles[name]}: {_md_build(r)}" for name, r in runs.items())


def _md_build(r: dict[str, Any]) -> str:
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


# sections that need only the datasets: name -> (measure(data, heldout), markdown(result))
DATASET_SECTIONS = {"dataset": (bench_dataset, md_dataset), "inputs": (bench_inputs, md_inputs),
                    "criteria": (bench_criteria, md_criteria),
                    "tradeoff": (bench_tradeoff, md_tradeoff), "ablation": (bench_ablation, md_ablation),
                    "step": (bench_step, md_step), "knobs": (bench_knobs, md_knobs)}
SECTIONS = ("features", "crop", "flip", "models", "render", "passes", "service", "stability", "reliability",
            *DATASET_SECTIONS)


def run_all(repeats: int = 30, only: tuple[str, ...] = ("features", "crop"), data: str | None = None,
            out_dir: str = "out/bench", arches: tuple[str, ...] | None = None,
            kinds: tuple[str, ...] | None = None, quick: tuple[str, ...] = ("albedo",),
            on_section: Callable[[str, str], None] | None = None,
            heldout: str | None = None) -> dict[str, Any]:
    """Measure the sections in `only`; `quick`: the quick images the models section compares
    (feature models are trained once per mode). `on_section(name, markdown)` is called as
    each section finishes, so an interrupted run keeps what it measured; a section that
    cannot run (e.g. no dataset build on record) is reported in results["failed"] and the
    others still run."""
    from learning.training.train import SVM_KINDS
    from learning.data.variant import select_variant
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
    if "flip" in only:
        measure("flip", lambda: bench_flip(repeats, datasets=tuple(d for d in (data, heldout) if d)), md_flip)
    if "models" in only:
        plain_done = False
        for q in quick:
            # raw-pixel and transfer models read the block whatever the quick image (measured
            # with the first such mode), and the noise image with halves (measured there)
            full = q == "halves" or not plain_done
            plain_done = plain_done or q != "halves"
            k, a = (kinds, arches) if full else (tuple(x for x in (kinds or SVM_KINDS) if x.startswith("dsvm")), ())
            measure("models" if q == "albedo" else "models_halves" if q == "halves" else f"models_quick_{q}",
                    lambda k=k, a=a, q=q: bench_models(data, Path(out_dir), a, k, q, heldout=heldout), md_models)
        measure("cost_accuracy", lambda: saved_comparisons(data, Path(out_dir), heldout), md_cost_accuracy)
    if "render" in only:
        measure("render", bench_render, md_render)
    if "passes" in only:
        from .bench_passes import bench_passes, md_passes
        measure("passes", bench_passes, md_passes)
    for name, (run, md) in DATASET_SECTIONS.items():
        if name in only:
            measure(name, lambda run=run, name=name: run(data, heldout, out_dir=out_dir) if name == "tradeoff"
                    else run(data, heldout), md)
    if "stability" in only:
        measure("stability", stability_section, md_stability)
    if "service" in only:
        from .bench_service import bench_service, md_service
        measure("service", bench_service, md_service)
    if "reliability" in only:
        from .reliability import bench_reliability, md_reliability
        measure("reliability", bench_reliability, md_reliability)
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
