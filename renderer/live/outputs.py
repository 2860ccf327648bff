"""What an adaptive render leaves on disk: final.exr, final.png, spp_map.png, report.json and, with a
reference, compare.png. Every file is written atomically, so an interrupted run never leaves a truncated
image that looks finished; no pyplot (global state: unsafe in Dask worker threads)."""
from __future__ import annotations

import io
import json
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from learning.data.exr import write_exr_channels, write_png
from noisefeat.atomic import atomic_write
from noisefeat.display import display
from noisefeat.extras import require
from noisefeat.jsonout import json_default

FINAL_EXR = "final.exr"
FINAL_PNG = "final.png"
SPP_MAP = "spp_map.png"
REPORT = "report.json"
COMPARE = "compare.png"
#: every file a render leaves in its folder (`write_outputs`): what a new render removes first
RESULTS = (FINAL_EXR, FINAL_PNG, SPP_MAP, REPORT, COMPARE)


def clear_results(out: str | os.PathLike) -> list[str]:
    """Remove the previous render's results from folder `out`, so that none is left beside
    this render's checkpoint or results; the names removed. One that cannot be removed (a
    folder in its place, a read-only entry): one line, before any pass."""
    removed = []
    for name in RESULTS:
        path = Path(out) / name
        try:
            path.unlink()
            removed.append(name)
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise PermissionError(f"{path}: cannot remove the previous render's result ({exc.strerror or exc}); "
                                  "remove it or choose another output folder") from None
    return removed


