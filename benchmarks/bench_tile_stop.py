"""The stop at tile grain against the observer's own: `noisestop bench tilestop`.

Per held-out scene and noise target, what each run spends and what the frame it ends with
shows: flip per block (the block grain's default), flip per 16x16 tile (the loop's
default: the tile's history against the tile curve of c), the oracle per block and per tile
(the final-frame tile truth, `learning.data.tile_truth`), the learned stop (`estimate`)
and the bundled model per block and gated per tile; and the spread s
(`learning.evaluation.spread`) of the halves' history and of the learned estimate, per
held-out scene. Samples are mean spp a pixel; "/ block grain" is against flip per block
on the same scene. "early" counts the blocks the final frame leaves above tau although their
own truth converges in the stack (noise the observer says could be gone).
"""
from __future__ import annotations

from typing import Any

#: (name, criterion, tile): the runs, at every tau; the model's only at TAU_MODEL (it is slow)
RUNS = (("flip per block", "flip", None), ("flip per tile", "flip", 16), ("estimate per tile", "estimate", 16),
        ("oracle per block", "oracle", None), ("oracle per tile", "oracle", 16))
MODEL_RUNS = (("model per block", "model", None), ("model per tile", "model", 16))
TAUS = (0.01, 0.02, 0.04)
TAU_MODEL = 0.02


def bench_tile_stop(data: str | None, heldout: str | None = None, taus: tuple[float, ...] = TAUS,
                    model: str | None = None) -> dict[str, Any]:
    """Every run of `RUNS` (and `MODEL_RUNS` at TAU_MODEL) on the held-out stacks, per scene."""
    from renderer.simulation.simulate import evaluate_criterion_cli

    if heldout is None:
        raise ValueError("bench tilestop needs --heldout DIR (the scenes no knob was set on)")
    out: dict[str, Any] = {"taus": list(taus), "heldout": heldout, "spread": spread_per_scene(heldout)}
    for tau in taus:
        runs = RUNS + (MODEL_RUNS if abs(tau - TAU_MODEL) < 1e-12 else ())
        for name, kind, tile in runs:
            r = evaluate_criterion_cli(heldout, kind, progress=False, tau=tau, tile=tile,
                                       **({"model": model} if kind == "model" else {}))
            per = {}
            for scene, m in r["per_scene"].items():
                c, end = m["counts"], r["end"]["per_scene"][scene]
                units = c["blocks"]
                per[scene] = {"spp": c["spent"] / units, "oracle_spp": c["oracle"] / units,
                              "above_tau": end["above_tau"], "early": end["early"], "worst": end["worst"],
                              "blocks": end["blocks"], "converging": end["converging"]}
            out.setdefault(str(tau), {})[name] = {"per_scene": per, "criterion": r["criterion"]}
    return out


def spread_per_scene(heldout: str, tile: int = 16) -> dict[str, dict[str, float]]:
    """scene (and "all") -> the spread s of the halves' history and of the shipped estimate,
    and how many tiles converge there."""
    import numpy as np

    from learning.data.dataset_dir import read_stacks
    from learning.data.relabel import with_tile_truth
    from learning.evaluation.spread import needed_margins, spread
    from learning.inputs.tile_table import stack_tile_table
    from learning.models.tile_error_bundle import load_tile_error_bundle
    from learning.training.train_estimate import estimates_of

    bundle = load_tile_error_bundle()
    out, pooled = {}, {"history": [], "estimate": []}
    for st in read_stacks(heldout):
        st = with_tile_truth(st, tile)
        table = stack_tile_table(st, tile)
        h, e = needed_margins(st, table.e_hist), needed_margins(st, estimates_of(bundle.estimator, table))
        pooled["history"].append(h)
        pooled["estimate"].append(e)
        out[st.scene] = {"history": spread(h), "estimate": spread(e), "tiles": int(h.size)}
    h, e = np.concatenate(pooled["history"]), np.concatenate(pooled["estimate"])
    out["all"] = {"history": spread(h), "estimate": spread(e), "tiles": int(h.size)}
    return out


def md_tile_stop(r: dict[str, Any]) -> str:
    lines = [f"Held-out stacks `{r['heldout']}`; every knob from the training scenes only. Each cell: blocks above "
             "tau at the end (early ones in brackets), the worst block, mean spp and its ratio to flip per block.", ""]
    for tau in r["taus"]:
        runs = r[str(tau)]
        names = list(runs)
        base = runs["flip per block"]["per_scene"]
        lines += [f"**tau {tau:g}**", "", "| scene | " + " | ".join(names) + " |",
                  "|---|" + "---|" * len(names)]
        totals = {n: [0, 0, 0.0] for n in names}
        for scene in sorted(base):
            cells = []
            for n in names:
                m = runs[n]["per_scene"][scene]
                ratio = m["spp"] / base[scene]["spp"] if base[scene]["spp"] else float("nan")
                cells.append(f"{m['above_tau']} ({m['early']}), {m['worst']:.4f}, {m['spp']:.0f} ({ratio:.2f}x)")
                t = totals[n]
                t[0] += m["above_tau"]; t[1] += m["early"]; t[2] += m["spp"]
            conv = base[scene]["converging"] == base[scene]["blocks"]
            lines.append(f"| {scene}{'' if conv else ' (not all blocks converge)'} | " + " | ".join(cells) + " |")
        b = totals["flip per block"][2]
        lines.append("| all | " + " | ".join(f"{t[0]} ({t[1]}), {t[2]:.0f} ({t[2] / b:.2f}x)" for t in totals.values())
                     + " |")
        lines.append("")
    if "spread" in r:
        lines += ["**The spread s of log(smallest estimate before the truth / tau)** over each scene's tiles whose "
                  "truth converges (tau 0.02; `learning.evaluation.spread`):", "",
                  "| scene | tiles | halves' history | learned estimate |", "|---|---|---|---|"]
        lines += [f"| {k} | {v['tiles']} | {v['history']:.3f} | {v['estimate']:.3f} |" for k, v in r["spread"].items()]
        lines.append("")
    return "\n".join(lines)
