"""`noisestop bench features crop`: the feature base and the fused extract_features against the
matmul of the same multiply-adds, and the cost of the blocks' crops.
"""
from __future__ import annotations

import logging
import statistics
import time
from typing import Any
import numpy as np
import torch
from .timing import MachineLoad, direct_macs, median_s

log = logging.getLogger(__name__)


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
                rounds[name].append(median_s(fn, per) * (macs / side ** 3 if name == "matmul" else 1.0))
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


def bench_crop(repeats: int = 3) -> dict[str, Any]:
    from .crop_cost import measure_crop_cost
    return measure_crop_cost(repeats=repeats)


def md_crop(c: dict[str, Any]) -> str:
    rows = ["| key | value |", "|---|---|"]
    rows += [f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in c.items()]
    return "\n".join(rows)
