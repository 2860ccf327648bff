"""The adaptive render's report.json: per block window (and tile) spp and verdict history, totals,
the ledger's counters and timers, and against a reference DESIGN's early-stop metrics and what a
person would see flipping between final.png and it; read from a finished render's live objects."""
from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.data.stack import Stack

from ..criteria import COUNTER_NAMES, external_counters
from .block_windows import compose
from .ledger import Ledger
from .passloop import PassLoop, schedule
from .plan import RenderPlan
from .progress import RunSettings
from .result import RenderResult

if TYPE_CHECKING:
    from .session import RenderSession

logger = logging.getLogger(__name__)

#: a report.json object or part (DESIGN fixes its keys: they are not this code's names)
Json = dict[str, Any]


def render_report(plan: RenderPlan, settings: RunSettings, loop: PassLoop, ledger: Ledger, wall_s: float) -> Json:
    """report.json's core: settings, units, counters and timers (`wall_s`: every attempt's
    seconds so far), and the early-stop metrics against the plan's labelled stack."""
    br, ref = plan.renderer, plan.reference.stack
    n, T, max_spp = br.n_blocks, br.tiles_per_block, settings.max_spp
    counters, timers, wall = ledger.counters, ledger.timers, float(wall_s)
    spp, nonfinite, converged = loop.acc.spp_all(), loop.acc.nonfinite_all(), ~loop.active   # per unit (block or tile)
    units = [{"id": u, "window": list(br.unit_window(u)), "spp": int(spp[u]), "converged": bool(converged[u]),
              "stop_spp": int(loop.stop_spp[u]) if converged[u] else None, "nonfinite": int(nonfinite[u]),
              "history": [[s, v] for s, v in loop.events.get(u, [])]} for u in range(n * T)]
    block_spp, block_done = spp.reshape(n, T), converged.reshape(n, T).all(axis=1)
    if T == 1:
        blocks = units
    else:                                     # a block: its tiles' mean spp, done when all of them are
        blocks = [{"id": b, "window": list(br.window(b)), "spp": int(round(float(block_spp[b].mean()))),
                   "converged": bool(block_done[b]), "stop_spp": int(block_spp[b].max()) if block_done[b] else None,
                   "nonfinite": int(nonfinite.reshape(n, T)[b].sum()), "history": []} for b in range(n)]
        for t in units:
            t["block"] = t["id"] // T
    setup_s, render_s, features_s, decisions_s = (float(timers.get(k, 0.0))
                                                  for k in ("setup_s", "render_s", "features_s", "decisions_s"))
    described = settings.criterion
    report: Json = {
        "scene": plan.label, "variant": plan.variant, "criterion": described,
        # the speed/accuracy knob the stops were made at: the model's decision offset
        # (None for other criteria, and for a server's own offset), flip's or variance's threshold
        "offset": described.get("offset"), "threshold": described.get("threshold"),
        # the noise target: the observer's tau the knob above was calibrated for (flip: c = c(tau))
        "tau": settings.tau,
        "resolution": [br.width, br.height], "grid": list(br.grid), "block": [br.block_h, br.block_w],
        "tile": [br.tile_h, br.tile_w], "step": settings.step, "min_spp": settings.min_spp, "max_spp": max_spp,
        # when units are judged (`renderer.live.passloop.next_decision`): where stops can land
        "decide_skip": settings.decide_skip, "decide_growth": settings.decide_growth,
        "seed": settings.seed, "exposure": settings.exposure, "quick": settings.quick, "passes": loop.rows,
        # samples_spent counts shared window pixels once per window
        "samples_spent": int(spp.sum()) * br.tile_h * br.tile_w, "mean_spp": float(spp.mean()),
        "saved_vs_uniform": 1.0 - float(spp.sum()) / (n * T * max_spp),
        "blocks_converged": int(block_done.sum()), "tiles_converged": int(converged.sum()), "wall_s": wall,
        "timing": {"setup_s": setup_s, "render_s": render_s, "features_s": features_s, "decisions_s": decisions_s,
                   "overhead_s": max(0.0, wall - setup_s - render_s - features_s - decisions_s)},
        "counters": {"blocks_rendered_per_pass": loop.rendered.tolist(),
                     "blocks_rendered": int(loop.rendered.sum()),
                     "blocks_featured": int(counters.get("units_featured", 0)),
                     "decisions": int(counters.get("units_asked", 0)),
                     **external_counters({k: int(counters.get(k, 0)) for k in COUNTER_NAMES})},
        "blocks": blocks, **({"tiles": units} if T > 1 else {}),
    }
    if ref is not None:
        report.update(against_reference(ref, block_spp.mean(axis=1) if T > 1 else spp, block_done, settings))
        for b, t in enumerate(ref.thresholds or []):
            report["blocks"][b]["true_threshold"] = t
    return report


