"""`noisestop bench observer` and `bench tau`: what the observer's pooling and the noise
target change, on the held-out scenes.

* observer: per held-out scene, blocks converged inside the stack and the oracle's total
  samples under each observer version (v1 block mean, v2 largest 16x16 tile mean, v3 v2 plus
  the dot term), and one picture of the blocks v2 accepts and v3 does not, each at its v2
  threshold next to the reference, enlarged 3x.
* tau: the `flip` criterion at c(tau) and the bundled model at its offset for tau, against
  the observer's labels at that tau, per scene, at tau 0.01, 0.02 and 0.04 (every knob
  from the training scenes only).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from noisefeat.extras import require

TAUS = (0.01, 0.02, 0.04)
KEYS = ("early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform")


def _oracle_spp(thresholds: list[int | None], spp: list[int]) -> int:
    """Samples per pixel the oracle spends on a stack's blocks (never converged: max spp)."""
    return int(sum(spp[-1] if t is None else t for t in thresholds))


#: the observers compared, oldest first: (version, pooling)
VERSIONS = (("v1", "mean"), ("v2", "tile16-max"), ("v3", "tile16-max+dots"))


def bench_observer(data: str, heldout: str | None = None, out_png: str = "docs/observer-v2-v3.png",
                   tau: float = 0.02, most: int = 12) -> dict[str, Any]:
    """Blocks converged and oracle samples under each observer version, per held-out scene;
    the picture of the blocks version 2 calls converged and version 3 does not."""
    from learning.data.dataset_dir import list_stacks
    from learning.data.relabel import observed
    from learning.data.stack import read_stack

    if heldout is None:
        raise ValueError("bench observer needs --heldout DIR (the scenes no knob was set on)")
    stacks = [read_stack(p) for p in list_stacks(heldout)]
    rows, accepted = [], []
    for st in stacks:
        seen = {v: observed(st, tau, pooling) for v, pooling in VERSIONS}
        row: dict[str, Any] = {"scene": st.scene, "blocks": st.n_blocks}
        for v, _ in VERSIONS:
            row[f"converged_{v}"] = sum(t is not None for t in seen[v].thresholds)
            row[f"oracle_spp_{v}"] = _oracle_spp(seen[v].thresholds, st.spp)
        rows.append(row)
        e3 = _errors(st)
        for b, (t2, t3) in enumerate(zip(seen["v2"].thresholds, seen["v3"].thresholds)):
            if t2 is not None and (t3 is None or t3 > t2):
                k = st.spp.index(t2)
                accepted.append({"scene": st.scene, "block": b, "v2": t2, "v3": t3,
                                 "v3_error_at_v2": float(e3[k, b]),
                                 "dots_at_v2": _dots_count(st, k, b, tau), "stack": st, "level": k})
    accepted.sort(key=lambda r: -r["v3_error_at_v2"])
    plot = _picture(accepted[:most], out_png, tau) if accepted else None
    total = {k: sum(r[k] for r in rows) for k in rows[0] if k != "scene"} if rows else {}
    return {"tau": tau, "per_scene": rows, "total": total, "plot": plot,
            "accepted_by_v2_only": len(accepted),
            "accepted": [{k: v for k, v in r.items() if k not in ("stack", "level")} for r in accepted]}


def _errors(st: Any) -> np.ndarray:
    from learning.data.observer import VirtualObserver
    return VirtualObserver().stack_errors(st)


def _dots_count(st: Any, k: int, b: int, tau: float) -> int:
    """Pixels of block b at level k over the dot level against the reference."""
    from noisefeat.dots import count_outliers
    return count_outliers(st.split(st.level(k))[b], st.split(st.reference())[b], tau)


