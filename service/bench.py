"""`noisestop bench`: the speed figures of BENCHMARKS.md, measured on this machine.

Every figure is a median over repeats after a warm-up call; the accuracy cost of each
speed choice is reported beside it (e.g. the spectral feature route vs torch.conv2d).
"""
from __future__ import annotations

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


def bench_models(data: str, out_dir: Path, arches: tuple[str, ...] | None = None) -> dict[str, Any]:
    from learning.compare import TRANSFER_ARCHES, compare_models
    result = compare_models(data, out_dir, arches=TRANSFER_ARCHES if arches is None else arches)
    result.pop("fitted")
    return result


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


SECTIONS = ("features", "crop", "models")


def run_all(repeats: int = 30, only: tuple[str, ...] = ("features", "crop"), data: str | None = None,
            out_dir: str = "out/bench", arches: tuple[str, ...] | None = None) -> dict[str, Any]:
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
        results["models"] = bench_models(data, Path(out_dir), arches)
        m = results["models"]
        markdown["models"] = (f"Trained on {', '.join(m['train_scenes'])}; evaluated on the held-out "
                              f"{', '.join(m['test_scenes'])}.\n\n" + markdown_table(m["rows"]))
    results["markdown"] = markdown
    return results


def format_results(r: dict[str, Any]) -> str:
    return "\n\n".join(f"## {name}\n{body}" for name, body in r["markdown"].items())
