"""`make run`: what the product is for, on one built-in scene, in a few minutes.

A demo beside the packages, not part of them (examples/ is not installed): it runs from a
source checkout, ``python -m examples.showcase`` (``make run`` calls it so).

1. Render the scene adaptively with the default criterion (blocks stop when converged).
2. Render it again with uniform sampling, given the same wall time (``--time-limit``).
3. Write out/equal_time.png: both images side by side, and below them the block where
   the adaptive render spent the most samples, enlarged: where noise is hardest to
   remove, equal time buys the adaptive render more samples.
   At the bottom, the darkest block the criterion stopped, at 1:1 and 3x, in each panel:
   where dots on black would show.
4. Print one summary line: the share of uniform's samples used, the speed-up over a
   uniform render to the same max spp (its time from the equal-time run's rate), how
   many blocks stopped, each side's worst-block and mean error against the scene's
   reference under DESIGN's observer (version 3: the largest 16x16-tile mean FLIP of a
   block, or its dot term if larger), and per side the pixels over the dot level (display
   error > 2.5 tau, 0.05 at tau 0.02): in all, in the worst stopped block, and how many blocks
   hold more of them adaptive than uniform.

The default scene is the held-out ``studio_preview`` (never used to train or calibrate):
three spheres (rough plastic, rough aluminium, matte) on a floor under a studio light.
Its tiles stop anywhere from 64 spp (the backdrop) to 4096 (the metal sphere's
highlights), so where the samples go matters, and to max 4096 spp a hard tile can get
what it needs. The per-tile criterion had no early tile on it in the held-out evaluation
(docs/benchmarks/accuracy.md). ``spot_stage`` (a dark
stage under one spot) shows the other side: its dark tiles stop early and leave more
blocks above tau than uniform at equal time (BENCHMARKS.md, "Speed"). Both scenes' 8192-spp
references ship beside this module in half floats (`examples/references/`: studio_preview's
made by `make_reference`, ``python -m examples.showcase --scene NAME --make-reference``;
spot_stage's is its held-out stack's); a scene
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

from noisefeat.dots import REPORT_LEVEL
from noisefeat.extras import require
from renderer.live.adaptive import adaptive_render
from renderer.live.outputs import prepare_output_dir, to_srgb8
from renderer.settings import DEFAULT_CRITERION

logger = logging.getLogger(__name__)

SCENE = "studio_preview"
SETTINGS: dict[str, Any] = {"resolution": 256, "block": 64, "step": 32, "min_spp": 32, "max_spp": 4096}
#: the shipped references: samples per pixel, and their seed (far from any render's: a
#: reference shares no samples with what it judges)
REFERENCE_SPP, REFERENCE_SEED = 8192, 900001
EQUAL_TIME = "equal_time.png"
REFERENCES = Path(__file__).parent / "references"


def shipped_reference(scene: str) -> np.ndarray | None:
    """The scene's reference image shipped in examples/references/ (None if there is none)."""
    from learning.data.exr import read_exr

    path = REFERENCES / f"{scene}.exr"
    return read_exr(path) if path.is_file() else None


def make_reference(scene: str, resolution: int = SETTINGS["resolution"]) -> Path:
    """Render `scene`'s reference as the dataset builder renders a stack's
    (`renderer.dataset.stackbuild.render_mean`: REFERENCE_SPP full-frame samples of the keyed
    tracer, seed REFERENCE_SEED, which no render of the showcase uses) and write it where
    `shipped_reference` reads it, in half floats (about 150-270 KB at 256x256). Minutes on
    a CPU: run once per scene, then commit the file."""
    from learning.data.exr import write_exr
    from learning.data.variant import select_variant

    from renderer.dataset.stackbuild import BuildSettings, render_mean
    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene

    select_variant()
    build = BuildSettings()
    with BlockRenderer(load_scene(scene, resolution), grid=tuple(build.grid)) as br:
        image = render_mean(br, REFERENCE_SPP, REFERENCE_SEED, 0, build.max_lanes)
    path = REFERENCES / f"{scene}.exr"
    write_exr(path, image.astype(np.float32), half=True)
    return path


def block_errors_vs(image: np.ndarray, reference: np.ndarray, report: dict[str, Any], tau: float) -> np.ndarray:
    """Per block of `report`, the observer's error of `image` against `reference` (DESIGN's
    pooling), each block judged on its own window."""
    from learning.data.block_terms import window_errors
    from learning.data.observer import VirtualObserver

    obs = VirtualObserver(tau=tau, exposure=float(report["exposure"]))
    return window_errors(reference, image, [b["window"] for b in report["blocks"]], obs.ppd, obs.exposure,
                         obs.pooling)


