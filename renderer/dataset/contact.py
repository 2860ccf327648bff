"""Contact sheet of a stack: a few levels, the reference and the quick image side by side,
with the grid and each block's threshold drawn, to check labels by eye."""
from __future__ import annotations

import os
from pathlib import Path

from noisefeat.extras import require

require("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from noisefeat.atomic import atomic_write  # noqa: E402

from learning.data.stack import Stack  # noqa: E402
from noisefeat.display import display  # noqa: E402


def _draw_grid(ax, stack: Stack, labels: list[str] | None = None) -> None:
    (gh, gw), (bh, bw) = stack.grid, stack.block
    for r in range(1, gh):
        ax.axhline(r * bh - 0.5, color="cyan", lw=0.6, alpha=0.7)
    for c in range(1, gw):
        ax.axvline(c * bw - 0.5, color="cyan", lw=0.6, alpha=0.7)
    if labels:
        for b, text in enumerate(labels):
            r, c = divmod(b, gw)
            ax.text(c * bw + bw / 2, r * bh + bh / 2, text, color="yellow", ha="center", va="center",
                    fontsize=7, bbox={"facecolor": "black", "alpha": 0.5, "pad": 1, "lw": 0})


def contact_sheet(stack: Stack, path: str | os.PathLike, n_levels: int = 4) -> Path:
    """Write the sheet as PNG (atomically) and return its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    picks = sorted({int(round(i)) for i in np.linspace(0, stack.n_levels - 1, n_levels)})
    panels = [(f"{stack.spp[k]} spp", stack.level(k)) for k in picks]
    panels.append((f"reference {stack.reference_spp} spp", stack.reference()))
    if stack.has_quick:
        panels.append((f"quick ({stack.quick_description})", stack.quick()))
    th_text = ["never" if t is None else str(t) for t in stack.thresholds or [None] * stack.n_blocks]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.6), dpi=110)
    for ax, (title, img) in zip(np.atleast_1d(axes), panels):
        ax.imshow(display(img).numpy(), interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set(xticks=[], yticks=[])
        _draw_grid(ax, stack, th_text if title.startswith("reference") else None)
    fig.suptitle(f"{stack.scene}: block thresholds (spp) drawn on the reference", fontsize=9)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp))
    finally:
        plt.close(fig)
