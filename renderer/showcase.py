"""`make run`: what the product is for, on one built-in scene, in a few minutes.

1. Render the scene adaptively with the default criterion (blocks stop when converged).
2. Render it again with uniform sampling, given the same wall time (``--time-limit``).
3. Write out/equal_time.png: both images side by side, and below them the block where
   the adaptive render spent the most samples, enlarged: where noise is hardest to
   remove, equal time buys the adaptive render more samples.
4. Print one summary line: the share of uniform's samples used, the speed-up over a
   uniform render to the same max spp (its time from the equal-time run's rate), how
   many blocks stopped, and each side's worst-block and mean error against the scene's
   reference under DESIGN's observer (the largest 16x16-tile mean FLIP of a block).

The default scene is the held-out ``spot_stage`` (never used to train or calibrate): a
dark stage lit by one spot, where the blocks need from 32 to 2048 spp, so where the
samples go matters most. Its 8192-spp reference ships with the package
(`renderer/references/spot_stage.exr`, the held-out stack's, in half floats); a scene
without one gets no error figures.
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
from noisefeat.extras import require

logger = logging.getLogger(__name__)

SCENE = "spot_stage"
SETTINGS: dict[str, Any] = {"resolution": 256, "block": 64, "step": 32, "min_spp": 32, "max_spp": 2048}
EQUAL_TIME = "equal_time.png"
REFERENCES = Path(__file__).parent / "references"


def shipped_reference(scene: str) -> np.ndarray | None:
    """The scene's reference image shipped with the package (None if there is none)."""
    from learning.data.exr import read_exr

    path = REFERENCES / f"{scene}.exr"
    return read_exr(path) if path.is_file() else None


def block_errors_vs(image: np.ndarray, reference: np.ndarray, report: dict[str, Any], tau: float) -> np.ndarray:
    """Per block of `report`, the observer's error of `image` against `reference` (DESIGN's
    pooling), each block judged on its own window."""
    from learning.data.observer import VirtualObserver

    obs = VirtualObserver(tau=tau, exposure=float(report.get("exposure", 0.0)))
    out = []
    for b in report["blocks"]:
        x, y, bw, bh = b["window"]
        win = (slice(y, y + bh), slice(x, x + bw))
        out.append(float(obs.errors(reference[win], image[win][None], (1, 1))[0, 0]))
    return np.asarray(out)


def equal_time_png(adaptive: np.ndarray, uniform: np.ndarray, a: dict[str, Any], u: dict[str, Any],
                   reference: np.ndarray | None = None, errors: dict[str, np.ndarray] | None = None) -> bytes:
    """PNG bytes: adaptive | uniform at equal time (| the reference), and below them the
    block the adaptive render spent most samples on (or, with errors, the adaptive
    render's worst block against the reference) enlarged 3x in each."""
    require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    if errors is not None:
        hard = a["blocks"][int(np.argmax(errors["adaptive"]))]
        what = "worst adaptive block"
    else:
        hard = max(a["blocks"], key=lambda b: b["spp"])
        what = "block with most samples"
    x, y, bw, bh = hard["window"]
    h, w = adaptive.shape[:2]
    panels = [(adaptive, f"adaptive ({a['criterion']['name']}, tau {a.get('tau')}): mean "
                         f"{a['mean_spp']:.0f} spp, {a['wall_s']:.0f} s", "adaptive", hard["spp"]),
              (uniform, f"uniform, same time: {u['mean_spp']:.0f} spp, {u['wall_s']:.0f} s", "uniform",
               int(u["blocks"][hard["id"]]["spp"]))]
    if reference is not None:
        panels.append((reference, "reference (8192 spp)", None, None))
    cols = len(panels)
    fig = Figure(figsize=(5 * cols, 5 * h / w + 5.4), dpi=100)
    FigureCanvasAgg(fig)
    for i, (img, title, key, spp) in enumerate(panels):
        ax = fig.add_subplot(2, cols, i + 1)
        ax.imshow(img, interpolation="nearest")
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), bw, bh, fill=False, ec="red", lw=1.2))
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
        zoom = fig.add_subplot(2, cols, cols + i + 1)
        zoom.imshow(np.repeat(np.repeat(img[y:y + bh, x:x + bw], 3, axis=0), 3, axis=1), interpolation="nearest")
        err = f", error {errors[key][hard['id']]:.4f}" if errors is not None and key else ""
        zoom.set_title(f"{what}, 3x" + (f": {spp} spp{err}" if spp is not None else ""), fontsize=9)
        zoom.set_axis_off()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def summary_line(a: dict[str, Any], u: dict[str, Any], errors: dict[str, np.ndarray] | None = None) -> str:
    """Share of uniform's samples, speed-up over uniform to max spp, blocks stopped, and
    (with `errors`) each side's worst-block and mean error against the reference."""
    share = 1.0 - a["saved_vs_uniform"]
    reached = max(1, min(b["spp"] for b in u["blocks"]))
    uniform_full = u["timing"]["setup_s"] + u["timing"]["render_s"] / reached * a["max_spp"]
    line = (f"{a['scene']}: adaptive used {share:.0%} of uniform's samples (mean {a['mean_spp']:.0f} of "
            f"{a['max_spp']} spp), {uniform_full / a['wall_s']:.1f}x faster than uniform to {a['max_spp']} spp "
            f"(uniform's time from its equal-time run), {a['blocks_converged']} of {len(a['blocks'])} blocks "
            f"stopped; at equal time uniform reached {reached} spp")
    if errors is None:
        return line
    ea, eu = errors["adaptive"], errors["uniform"]
    return (line + f"; error against the reference (tau {a['tau']:g}): worst block {ea.max():.4f} adaptive, "
            f"{eu.max():.4f} uniform; mean {ea.mean():.4f} adaptive, {eu.mean():.4f} uniform; adaptive blocks "
            f"above tau: {int((ea > a['tau']).sum())} ({sum(bool(e > a['tau']) and not b['converged'] for e, b in zip(ea, a['blocks']))} "
            f"of them at max spp)")


def showcase(scene: str = SCENE, out: str | Path = "out", **settings: Any) -> dict[str, Any]:
    """Adaptive, then uniform for the same time; write equal_time.png; return both reports."""
    from learning.data.exr import read_exr
    from noisefeat.atomic import atomic_write

    root = prepare_output_dir(out)
    opts = {**SETTINGS, **settings}
    a = adaptive_render(scene, root / "adaptive", DEFAULT_CRITERION, **opts)
    u = adaptive_render(scene, root / "uniform", "uniform", time_limit=a["wall_s"], **opts)
    linear = {d: read_exr(root / d / "final.exr") for d in ("adaptive", "uniform")}
    reference = shipped_reference(scene)
    if reference is not None and reference.shape != linear["adaptive"].shape:
        logger.warning("the shipped reference of %s is %s, the render %s: no error figures", scene,
                       reference.shape, linear["adaptive"].shape)
        reference = None
    errors = None if reference is None else \
        {d: block_errors_vs(img, reference, a, float(a["tau"])) for d, img in linear.items()}
    show = [to_srgb8(linear[d], a.get("exposure", 0.0)) for d in ("adaptive", "uniform")]
    ref8 = None if reference is None else to_srgb8(reference, a.get("exposure", 0.0))
    atomic_write(root / EQUAL_TIME, equal_time_png(show[0], show[1], a, u, ref8, errors))
    return {"adaptive": a, "uniform": u, "errors": errors, "summary": summary_line(a, u, errors),
            "image": str(root / EQUAL_TIME)}


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