def prepare_output_dir(path: str | os.PathLike) -> Path:
    """`path` as an existing, writable directory, or a one-line error before any work: not an empty name
    (`Path("")` is the current folder, where the out-folder lock did not hold) nor the root folder (by
    where the path leads: `//`, `/..` and a link to `/` too). Writability is probed by creating a file:
    permission bits do not bind root, a read-only mount binds everyone."""
    text = os.fspath(path)
    if not text:
        raise ValueError("the output folder is an empty name: name a folder (e.g. --out out)")
    if os.path.realpath(text) == os.path.realpath(os.sep):
        raise ValueError(f"{text}: the output folder cannot be the root folder; name a folder of its own")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise NotADirectoryError(f"{p}: exists and is not a directory (the output must be a folder)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PermissionError(f"{p}: cannot create the output folder ({exc.strerror or exc})") from None
    try:
        with tempfile.NamedTemporaryFile(dir=p, prefix=".write-probe-"):
            pass
    except OSError as exc:
        raise PermissionError(f"{p}: the output folder is not writable ({exc.strerror or exc})") from None
    return p


def to_srgb8(image: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """DESIGN's display transform, quantised to uint8 [H, W, 3]."""
    d = display(np.asarray(image, np.float32), exposure).numpy()
    return np.clip(np.rint(d * 255.0), 0, 255).astype(np.uint8)


#: the spp map's layout, in pixels: the map is scaled to about this size (whole factors up,
#: nearest-neighbour down), with a colour bar at its right and a legend under it
MAP_SIZE, BAR_W, BAR_GAP, MARGIN, LEGEND_ROW = 512, 18, 14, 12, 18


def spp_map_png(spp: np.ndarray, windows: Sequence[Sequence[int]], block_spp: Sequence[int],
                converged: Sequence[bool], min_spp: int, max_spp: int,
                above_target: Sequence[int] = ()) -> bytes:
    """PNG bytes: a heat map of the samples per pixel (log2 viridis from `min_spp` to `max_spp`), a colour
    bar and a legend; windows outlined, in red those that ran to max spp, in orange those a budget left
    above target (`above_target`, ids); each one's spp written on it up to 64 windows. Pillow and cmap,
    not matplotlib: its import and draw cost every render 0.5 s."""
    from PIL import Image, ImageDraw, ImageFont

    Colormap = require("cmap").Colormap        # a missing [render] extra: one line naming it

    spp = np.asarray(spp, np.float64)
    h, w = spp.shape
    lo, hi = max(1, int(min_spp)), max(int(max_spp), int(min_spp) + 1)
    lut = np.rint(Colormap("viridis").lut(256)[:, :3] * 255).astype(np.uint8)
    span = np.log2(hi) - np.log2(lo)
    level = (np.log2(np.clip(spp, lo, hi)) - np.log2(lo)) / span
    heat = Image.fromarray(lut[np.clip(np.rint(level * 255), 0, 255).astype(np.intp)])
    scale = MAP_SIZE / max(h, w)
    scale = float(max(1, int(scale))) if scale >= 1 else scale
    mw, mh = max(1, round(w * scale)), max(1, round(h * scale))
    heat = heat.resize((mw, mh), Image.NEAREST).convert("RGBA")
    font = ImageFont.load_default(size=12)
    canvas = Image.new("RGBA", (MARGIN + mw + BAR_GAP + BAR_W + 80, MARGIN + mh + 10 + 3 * LEGEND_ROW), "white")
    canvas.paste(heat, (MARGIN, MARGIN))
    overlay = Image.new("RGBA", canvas.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    left = {int(b) for b in above_target}
    colours = {"red": (220, 30, 30, 230), "orange": (255, 160, 0, 230), "white": (255, 255, 255, 90)}
    for b, ((x, y, bw, bh), s, ok) in enumerate(zip(windows, block_spp, converged)):
        ran_out = not ok and s >= max_spp
        short = b in left and not ran_out
        x0, y0 = MARGIN + round(x * scale), MARGIN + round(y * scale)
        x1, y1 = MARGIN + round((x + bw) * scale) - 1, MARGIN + round((y + bh) * scale) - 1
        draw.rectangle((x0, y0, x1, y1), outline=colours["red" if ran_out else "orange" if short else "white"],
                       width=2 if ran_out or short else 1)
        if len(windows) <= 64:
            text = f"{int(s)}"
            tx0, ty0, tx1, ty1 = draw.textbbox(((x0 + x1) / 2, (y0 + y1) / 2), text, font=font, anchor="mm")
            draw.rectangle((tx0 - 2, ty0 - 2, tx1 + 2, ty1 + 2), fill=(0, 0, 0, 115))
            draw.text(((x0 + x1) / 2, (y0 + y1) / 2), text, font=font, anchor="mm", fill=(255, 255, 255, 255))
    canvas = Image.alpha_composite(canvas, overlay)
    draw = ImageDraw.Draw(canvas)
    bx = MARGIN + mw + BAR_GAP                     # the colour bar: the same log2 scale
    ramp = lut[np.rint(np.linspace(255, 0, mh)).astype(np.intp)]
    canvas.paste(Image.fromarray(np.repeat(ramp[:, None], BAR_W, axis=1)), (bx, MARGIN))
    draw.rectangle((bx, MARGIN, bx + BAR_W - 1, MARGIN + mh - 1), outline="black")
    for t in (int(2 ** e) for e in range(31) if lo <= 2 ** e <= hi):
        ty = MARGIN + round((1 - (np.log2(t) - np.log2(lo)) / span) * (mh - 1))
        draw.line((bx + BAR_W, ty, bx + BAR_W + 3, ty), fill="black")
        draw.text((bx + BAR_W + 5, ty), str(t), font=font, anchor="lm", fill="black")
    draw.text((bx, MARGIN + mh + 4), "spp", font=font, anchor="lt", fill="black")
    stopped = int(sum(bool(c) for c in converged))
    entries = [((128, 128, 128), f"stopped by the criterion ({stopped})"),
               ((220, 30, 30), f"ran to max spp {max_spp} "
                f"({sum(1 for s, c in zip(block_spp, converged) if not c and s >= max_spp)})")]
    short = sum(1 for b in left if b < len(block_spp) and block_spp[b] < max_spp)
    if short:
        entries.append(((255, 160, 0), f"above target when the budget ended ({short})"))
    for i, (colour, label) in enumerate(entries):
        ly = MARGIN + mh + 10 + LEGEND_ROW * i + LEGEND_ROW // 3
        draw.line((MARGIN, ly, MARGIN + 22, ly), fill=colour, width=2)
        draw.text((MARGIN + 28, ly), label, font=font, anchor="lm", fill="black")
    buf = io.BytesIO()
    canvas.convert("RGB").save(buf, format="PNG")
    return buf.getvalue()


def compare_png(final8: np.ndarray, reference8: np.ndarray, windows: Sequence[Sequence[int]], spp: Sequence[int],
                errors: Sequence[float], tau: float) -> bytes:
    """PNG bytes: final image and reference side by side, each block of the final image
    labelled with its spp and its FLIP error (red: above tau, noise a person would see)."""
    require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    h, w = final8.shape[:2]
    inches = max(4.0, w / 100.0)
    fig = Figure(figsize=(2 * inches, inches * h / w + 0.3), dpi=100)
    FigureCanvasAgg(fig)
    size = max(5.0, min(11.0, 0.2 * 72.0 * inches * (windows[0][2] / w)))
    for i, (img, title) in enumerate(((final8, "final (spp, FLIP vs reference)"), (reference8, "reference"))):
        ax = fig.add_axes((i / 2, 0, 0.5, h / (h + 30)))
        ax.imshow(img, interpolation="nearest")
        ax.set_axis_off()
        ax.set_title(title, fontsize=8)
        for x, y, bw, bh in windows:
            ax.add_patch(Rectangle((x - 0.5, y - 0.5), bw, bh, fill=False, ec="cyan", lw=0.6, alpha=0.7))
        if i == 0:
            for (x, y, bw, bh), s, e in zip(windows, spp, errors):
                ax.text(x + bw / 2 - 0.5, y + bh / 2 - 0.5, f"{int(s)}\n{e:.3f}", ha="center",
                        va="center", fontsize=size, color="red" if e > tau else "#7CFC00",
                        bbox={"facecolor": "black", "alpha": 0.55, "pad": 1.5, "lw": 0})
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def write_outputs(out: str | os.PathLike, image: np.ndarray, report: dict[str, Any], *, spp: np.ndarray,
                  converged: np.ndarray, reference: np.ndarray | None = None) -> dict[str, str]:
    """Write a render's files into `out`; their paths by name. `spp` and `converged`: per
    pixel [H, W]; compare.png with a reference (and `final_vs_reference` in the report)."""
    out = Path(out)
    img = np.asarray(image, np.float32)
    if np.shape(spp) != img.shape[:2] or np.shape(converged) != img.shape[:2]:
        raise ValueError(f"per-pixel spp {np.shape(spp)} / converged {np.shape(converged)} do not match "
                         f"the image {img.shape[:2]}")
    srgb8 = to_srgb8(img, report["exposure"])
    blocks = report["blocks"]
    units = report.get("tiles", blocks)       # the spp map at the grain that stops: tiles when cut
    write_exr_channels(out / FINAL_EXR, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2],
                                         "spp": np.asarray(spp, np.float32),
                                         "converged": np.asarray(converged, np.float32)})
    write_png(out / FINAL_PNG, srgb8)
    above = [b["id"] for b in (report.get("budget") or {}).get("above_target", [])]
    atomic_write(out / SPP_MAP, spp_map_png(spp, [u["window"] for u in units], [u["spp"] for u in units],
                                            [u["converged"] for u in units], report["min_spp"], report["max_spp"],
                                            above))
    names = [FINAL_EXR, FINAL_PNG, SPP_MAP, REPORT]
    check = report.get("final_vs_reference")
    if reference is not None and check is not None:
        atomic_write(out / COMPARE, compare_png(srgb8, to_srgb8(reference, report["exposure"]),
                                                [b["window"] for b in blocks], [b["spp"] for b in blocks],
                                                check["errors"], check["tau"]))
        names.append(COMPARE)
    atomic_write(out / REPORT, (json.dumps(report, indent=2, default=json_default) + "\n").encode("utf-8"))
    return {name: str(out / name) for name in names}


def format_report(report: dict[str, Any], out: str | os.PathLike | None = None) -> str:
    """A few human-readable lines about a finished render (the non --json output)."""
    gh, gw = report["grid"]
    blocks = report["blocks"]
    rows = [" ".join(f"{b['spp']:>6}{'*' if b['converged'] else ' '}" for b in blocks[r * gw:(r + 1) * gw])
            for r in range(gh)]
    t = report["timing"]
    knob = (f" at offset {report['offset']:g}" if report.get("offset") is not None else
            f" at threshold {report['threshold']:g}" if report.get("threshold") is not None else "")
    lines = [f"scene {report['scene']}: {report['resolution'][0]}x{report['resolution'][1]}, "
             f"criterion {report['criterion']['name']}{knob}, variant {report['variant']}",
             "spp per block (* = stopped by the criterion):", *rows,
             f"saved vs uniform {report['saved_vs_uniform']:.1%}, mean spp {report['mean_spp']:.1f}, "
             f"{report['passes']} passes",
             f"wall {report['wall_s']:.2f} s = setup {t['setup_s']:.2f} + render {t['render_s']:.2f}"
             f" + features {t['features_s']:.2f} + decisions {t['decisions_s']:.2f}"
             f" + overhead {t['overhead_s']:.2f}"]
    if "early_stop_rate" in report:
        lines.append(f"vs reference: early-stop rate {report['early_stop_rate']:.1%}, "
                     f"spp ratio vs oracle {report['spp_ratio_vs_oracle']:.2f}")
    if "final_vs_reference" in report:
        f = report["final_vs_reference"]
        stopped = f.get("visible_noise_stopped_blocks")
        lines.append(f"final image vs reference: {f['visible_noise_blocks']} of {len(f['errors'])} blocks above "
                     f"the observer's FLIP threshold {f['tau']:g} (visible noise"
                     + (f"; {stopped} of them stopped by the criterion, the others ran to max spp" if stopped
                        is not None else "") + "; see compare.png)")
    budget = report.get("budget")
    if budget and budget.get("ended"):
        left = budget.get("above_target", [])
        lines.append(f"budget ended with {len(left)} block(s) above target (outlined in spp_map.png): "
                     + ", ".join(f"{x['id']}" + (f" ({x['ratio']:.2f}x)" if x["ratio"] is not None else "")
                                 for x in left[:8]) + (" ..." if len(left) > 8 else ""))
    if out is not None:
        lines.append(f"outputs in {out}")
    return "\n".join(lines)
