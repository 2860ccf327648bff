"""The charts of BENCHMARKS.md: what a user picks a setting from, drawn rather than tabled.

Each function takes the result rows a `noisestop bench` section measured and writes one PNG
atomically; none of them measures anything.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

from noisefeat.extras import require

require("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from learning.evaluation.plots import save_figure  # noqa: E402

EARLY_STOP_TARGET = 0.05


def save(fig, path: str | os.PathLike, dpi: int = 100) -> str:
    return str(save_figure(fig, path, dpi))


def pareto(curves: Sequence[Mapping], points: Sequence[Mapping], scenes: Sequence[str],
           path: str | os.PathLike, title: str = "held-out scenes") -> str:
    """Samples vs oracle (x) against early-stop rate (y): one line per criterion.

    `curves`: {"label", "rows" (each with early_stop_rate and spp_ratio_vs_oracle),
    "dashed"?, "marker"?}; `points`: {"label", "row"}, the defaults, circled."""
    fig, ax = plt.subplots(figsize=(8.5, 5.2))
    for i, c in enumerate(curves):
        rows = c["rows"]
        ax.plot([r["spp_ratio_vs_oracle"] for r in rows], [r["early_stop_rate"] for r in rows],
                c.get("marker", ".") + ("--" if c.get("dashed") else "-"), ms=4, color=c.get("color", f"C{i}"),
                lw=c.get("lw", 1.2), label=c["label"])
    ax.plot([1.0], [0.0], "k*", ms=14, label="oracle")
    for j, p in enumerate(points):
        ax.plot([p["row"]["spp_ratio_vs_oracle"]], [p["row"]["early_stop_rate"]], "o", ms=14 - 3 * j,
                mfc="none", mec=("red", "blue", "green")[j % 3], mew=2, label=p["label"])
    ax.axhline(EARLY_STOP_TARGET, color="red", lw=0.6, ls=":")
    ax.set_xlabel("samples spent / oracle's samples")
    ax.set_ylabel("early-stop rate (blocks stopped with visible noise)")
    ax.set_title(f"speed / accuracy on {len(scenes)} {title} (lower left is better)", fontsize=9)
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


def step_size(rows: Sequence[Mapping], scene: str, path: str | os.PathLike,
              criteria: Sequence[str] = ("model", "flip")) -> str:
    """Render step (spp per pass): wall time of a real render, and held-out early stops and
    samples vs oracle, side by side, one line per criterion."""
    steps = [r["step"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9.5, 3.6))
    for i, name in enumerate(criteria):
        a.plot(steps, [r[name]["wall_s"] for r in rows], "o-", color=f"C{i}", label=f"{name}: wall time")
        b.plot(steps, [r[name]["early_stop_rate"] for r in rows], "o-", color=f"C{i}",
               label=f"{name}: early-stop rate")
        b.plot(steps, [r[name]["spp_ratio_vs_oracle"] - 1 for r in rows], "s--", color=f"C{i}",
               label=f"{name}: extra samples vs oracle (ratio - 1)")
    a.set_ylabel(f"wall time, {scene} (s)")
    a.legend(fontsize=7)
    b.axhline(EARLY_STOP_TARGET, color="red", lw=0.6, ls=":")
    b.legend(fontsize=7)
    b.set_ylim(bottom=0)
    for ax in (a, b):
        ax.set_xscale("log", base=2)
        ax.set_xticks(steps, [str(s) for s in steps])
        ax.set_xlabel("step (spp per pass)")
        ax.grid(alpha=0.3)
    a.set_title("render cost", fontsize=9)
    b.set_title("held-out scenes", fontsize=9)
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


def realscenes(scenes: Sequence[Mapping], path: str | os.PathLike, tau: float) -> str:
    """Per suite scene, `mi.render`'s worst block against its render seconds (two seeds, a
    point every 64 spp), with the default render (star) and the time-limited one (triangle)
    at their wall times: a point below and left of the curves is a picture `mi.render` has
    not reached by then (`bench realscenes`)."""
    n = len(scenes)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.9 * rows), squeeze=False)
    for ax, s in zip(axes.flat, scenes):
        for i, (seed, pts) in enumerate(s["curves"].items()):
            ax.plot([p["t"] for p in pts], [p["worst"] for p in pts], "-", color=f"C{i}", lw=1.1,
                    label=f"mi.render, seed {seed}")
        a, lim = s["adaptive"], s["time_limit"]
        ax.plot([a["wall_s"]], [a["worst"]], "*", color="k", ms=11, label="noisestop (default)")
        ax.plot([lim["ours"]["wall_s"]], [lim["ours"]["worst"]], "^", color="C3", ms=8,
                label="noisestop --time-limit")
        ax.axhline(tau, color="0.6", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_title(f"{s['scene']}: {s['equal_time_verdict']}", fontsize=9)
        ax.set_xlabel("seconds", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].set_ylabel("worst block (FLIP)", fontsize=8)
    axes.flat[0].legend(fontsize=6, loc="upper right")
    fig.tight_layout()
    return save(fig, path)
