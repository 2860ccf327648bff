"""`noisestop bench`: the speed figures of BENCHMARKS.md, measured on this machine.

Every figure is a median over repeats after a warm-up call; the accuracy cost of each
speed choice is reported beside it (e.g. the spectral feature route vs torch.conv2d).
"""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable
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


def run_all(repeats: int = 30) -> dict[str, Any]:
    from renderer.variant import select_variant
    variant = select_variant()
    results: dict[str, Any] = {"variant": variant, "features": bench_features(repeats)}
    results["crop"] = bench_crop(repeats=max(1, min(repeats, 3)))
    return results


def format_results(r: dict[str, Any]) -> str:
    f = r["features"]
    lines = [
        f"mitsuba variant: {r['variant']}; torch threads: {f['threads']}",
        f"features, {f['blocks']} blocks of {f['block_size']}x{f['block_size']}:",
        f"  feature base (L -> 26)        {f['feature_base_ms']:8.2f} ms   (goal <= {f['goal_ms']:.0f} ms)",
        f"  display + L* (RGB -> L)       {f['lightness_ms']:8.2f} ms",
        f"  extract_features (RGB -> 26)  {f['extract_features_ms']:8.2f} ms",
        f"  torch.conv2d route (reference){f['direct_conv2d_ms']:8.1f} ms",
        f"  direct multiply-adds          {f['direct_macs'] / 1e6:8.1f} M",
        f"  dense matmul rate             {f['matmul_gmacs']:8.1f} GMAC/s -> same MACs in "
        f"{f['matmul_same_macs_ms']:.2f} ms",
        f"  feature base / matmul time    {f['feature_base_vs_matmul']:8.2f} x   (goal <= {f['goal_ratio']:.0f} x)",
        f"  spectral vs conv2d            max abs diff {f['spectral_vs_conv2d_max_abs_diff']:.2e}, "
        f"max rel diff {f['spectral_vs_conv2d_max_rel_diff']:.2e}",
    ]
    if "crop" in r:
        c = r["crop"]
        lines.append("crop rendering: " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in c.items()))
    return "\n".join(lines)
