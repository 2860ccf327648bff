"""The charts of BENCHMARKS.md: what a user picks a setting from, drawn rather than tabled.

Each function takes the result rows a `noisestop bench` section measured and writes one PNG
atomically; none of them measures anything.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from learning.plots import save_figure  # noqa: E402

EARLY_STOP_TARGET = 0.05


def save(fig, path: str | os.PathLike, dpi: int = 100) -> str:
    return str(save_figure(fig, path, dpi))


def pareto(curves: Mapping[str, Sequence[Mapping]], variance: Sequence[Mapping],
           default: Mapping | None, default_label: str, scenes: Sequence[str],
           path: str | os.PathLike) -> str:
    """Samples vs oracle (x) against early-stop rate (y): one line per criterion."""
    fig, ax = plt.subplots(figsize=(8, 5))
    for i, (name, rows) in enumerate(curves.items()):
        style = "--" if "albedo" in name else "-"
        marker = "s" if name.startswith("svm") else "."
        ax.plot([r["spp_ratio_vs_oracle"] for r in rows], [r["early_stop_rate"] for r in rows],
                marker + style, ms=4, color=f"C{i}", label=f"{name}, offset -1..3")
    ax.plot([r["spp_ratio_vs_oracle"] for r in variance], [r["early_stop_rate"] for r in variance],
            "x:", color="grey", label="variance (Cycles), threshold "
            f"{variance[0]['threshold']}..{variance[-1]['threshold']}")
    ax.plot([1.0], [0.0], "k*", ms=14, label="oracle")
    if default is not None:
        ax.plot([default["spp_ratio_vs_oracle"]], [default["early_stop_rate"]], "o", ms=14,
                mfc="none", mec="red", mew=2, label=default_label)
    ax.axhline(EARLY_STOP_TARGET, color="red", lw=0.6, ls=":")
    ax.set_xlabel("samples spent / oracle's samples (held-out scenes)")
    ax.set_ylabel("early-stop rate (blocks stopped with visible noise)")
    ax.set_title(f"speed / accuracy on held-out scenes: {', '.join(scenes)} "
                 "(lower left is better)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return save(fig, path)


def spp_maps(maps: Mapping[str, Mapping[str, np.ndarray]], max_spp: int, title: str,
             path: str | os.PathLike) -> str:
    """Per scene, one heat map per row name ('model', 'oracle'): spp per block, annotated."""
    names = list(next(iter(maps.values())))
    fig, axes = plt.subplots(len(names), len(maps), figsize=(2.6 * len(maps), 2.6 * len(names)),
                             squeeze=False)
    for j, (scene, per) in enumerate(sorted(maps.items())):
        for i, name in enumerate(names):
            m, ax = per[name], axes[i, j]
            ax.imshow(m, cmap="magma", vmin=0, vmax=max_spp)
            for (r, c), val in np.ndenumerate(m):
                ax.text(c, r, str(int(val)), ha="center", va="center", fontsize=7,
                        color="white" if val < 0.6 * max_spp else "black")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{scene}: {name}, {int(m.sum())} spp", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save(fig, path, dpi=90)


def step_size(rows: Sequence[Mapping], scene: str, path: str | os.PathLike) -> str:
    """Render step (spp per pass): wall time of a real render, and held-out early stops and
    samples vs oracle, side by side."""
    steps = [r["step"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    a.plot(steps, [r["wall_s"] for r in rows], "o-", color="C0")
    a.set_ylabel(f"wall time, {scene} (s)")
    a2 = a.twinx()
    a2.plot(steps, [r["saved_vs_uniform"] for r in rows], "s--", color="C2")
    a2.set_ylabel("saved vs uniform", color="C2")
    b.plot(steps, [r["early_stop_rate"] for r in rows], "o-", color="C3", label="early-stop rate")
    b.plot(steps, [r["spp_ratio_vs_oracle"] - 1 for r in rows], "s--", color="C1",
           label="extra samples vs oracle (ratio - 1)")
    b.axhline(EARLY_STOP_TARGET, color="red", lw=0.6, ls=":")
    b.legend(fontsize=7)
    b.set_ylim(bottom=0)
    for ax in (a, b):
        ax.set_xscale("log", base=2)
        ax.set_xticks(steps, [str(s) for s in steps])
        ax.set_xlabel("step (spp per pass)")
        ax.grid(alpha=0.3)
    a.set_title("render cost", fontsize=9)
    b.set_title("held-out scenes, bundled model", fontsize=9)
    fig.tight_layout()
    return save(fig, path)


def ablation(rows: Sequence[Mapping], path: str | os.PathLike) -> str:
    """Feature-pipeline switches: precision and early-stop rate per combination (bars)."""
    labels = [f"{r['weights'][:6]}/{r['quick']}/{'wav' if r['wavelet'] else 'no wav'}" for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(7, 0.7 * len(rows)), 3.8))
    ax.bar(x - 0.2, [r["precision"] for r in rows], 0.4, label="precision", color="C0")
    ax.bar(x + 0.2, [r["early_stop_rate"] for r in rows], 0.4, label="early-stop rate", color="C3")
    ax.axhline(EARLY_STOP_TARGET, color="red", lw=0.6, ls=":")
    ax.set_xticks(x, labels, rotation=35, ha="right", fontsize=7)
    ax.set_ylim(0, 1)
    ax.set_title("DSVM on held-out scenes: conv weights / quick image / wavelet layer (offset 0)",
                 fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save(fig, path)
