"""`noisestop bench budget`: a sample budget spent where the noise is, against uniform.

For every held-out stack: uniform sampling to `UNIFORM_SPP` against the budget render
(flip criterion at c(tau)) given the same samples in total (the budget simulated on the
stack's own passes, `renderer.simulation.simulate.simulate_budget`: equal spp, not measured time). Each
side's error per block is the virtual observer's against the 8192-spp reference, at the
level the block ended at (DESIGN's pooling: the largest 16x16 tile mean of FLIP).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from learning.names import DEFAULT_TAU

UNIFORM_SPP = 512


def bench_budget(data: str | None, heldout: str | None = None, spp: int = UNIFORM_SPP,
                 tau: float = DEFAULT_TAU) -> dict[str, Any]:
    from learning.data.observer import observer_for
    from learning.data.relabel import read_observed
    from learning.evaluation.generalisation import scene_groups
    from renderer.simulation.simulate import simulate_budget
    from renderer.criteria import FlipCriterion

    root = heldout or data
    if root is None:
        raise ValueError("bench budget needs --heldout DIR (or --data DIR)")
    stacks = read_observed(root, tau)
    groups = scene_groups(stacks)
    rows = []
    for st in stacks:
        levels = list(st.spp)
        if spp not in levels:
            raise ValueError(f"{st.path}: no level at {spp} spp to compare uniform sampling at")
        e = observer_for(st, tau).stack_errors(st)                    # [K, n]
        sim = simulate_budget(st, FlipCriterion(tau=tau), spp_budget=spp, min_spp=int(levels[0]))
        at = [levels.index(s) for s in sim["spp"]]
        eb = np.array([e[k, b] for b, k in enumerate(at)])
        eu = e[levels.index(spp)]
        rows.append({"scene": st.scene, "converging": st.scene in groups.get("converging", []),
                     "budget_spp": float(np.mean(sim["spp"])), "spp": sim["spp"],
                     "stopped": int(sum(sim["converged"])), "rounds": sim["rounds"],
                     "above_target": len(sim["budget"]["above_target"]),
                     "uniform_worst": float(eu.max()), "budget_worst": float(eb.max()),
                     "uniform_mean": float(eu.mean()), "budget_mean": float(eb.mean()),
                     "uniform_visible": int((eu > tau).sum()), "budget_visible": int((eb > tau).sum())})
    for r in rows:
        r["worst_ok"] = r["budget_worst"] <= r["uniform_worst"]
        r["mean_ok"] = r["budget_mean"] <= r["uniform_mean"]
    return {"tau": tau, "spp": spp, "heldout": str(root), "rows": rows}


def md_budget(r: dict[str, Any]) -> str:
    lines = [f"Uniform sampling to {r['spp']} spp against `--spp-budget {r['spp']}` (flip at c(tau), tau "
             f"{r['tau']:g}), simulated on the held-out stacks (equal samples, not measured time); error = the "
             "observer's FLIP against the 8192-spp reference (largest 16x16 tile mean per block):", "",
             "| scene | converges | budget: mean spp | blocks stopped | above target at the end | worst block: "
             "uniform / budget | budget / uniform | mean: uniform / budget | budget / uniform "
             "| blocks above tau: uniform / budget | goal |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        missed = [k for k, ok in (("worst", x["worst_ok"]), ("mean", x["mean_ok"])) if not ok]
        goal = "met" if not missed else f"missed ({', '.join(missed)})"
        lines.append(f"| {x['scene']} | {'yes' if x['converging'] else 'no'} | {x['budget_spp']:.0f} | {x['stopped']} "
                     f"| {x['above_target']} | {x['uniform_worst']:.4f} / {x['budget_worst']:.4f} "
                     f"| {x['budget_worst'] / x['uniform_worst']:.3f} "
                     f"| {x['uniform_mean']:.5f} / {x['budget_mean']:.5f} | {x['budget_mean'] / x['uniform_mean']:.3f} "
                     f"| {x['uniform_visible']} / {x['budget_visible']} | {goal} |")
    return "\n".join(lines)