def against_reference(ref: Stack, spp: np.ndarray, converged: np.ndarray, settings: RunSettings) -> Json:
    """DESIGN metrics against a labelled stack's true thresholds T_b. The oracle spends what
    `OracleCriterion` would in this loop: the first pass at or after min_spp and T_b (censored:
    max_spp); a stop below T_b is early (censored: any stop)."""
    if ref.thresholds is None:
        raise ValueError(f"{ref.path}: reference stack has no thresholds (not labelled)")
    max_spp, min_spp = settings.max_spp, settings.min_spp
    cum = schedule(settings.step, max_spp)
    oracle = []
    for t in ref.thresholds:
        ok = cum[cum >= max(min_spp, t)] if t is not None else cum[:0]
        oracle.append(int(ok[0]) if ok.size else int(max_spp))
    early = [bool(converged[b] and (t is None or spp[b] < t)) for b, t in enumerate(ref.thresholds)]
    return {"reference": {"path": str(ref.path), "scene": ref.scene, "thresholds": list(ref.thresholds),
                          "oracle_spp": oracle},
            "early_stop_rate": float(np.mean(early)),
            "spp_ratio_vs_oracle": float(spp.sum()) / float(sum(oracle))}


def window_dots(image: np.ndarray, reference: np.ndarray, windows: Sequence[Sequence[int]], tau: float,
                exposure: float = 0.0) -> np.ndarray:
    """int64 [windows]: per (x, y, w, h) window, the pixels of `image` more than the dot
    level (2.5 tau) off `reference` on the display."""
    from noisefeat.dots import count_outliers

    return np.array([count_outliers(image[y:y + h, x:x + w], reference[y:y + h, x:x + w], tau, exposure)
                     for x, y, w, h in windows], np.int64)


def final_vs_reference(image: np.ndarray, reference: np.ndarray, grid: tuple[int, int], tau: float,
                       exposure: float = 0.0, stopped: np.ndarray | None = None,
                       windows: Sequence[Sequence[int]] | None = None) -> Json:
    """What a person would see flipping between final.png and the reference: the observer's per-block
    error, the blocks above tau (and of them those `stopped`), per block the pixels over the dot level
    (`window_dots`), and among the stopped blocks the most dots and how many hold more than a block may
    (16 in 64x64). `windows` (x, y, w, h) per block: instead of cutting the frame into `grid` (overlapping
    windows do not tile it)."""
    from learning.data.block_terms import window_errors
    from learning.data.observer import VirtualObserver
    from noisefeat.dots import REPORT_LEVEL, dot_rank

    obs = VirtualObserver(tau=tau, exposure=exposure)
    if windows is None:
        gh, gw = int(grid[0]), int(grid[1])
        bh, bw = image.shape[0] // gh, image.shape[1] // gw
        windows = [(c * bw, r * bh, bw, bh) for r in range(gh) for c in range(gw)]
    e = window_errors(reference, image, windows, obs.ppd, exposure, obs.pooling)
    dots = window_dots(image, reference, windows, tau, exposure)
    allowed = np.array([dot_rank(h, w) - 1 for _, _, w, h in windows])
    visible = e > tau
    out = {"tau": tau, "pooling": obs.pooling, "errors": [float(x) for x in e],
           "worst_error": float(e.max()), "mean_error": float(e.mean()),
           "visible_noise_blocks": int(visible.sum()), "dots": dots.tolist(),
           "dot_level": REPORT_LEVEL * tau}
    if stopped is not None:
        stop = np.asarray(stopped, bool)
        out["visible_noise_stopped_blocks"] = int((visible & stop).sum())
        # the dots check: no block the criterion stopped holds more dots than a block may
        out["max_stopped_dots"] = int(dots[stop].max()) if stop.any() else 0
        out["dotted_stopped_blocks"] = int((stop & (dots > allowed)).sum())
    return out


