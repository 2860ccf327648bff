"""Plots people would rather look at than read: thresholds per block (paper Figs 10/12)
and precision against labels queried (Figs 7/16)."""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from noisefeat.extras import require

require("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from noisefeat.atomic import atomic_write  # noqa: E402

from .evaluate import stops_by_scene  # noqa: E402
from .metrics import never_spp, stop_thresholds, true_thresholds  # noqa: E402


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Write a figure atomically (temporary name, then rename) and close it."""
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi))
    finally:
        plt.close(fig)


def plot_thresholds(model, table, out_dir: str | os.PathLike, offset: float | None = None,
                    min_spp: int | None = None) -> list[Path]:
    """One PNG per scene: the model's stopping spp per block (the stop rule at its offset,
    or `offset`) against the expert's."""
    out_dir = Path(out_dir)
    paths = []
    per_scene = stops_by_scene(table, model.decision_function(table.X), model.rule(offset, min_spp))
    for scene, (v, _, th, spp) in per_scene.items():
        t_pred, t_true = stop_thresholds(v, spp), true_thresholds(th, spp)
        never = never_spp(spp)
        b = np.arange(len(t_true))
        fig, ax = plt.subplots(figsize=(7, 3.2))
        ax.plot(b, t_true, "o-", color="black", label="expert (virtual observer)")
        ax.plot(b, t_pred, "s--", color="tab:orange", label=f"model ({model.name})")
        early = t_pred < t_true
        ax.scatter(b[early], t_pred[early], s=90, facecolors="none", edgecolors="red",
                   label="early stop (visible noise)")
        ax.axhline(never, color="grey", lw=0.7, ls=":")
        ax.text(0, never, " never converged", va="bottom", fontsize=7, color="grey")
        ax.set_xlabel("block (row-major)")
        ax.set_ylabel("threshold (spp)")
        ax.set_xticks(b)
        ax.set_title(f"{scene}: stopping threshold per block", fontsize=9)
        ax.legend(fontsize=7, loc="best")
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / f"thresholds-{scene}.png"))
    return paths


def plot_learning_curves(histories: Mapping[str, Sequence[Mapping]], path: str | os.PathLike,
                         pool_size: int | None = None) -> Path:
    """Held-out precision against the number of labels queried, one line per model."""
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, hist in histories.items():
        pts = [(h["queries"], h["val_precision"]) for h in hist if "val_precision" in h]
        if pts:
            q, p = zip(*pts)
            ax.plot(q, p, label=name)
    ax.set_xlabel("labels queried" + (f" (pool: {pool_size})" if pool_size else ""))
    ax.set_ylabel("precision on held-out scenes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, Path(path))


def plot_cost_accuracy(rows: Sequence[Mapping], path: str | os.PathLike, title: str = "") -> Path:
    """Decision cost (test time per 101 sub-images, log x) against precision, one point per
    model: the models a user would pick from lie on the upper-left frontier."""
    pts = [r for r in rows if r.get("precision") is not None and r.get("test_101_s")]
    if not pts:
        raise ValueError("no model row has both a precision and a positive test time")
    fig, ax = plt.subplots(figsize=(8, 4.6))
    for r in pts:
        feature = str(r["model"]).startswith("dsvm")
        ax.scatter(r["test_101_s"], r["precision"], s=40, zorder=3,
                   marker="o" if feature else "s", color="tab:blue" if feature else "tab:gray")
    ax.set_xscale("log")
    xs = [r["test_101_s"] for r in pts]
    ax.set_xlim(min(xs) / 1.5, max(xs) * 4)           # room for the labels on the right
    ys = [r["precision"] for r in pts]
    pad = max(0.02, 0.1 * (max(ys) - min(ys)))
    ax.set_ylim(min(ys) - pad, max(ys) + pad)
    fig.canvas.draw()
    placed: list[tuple[float, float, float, float]] = []
    for r in sorted(pts, key=lambda r: (r["test_101_s"], -r["precision"])):
        label = str(r["model"]).replace(" (untrained base)", "*")
        _label_clear_of(ax, (r["test_101_s"], r["precision"]), label, placed)
    ax.set_xlabel("decision cost: test time per 101 sub-images (s, features included)")
    ax.set_ylabel("precision on held-out scenes")
    ax.set_title(title or "decision cost vs accuracy (circles: feature SVMs; * untrained conv base)",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, Path(path))


def _label_clear_of(ax, xy: tuple[float, float], label: str,
                    placed: list[tuple[float, float, float, float]]) -> None:
    """Annotate xy at the first offset whose text box (display pixels, estimated from the
    label length) overlaps no label placed before; records the box in `placed`."""
    px, py = ax.transData.transform(xy)
    scale = ax.figure.dpi / 72.0
    w, h = 5.2 * len(label) * scale, 9.0 * scale
    for dx, dy in ((5, 4), (5, -11), (5, 15), (5, -22), (5, 26), (5, -33), (5, 37)):
        x0, y0 = px + dx * scale, py + dy * scale
        box = (x0, y0, x0 + w, y0 + h)
        if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in placed):
            break
    placed.append(box)
    ax.annotate(label, xy, textcoords="offset points", xytext=(dx, dy), fontsize=8,
                arrowprops=None if (dx, dy) == (5, 4) else {"arrowstyle": "-", "lw": 0.4, "color": "grey"})