def _picture(rows: list[dict[str, Any]], out_png: str, tau: float) -> str:
    """Each block at its version-2 threshold next to the reference, both enlarged 3x."""
    require("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from renderer.live.outputs import to_srgb8

    cols = 4
    lines = (len(rows) + cols - 1) // cols
    fig = Figure(figsize=(4.2 * cols, 2.35 * lines + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    for i, r in enumerate(rows):
        st, b = r["stack"], r["block"]
        crop = st.split(st.level(r["level"]))[b]
        ref = st.split(st.reference())[b]
        pair = np.concatenate([to_srgb8(crop), np.full((crop.shape[0], 4, 3), 255, np.uint8), to_srgb8(ref)], axis=1)
        ax = fig.add_subplot(lines, cols, i + 1)
        ax.imshow(np.repeat(np.repeat(pair, 3, axis=0), 3, axis=1), interpolation="nearest")
        v3 = "never" if r["v3"] is None else f"{r['v3']}"
        ax.set_title(f"{r['scene']} block {b}: {r['v2']} spp | reference\n"
                     f"{r['dots_at_v2']} dots, v3 error {r['v3_error_at_v2']:.3f} (tau {tau:g}); v3 threshold {v3}",
                     fontsize=8)
        ax.set_axis_off()
    fig.suptitle("Blocks observer version 2 (16x16 tile FLIP) calls converged and version 3 (+ dots) does not: "
                 "at the v2 threshold (left) beside the reference (right), 3x", fontsize=10)
    fig.tight_layout()
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=100)
    return str(out_png)


def md_observer(r: dict[str, Any]) -> str:
    lines = [f"Held-out scenes, tau {r['tau']:g}; the oracle's samples count a block that never converges "
             "inside its stack at the stack's last level (`noisestop bench observer --heldout data/heldout`). "
             "v1: block mean; v2: largest 16x16 tile mean; v3: v2 or the dot term, whichever is larger.", "",
             "| scene | blocks | converged v1 | converged v2 | converged v3 | oracle spp v1 | oracle spp v2 | "
             "oracle spp v3 | v3 / v2 |", "|---|---|---|---|---|---|---|---|---|"]
    for row in [*r["per_scene"], {"scene": "**all**", **r["total"]}]:
        lines.append(f"| {row['scene']} | {row['blocks']} | {row['converged_v1']} | {row['converged_v2']} | "
                     f"{row['converged_v3']} | {row['oracle_spp_v1']} | {row['oracle_spp_v2']} | "
                     f"{row['oracle_spp_v3']} | {row['oracle_spp_v3'] / max(1, row['oracle_spp_v2']):.2f}x |")
    lines += ["", f"{r['accepted_by_v2_only']} blocks are converged for version 2 at a level where version 3 "
              f"still sees dots; the {min(12, r['accepted_by_v2_only'])} with the largest version-3 error at "
              f"that level: [{r['plot']}]({r['plot']})."]
    return "\n".join(lines)


#: the runs of the tau bench: (name, criterion, tile); flip at the loop's default tile and
#: per block, the bundled model per block (its unit)
TAU_RUNS = (("flip", "flip", 16), ("flip per block", "flip", None), ("model", "model", None))


def bench_tau(data: str, heldout: str | None = None, taus: tuple[float, ...] = TAUS,
              model: str | None = None) -> dict[str, Any]:
    """flip at c(tau) (per 16x16 tile, the loop's default, and per block) and the bundled
    model at its offset for tau, against labels at tau; at tile grain early stops count
    tiles against the tile truth and blocks holding an early tile; every run also says how
    many blocks the version-3 observer finds above tau in the image it ends with."""
    from learning.evaluation.generalisation import scene_groups
    from learning.inputs.halves import flip_c, load_flip_calibration, unit_calibration
    from learning.models.bundle import load_model
    from renderer.simulation.simulate import evaluate_criterion_cli

    if heldout is None:
        raise ValueError("bench tau needs --heldout DIR (the scenes no knob was set on)")
    cal = load_flip_calibration()
    bundled = load_model(model)
    out: dict[str, Any] = {"taus": list(taus), "runs": [name for name, _, _ in TAU_RUNS]}
    from learning.data.relabel import read_observed
    for tau in taus:
        groups = scene_groups(read_observed(heldout, tau))
        for name, kind, tile in TAU_RUNS:
            r = evaluate_criterion_cli(heldout, kind, progress=False, tau=tau, tile=tile,
                                       **({"model": model} if kind == "model" else {}))
            knob = flip_c(unit_calibration(cal, tile), tau) if kind == "flip" else bundled.offset_at(tau)
            conv = r.get("groups", {}).get("converging", {})
            end = r["end"]["per_scene"]
            blocks = r.get("blocks", {}).get("per_scene", {})
            out.setdefault(name, {})[str(tau)] = {
                "knob": knob, "tile": tile, "groups": groups, **{k: r[k] for k in KEYS},
                "converging": {k: conv.get(k) for k in KEYS}, "end_above_tau": r["end"]["above_tau"],
                "per_scene": {s: {**{k: m[k] for k in KEYS}, "early_units": int(m["counts"].get("early", 0)),
                                  "early_block_rate": m.get("early_block_rate"),
                                  "vs_block_oracle": blocks.get(s, {}).get("spp_ratio_vs_block_oracle"),
                                  "end_above_tau": end[s]["above_tau"], "blocks": end[s]["blocks"]}
                              for s, m in r["per_scene"].items()}}
    return out


def md_tau(r: dict[str, Any]) -> str:
    lines = ["Every knob from the training scenes only: flip's c(tau) from `learning/flip.json` (its tile curve "
             "at tile grain), the bundled model's offset for tau from its training record; labels by the "
             "observer at that tau (`noisestop evaluate --data data/heldout --criterion flip|model --tau T "
             "[--tile 16]`). At tile grain an early stop is a tile's, against the tile truth; \"above tau at the "
             "end\" is the version-3 block observer on the image the simulated render ends with.", ""]
    for name in r.get("runs", ("flip", "model")):
        for tau in r["taus"]:
            row = r[name][str(tau)]
            conv = row["converging"]
            unit = "tiles" if row.get("tile") else "blocks"
            lines.append(f"**{name}, tau {tau:g}** ({'c' if name.startswith('flip') else 'offset'} "
                         f"{row['knob']:.4g}): early {unit} {row['early_stop_rate']:.1%} at "
                         f"{row['spp_ratio_vs_oracle']:.2f}x the oracle (converging scenes: "
                         f"{_pct(conv.get('early_stop_rate'))} at {_x(conv.get('spp_ratio_vs_oracle'))}); "
                         f"{row.get('end_above_tau', 'n/a')} blocks above tau at the end")
            lines.append("")
            lines.append(f"| scene | early {unit} | early stops | samples / oracle | samples / block oracle | "
                         "blocks with an early tile | above tau at the end | saved vs uniform |")
            lines.append("|---|---|---|---|---|---|---|---|")
            for s, m in sorted(row["per_scene"].items()):
                mark = "" if s in row["groups"].get("converging", []) else " (does not converge)"
                lines.append(f"| {s}{mark} | {m.get('early_units', m.get('early_blocks'))} | "
                             f"{m['early_stop_rate']:.1%} | {m['spp_ratio_vs_oracle']:.2f}x | "
                             f"{_x(m.get('vs_block_oracle'))} | {_pct(m.get('early_block_rate'))} | "
                             f"{m.get('end_above_tau', 'n/a')} of {m.get('blocks', 'n/a')} | "
                             f"{m['saved_vs_uniform']:.1%} |")
            lines.append("")
    return "\n".join(lines)


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1%}"


def _x(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.2f}x"