def nonfinite_line(report: Json) -> str | None:
    """The line a render that dropped non-finite samples ends with; None when it dropped none."""
    nf = report.get("nonfinite") or {}
    if not nf.get("dropped"):
        return None
    head = f"non-finite samples: {nf['dropped']} (pixel, pass) value(s) of scene {report['scene']} were NaN/Inf"
    if nf.get("pixels"):
        return (f"{head}; {nf['pixels']} pixel(s) have no finite sample (black in the image, not an "
                f"estimate) and {nf['units']} unit(s) never converged for want of one")
    return f"{head} and were dropped; every pixel still has a finite estimate"


def render_result(session: RenderSession, *, time_limit_reached: bool) -> RenderResult:
    """A finished session as the image, per-pixel spp and stops, and report.json."""
    plan, loop, ledger, budget = session.render_plan, session.loop, session.ledger, session.budget
    br, spec, ref = plan.renderer, plan.spec, plan.reference
    acc, n = loop.acc, br.n_units
    report = render_report(plan, session.settings, loop, ledger, session.wall_s())
    report["settings_source"] = spec.settings_source()
    if spec.defines:
        report["defines"] = dict(spec.defines)
    if spec.time_limit is not None:
        report["time_limit"] = {"seconds": float(spec.time_limit), "reached": time_limit_reached}
    if budget is not None and budget.limited:    # not a resumed one's budget of none
        report["budget"] = budget.describe(loop, time_limit_reached)
    report["render_calls"] = session.counts()
    units, windows, frame = np.arange(n), [br.unit_window(u) for u in range(n)], (br.height, br.width)
    image, spp_px, owner = compose(acc.means(units).cpu().numpy(), windows, acc.spp_all(), frame)
    empty, _, _ = compose(acc.unsampled(units)[..., None].astype(np.float64), windows, acc.spp_all(), frame)
    # (pixel, pass) values dropped as NaN/Inf; pixels with no finite sample (shown as 0; a farm
    # exits 3 on them); units never converged for want of a finite estimate
    report["nonfinite"] = {"dropped": int(acc.nonfinite_all().sum()), "pixels": int((empty[..., 0] > 0).sum()),
                           "units": int((acc.unestimated(units) > 0).sum())}
    if report["nonfinite"]["dropped"]:
        logger.warning("%s", nonfinite_line(report))
    block_done = (~loop.active).reshape(br.n_blocks, br.tiles_per_block).all(axis=1)
    image = image.astype(np.float32)
    ref_img = ref.image if ref.stack is None else ref.stack.reference()
    if ref.stack is not None and ref_img.shape != image.shape:
        logger.warning("reference image %s differs from the render %s: no final-vs-reference check",
                       ref_img.shape, image.shape)
        ref_img = None
    if ref_img is not None:
        report["final_vs_reference"] = final_vs_reference(
            image, ref_img, br.grid, float(spec.tau), float(spec.exposure), block_done,
            windows=[br.window(b) for b in range(br.n_blocks)] if br.overlapping else None)
        if ref.stack is None:
            report["reference"] = {"image": os.fspath(ref.given) if isinstance(ref.given, (str, os.PathLike))
                                   else "array", "width": br.width, "height": br.height}
    return RenderResult(image=image, spp=spp_px, converged=(~loop.active)[owner], report=report,
                        reference=ref_img)