def block_outliers_vs(image: np.ndarray, reference: np.ndarray, report: dict[str, Any], tau: float) -> np.ndarray:
    """int [blocks]: per block of `report`, the pixels of `image` whose display error against
    `reference` exceeds the reports' dot level (`renderer.live.report.window_dots`)."""
    from renderer.live.report import window_dots

    return window_dots(image, reference, [b["window"] for b in report["blocks"]], tau,
                       float(report["exposure"]))


def darkest_stopped(a: dict[str, Any], image: np.ndarray) -> dict[str, Any] | None:
    """The stopped block of the adaptive report whose window is darkest in `image` (where
    dots on black show first), or None if no block stopped."""
    stopped = [b for b in a["blocks"] if b["converged"]]
    if not stopped:
        return None

    def mean(b: dict[str, Any]) -> float:
        x, y, bw, bh = b["window"]
        return float(np.mean(image[y:y + bh, x:x + bw]))
    return min(stopped, key=mean)


def equal_time_png(adaptive: np.ndarray, uniform: np.ndarray, a: dict[str, Any], u: dict[str, Any],
                   reference: np.ndarray | None = None, errors: dict[str, np.ndarray] | None = None) -> bytes:
    """PNG bytes: adaptive | uniform at equal time (| the reference); below them the block
    the adaptive render spent most samples on (or, with errors, the adaptive render's worst
    block against the reference) enlarged 3x in each; and at the bottom the darkest block
    the criterion stopped, at 1:1 (pixel for pixel, as a person sees dots on black) and 3x."""
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
    dark = darkest_stopped(a, adaptive if reference is None else reference)
    x, y, bw, bh = hard["window"]
    h, w = adaptive.shape[:2]
    panels = [(adaptive, f"adaptive ({a['criterion']['name']}, tau {a.get('tau')}): mean "
                         f"{a['mean_spp']:.0f} spp, {a['wall_s']:.0f} s", "adaptive", hard["spp"]),
              (uniform, f"uniform, same time: {u['mean_spp']:.0f} spp, {u['wall_s']:.0f} s", "uniform",
               int(u["blocks"][hard["id"]]["spp"]))]
    if reference is not None:
        panels.append((reference, f"reference ({REFERENCE_SPP} spp)", None, None))
    cols = len(panels)
    dpi, col_w, pad, title = 100, 500, 20, 30           # pixels: the layout is fixed, never squeezed
    img_h = int(round((col_w - 2 * pad) * h / w))
    zoom_h = col_w - 2 * pad
    band = 0 if dark is None else 3 * dark["window"][3] + 2 * title   # the 1:1 and 3x row
    fig_w, fig_h = cols * col_w, title + img_h + title + zoom_h + pad + band + pad
    fig = Figure(figsize=(fig_w / dpi, fig_h / dpi), dpi=dpi)
    FigureCanvasAgg(fig)

    def axes(i: int, top: int, height: int) -> Any:
        """An axes in column i whose top edge is `top` pixels below the figure's top."""
        return fig.add_axes(((i * col_w + pad) / fig_w, 1 - (top + height) / fig_h,
                             (col_w - 2 * pad) / fig_w, height / fig_h))
    for i, (img, title_text, key, spp) in enumerate(panels):
        ax = axes(i, title, img_h)
        ax.imshow(img, interpolation="nearest")
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), bw, bh, fill=False, ec="red", lw=1.2))
        if dark is not None:
            dx, dy, dw, dh = dark["window"]
            ax.add_patch(Rectangle((dx - 0.5, dy - 0.5), dw, dh, fill=False, ec="cyan", lw=1.2))
        ax.set_title(title_text, fontsize=9)
        ax.set_axis_off()
        zoom = axes(i, title + img_h + title, zoom_h)
        zoom.imshow(np.repeat(np.repeat(img[y:y + bh, x:x + bw], 3, axis=0), 3, axis=1), interpolation="nearest")
        err = f", error {errors[key][hard['id']]:.4f}" if errors is not None and key else ""
        zoom.set_title(f"{what} (red), 3x" + (f": {spp} spp{err}" if spp is not None else ""), fontsize=9)
        zoom.set_axis_off()
    if dark is not None:
        _one_to_one_row(fig, panels, dark, u, errors, col_w, pad)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def _one_to_one_row(fig: Any, panels: list[tuple], dark: dict[str, Any], u: dict[str, Any],
                    errors: dict[str, np.ndarray] | None, col_w: int, pad: int) -> None:
    """The bottom row of equal_time.png: the darkest stopped block (cyan) of each panel,
    placed pixel for pixel (`figimage`, no resampling) at 1:1 and beside it at 3x, with
    its spp and (with a reference) its count of pixels over the dot level."""
    dx, dy, dw, dh = dark["window"]
    fig_w, fig_h = fig.get_figwidth() * fig.dpi, fig.get_figheight() * fig.dpi
    for i, (img, _, key, _) in enumerate(panels):
        crop = np.ascontiguousarray(img[dy:dy + dh, dx:dx + dw])
        x0 = int(i * col_w + pad)
        fig.figimage(crop, xo=x0, yo=pad, origin="upper")
        fig.figimage(np.repeat(np.repeat(crop, 3, axis=0), 3, axis=1), xo=x0 + dw + pad, yo=pad, origin="upper")
        spp = {"adaptive": dark["spp"], "uniform": int(u["blocks"][dark["id"]]["spp"])}.get(key)
        dots = f", {errors['outliers_' + key][dark['id']]} px over the dot level" \
            if errors is not None and key and f"outliers_{key}" in errors else ""
        label = "darkest stopped block (cyan), 1:1 and 3x" + (f": {spp} spp{dots}" if spp is not None else "")
        fig.text(x0 / fig_w, (pad + 3 * dh + 8) / fig_h, label, fontsize=9, va="bottom")


