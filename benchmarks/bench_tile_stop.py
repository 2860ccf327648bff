"""The stop at tile grain against the observer's own (issue 49): `noisestop bench tilestop`.

Per held-out scene and noise target, what each run spends and what the frame it ends with
shows: flip per block (the block grain's default), flip per 16x16 tile (the loop's
default: the tile's history against the tile curve of c), the oracle per block and per tile
(the final-frame tile truth, `learning.data.tile_truth`), and the bundled model per block
and gated per tile. Samples are mean spp a pixel; "/ block grain" is against flip per block
on the same scene. "early" counts the blocks the final frame leaves above tau although their
own truth converges in the stack (noise the observer says could be gone).
"""
from __future__ import annotations

from typing import Any

#: (name, criterion, tile): the runs, at every tau; the model's only at TAU_MODEL (it is slow)
RUNS = (("flip per block", "flip", None), ("flip per tile", "flip", 16),
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
    out: dict[str, Any] = {"taus": list(taus), "heldout": heldout}
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
    return "\n".join(lines)
