"""Decisions skipped towards a unit's predicted stop: `noisestop bench skip`.

The speed knobs `decide_skip` and `decide_growth` (`renderer.live.passloop.next_decision`)
judge a unit that is r times above its target again only at (skip r)^2 times its spp, and
never before (1 + growth) times it. What they save is decisions (FLIP evaluations, the
loop's own cost); what they may cost is samples (a stop found a few passes late) and
accuracy (a unit judged less often could in principle stop on a different level). Both
are measured here on held-out stacks, per scene, at tile and block grain, with the final
frame judged by the version-3 observer (`renderer.simulation.simulate.end_of_render`).
"""
from __future__ import annotations

from typing import Any

#: the knobs' values measured, (decide_skip, decide_growth); (0, 0): every pass judged, the
#: reference; the growth rows at the skip's default
KNOBS = ((0.0, 0.0), (0.5, 0.0), (0.7, 0.0), (0.85, 0.0), (0.5, 1 / 32), (0.5, 1 / 16), (0.5, 1 / 8))
TAUS = (0.02, 0.04)
GRAINS = (("tile", 16), ("block", None))


def knob_key(tau: float, grain: str, skip: float, growth: float) -> str:
    """The run's key in the results (JSON keys are strings)."""
    return f"{tau:g} {grain} {skip:g} {growth:g}"


def bench_skip(data: str | None, heldout: str | None = None, taus: tuple[float, ...] = TAUS,
               knobs: tuple[tuple[float, float], ...] = KNOBS) -> dict[str, Any]:
    """flip with each pair of knobs on the held-out stacks, per scene, at each grain and tau."""
    from renderer.simulation.simulate import evaluate_criterion_cli

    if heldout is None:
        raise ValueError("bench skip needs --heldout DIR (the scenes no knob was set on)")
    out: dict[str, Any] = {"heldout": heldout, "taus": list(taus), "knobs": [list(k) for k in knobs], "runs": {}}
    for tau in taus:
        for grain, tile in GRAINS:
            for skip, growth in knobs:
                r = evaluate_criterion_cli(heldout, "flip", progress=False, tau=tau, tile=tile, decide_skip=skip,
                                           decide_growth=growth)
                per = {}
                for scene, m in r["per_scene"].items():
                    c, end = m["counts"], r["end"]["per_scene"][scene]
                    per[scene] = {"spp": c["spent"] / c["blocks"], "above_tau": end["above_tau"],
                                  "early": end["early"], "worst": end["worst"]}
                out["runs"][knob_key(tau, grain, skip, growth)] = {
                    "per_scene": per, "featured": int(r["counters"].get("blocks_featured", 0)),
                    "asked": int(r["counters"].get("blocks_asked", 0))}
    return out


def md_skip(r: dict[str, Any]) -> str:
    """One table per tau and grain: a row per pair of knobs, totals over the scenes, then the
    scenes whose figures moved."""
    lines = [f"Held-out stacks `{r['heldout']}`, flip (decide_growth's default chosen on the training stacks; "
             "decide_skip's, 0.5, after its held-out rows here had been seen, no training set being at hand "
             "then). Decisions: "
             "units asked (FLIP evaluations in brackets); samples: the sum over scenes of mean spp; blocks above "
             "tau at the end of the render (early ones in brackets) and the worst block.", ""]
    for tau in r["taus"]:
        for grain, _ in GRAINS:
            base = r["runs"][knob_key(tau, grain, 0.0, 0.0)]
            lines += [f"**tau {tau:g}, {grain} grain**", "",
                      "| decide_skip | decide_growth | decisions | / every pass | samples | / every pass | "
                      "above tau (early) | worst |",
                      "|---|---|---|---|---|---|---|---|"]
            b_spp = sum(p["spp"] for p in base["per_scene"].values())
            for skip, growth in r["knobs"]:
                run = r["runs"][knob_key(tau, grain, skip, growth)]
                per = run["per_scene"].values()
                spp = sum(p["spp"] for p in per)
                lines.append(f"| {skip:g} | {growth:g} | {run['asked']} ({run['featured']}) | "
                             f"{run['asked'] / base['asked']:.2f}x | {spp:.0f} | {spp / b_spp:.3f}x | "
                             f"{sum(p['above_tau'] for p in per)} ({sum(p['early'] for p in per)}) | "
                             f"{max(p['worst'] for p in per):.4f} |")
            moved = []
            for skip, growth in r["knobs"][1:]:
                run = r["runs"][knob_key(tau, grain, skip, growth)]["per_scene"]
                for scene, p in sorted(run.items()):
                    q = base["per_scene"][scene]
                    if (p["above_tau"], p["early"]) != (q["above_tau"], q["early"]):
                        moved.append(f"skip {skip:g} growth {growth:g}, {scene}: {q['above_tau']} -> "
                                     f"{p['above_tau']} above tau (worst {q['worst']:.4f} -> {p['worst']:.4f})")
            lines += ["", "Scenes whose count moved: " + ("; ".join(moved) if moved else "none") + ".", ""]
    return "\n".join(lines)