def summary_line(a: dict[str, Any], u: dict[str, Any], errors: dict[str, np.ndarray] | None = None) -> str:
    """What a user judges first (with `errors`: blocks above tau and the worst block against
    the reference, each side at equal time), then samples and time (share of uniform's
    samples, speed-up over uniform to max spp, blocks stopped), then the mean error and the
    dots."""
    share = 1.0 - a["saved_vs_uniform"]
    reached = max(1, min(b["spp"] for b in u["blocks"]))
    uniform_full = u["timing"]["setup_s"] + u["timing"]["render_s"] / reached * a["max_spp"]
    cost = (f"adaptive used {share:.0%} of uniform's samples (mean {a['mean_spp']:.0f} of {a['max_spp']} spp), "
            f"{uniform_full / a['wall_s']:.1f}x faster than uniform to {a['max_spp']} spp (uniform's time from its "
            f"equal-time run), {a['blocks_converged']} of {len(a['blocks'])} blocks stopped; at equal time uniform "
            f"reached {reached} spp")
    if errors is None:
        return f"{a['scene']}: {cost}"
    ea, eu, tau = errors["adaptive"], errors["uniform"], float(a["tau"])
    at_max = sum(bool(e > tau) and not b["converged"] for e, b in zip(ea, a["blocks"]))
    return (f"{a['scene']} at equal time ({a['wall_s']:.0f} s each), against the reference (tau {tau:g}): blocks "
            f"above tau {int((ea > tau).sum())} adaptive ({at_max} of them at max spp), {int((eu > tau).sum())} "
            f"uniform, of {len(ea)}; worst block {ea.max():.4f} adaptive, {eu.max():.4f} uniform; {cost}; "
            f"mean block error {ea.mean():.4f} adaptive, {eu.mean():.4f} uniform" + dots_summary(a, errors))


def dots_summary(a: dict[str, Any], errors: dict[str, np.ndarray]) -> str:
    """The summary's dots clause: per side, the pixels over the dot level (2.5 tau on the
    display) in all blocks and in the worst block the criterion stopped, and how many
    blocks hold more of them adaptive than uniform (none should)."""
    oa, ou = errors["outliers_adaptive"], errors["outliers_uniform"]
    stopped = np.array([b["converged"] for b in a["blocks"]], bool)
    worst = int(np.argmax(np.where(stopped, oa, -1))) if stopped.any() else None
    level = REPORT_LEVEL * float(a["tau"])
    where = "no block stopped" if worst is None else \
        f"worst stopped block {int(oa[worst])} adaptive, {int(ou[worst])} uniform"
    return (f"; pixels over {level:g} display error (dots): {int(oa.sum())} adaptive, {int(ou.sum())} uniform; "
            f"{where}; blocks with more adaptive than uniform: {int((oa > ou).sum())}")


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
    errors = None if reference is None else {
        **{d: block_errors_vs(img, reference, a, float(a["tau"])) for d, img in linear.items()},
        **{f"outliers_{d}": block_outliers_vs(img, reference, a, float(a["tau"])) for d, img in linear.items()}}
    show = [to_srgb8(linear[d], a["exposure"]) for d in ("adaptive", "uniform")]
    ref8 = None if reference is None else to_srgb8(reference, a["exposure"])
    atomic_write(root / EQUAL_TIME, equal_time_png(show[0], show[1], a, u, ref8, errors))
    return {"adaptive": a, "uniform": u, "errors": errors, "summary": summary_line(a, u, errors),
            "image": str(root / EQUAL_TIME)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m examples.showcase", description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=SCENE)
    p.add_argument("--out", default="out")
    p.add_argument("--make-reference", action="store_true",
                   help=f"render the scene's {REFERENCE_SPP}-spp reference into examples/references/ and stop")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.make_reference:
            print(make_reference(args.scene))
            return 0
        result = showcase(args.scene, args.out)
    except (ValueError, OSError) as exc:
        print(f"showcase: error: {exc}", file=sys.stderr)
        return 2
    print(result["summary"])
    print(f"images: {result['image']}, {args.out}/adaptive/ (final, spp_map.png, report.json), {args.out}/uniform/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
