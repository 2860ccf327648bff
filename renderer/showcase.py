"""`make run`: what the product is for, on one built-in scene, in a few minutes.

1. Render the scene adaptively with the default criterion (blocks stop when converged).
2. Render it again with uniform sampling, given the same wall time (``--time-limit``).
3. Write out/equal_time.png: both images side by side, and below them the block where
   the adaptive render spent the most samples, enlarged: where noise is hardest to
   remove, equal time buys the adaptive render more samples.
4. Print one summary line: the share of uniform's samples used, the speed-up over a
   uniform render to the same max spp (its time from the equal-time run's rate), and how
   many blocks stopped.

The default scene is the held-out ``spot_stage`` (never used to train or calibrate): a
dark stage lit by one spot, where the blocks need from 32 to 2048 spp (its 8192-spp
reference: the oracle spends 18 % of uniform's samples at max 2048 spp, README "make
run"), so where the samples go matters most. Some of its near-black blocks stop at 32 spp
with a few firefly dots that both the flip criterion and the virtual observer let pass
(look at the equal-time image's background).
"""
from __future__ import annotations

import argparse
import io
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .adaptive import adaptive_render
from .names import DEFAULT_CRITERION
from .outputs import prepare_output_dir, to_srgb8

logger = logging.getLogger(__name__)

SCENE = "spot_stage"
SETTINGS: dict[str, Any] = {"resolution": 256, "block": 64, "step": 32, "min_spp": 32, "max_spp": 2048}
EQUAL_TIME = "equal_time.png"


def equal_time_png(adaptive: np.ndarray, uniform: np.ndarray, a: dict[str, Any], u: dict[str, Any]) -> bytes:
    """PNG bytes: adaptive | uniform at equal time, and the hardest block of each enlarged."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    hard = max(a["blocks"], key=lambda b: b["spp"])
    x, y, bw, bh = hard["window"]
    h, w = adaptive.shape[:2]
    fig = Figure(figsize=(10, 5 * h / w + 5.4), dpi=100)
    FigureCanvasAgg(fig)
    titles = (f"adaptive ({a['criterion']['name']}): mean {a['mean_spp']:.0f} spp, {a['wall_s']:.0f} s",
              f"uniform, same time: {u['mean_spp']:.0f} spp, {u['wall_s']:.0f} s")
    for i, (img, title) in enumerate(((adaptive, titles[0]), (uniform, titles[1]))):
        ax = fig.add_subplot(2, 2, i + 1)
        ax.imshow(img, interpolation="nearest")
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), bw, bh, fill=False, ec="red", lw=1.2))
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
        zoom = fig.add_subplot(2, 2, i + 3)
        zoom.imshow(img[y:y + bh, x:x + bw], interpolation="nearest")
        spp = hard["spp"] if i == 0 else int(u["blocks"][hard["id"]]["spp"])
        zoom.set_title(f"red block enlarged: {spp} spp", fontsize=9)
        zoom.set_axis_off()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def summary_line(a: dict[str, Any], u: dict[str, Any]) -> str:
    """Share of uniform's samples, speed-up over uniform to max spp, blocks stopped."""
    share = 1.0 - a["saved_vs_uniform"]
    reached = max(1, min(b["spp"] for b in u["blocks"]))
    uniform_full = u["timing"]["setup_s"] + u["timing"]["render_s"] / reached * a["max_spp"]
    return (f"{a['scene']}: adaptive used {share:.0%} of uniform's samples (mean {a['mean_spp']:.0f} of "
            f"{a['max_spp']} spp), {uniform_full / a['wall_s']:.1f}x faster than uniform to {a['max_spp']} spp "
            f"(uniform's time from its equal-time run), {a['blocks_converged']} of {len(a['blocks'])} blocks "
            f"stopped; at equal time uniform reached {reached} spp")


def showcase(scene: str = SCENE, out: str | Path = "out", **settings: Any) -> dict[str, Any]:
    """Adaptive, then uniform for the same time; write equal_time.png; return both reports."""
    from learning.data.exr import atomic_write_bytes, read_exr

    root = prepare_output_dir(out)
    opts = {**SETTINGS, **settings}
    a = adaptive_render(scene, root / "adaptive", DEFAULT_CRITERION, **opts)
    u = adaptive_render(scene, root / "uniform", "uniform", time_limit=a["wall_s"], **opts)
    images = [to_srgb8(read_exr(root / d / "final.exr"), a.get("exposure", 0.0)) for d in ("adaptive", "uniform")]
    atomic_write_bytes(root / EQUAL_TIME, equal_time_png(images[0], images[1], a, u))
    return {"adaptive": a, "uniform": u, "summary": summary_line(a, u), "image": str(root / EQUAL_TIME)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m renderer.showcase", description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=SCENE)
    p.add_argument("--out", default="out")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        result = showcase(args.scene, args.out)
    except (ValueError, OSError) as exc:
        print(f"showcase: error: {exc}", file=sys.stderr)
        return 2
    print(result["summary"])
    print(f"images: {result['image']}, {args.out}/adaptive/ (final, spp_map.png, report.json), {args.out}/uniform/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
