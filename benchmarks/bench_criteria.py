"""`bench criteria`: every stopping criterion simulated on the held-out stacks (docs/benchmarks/accuracy.md,
"Criteria at block grain"), with its decision cost, each knob calibrated on the training scenes.
"""
from __future__ import annotations

from typing import Any

from .decisions import VARIANCE_THRESHOLDS, group_line, model_and_check, pair, summary


def bench_criteria(data: str, heldout: str | None = None, model: str | None = None,
                   max_early_stop: float = 0.05,
                   thresholds: tuple[float, ...] = VARIANCE_THRESHOLDS) -> dict[str, Any]:
    """Every criterion simulated on the held-out stacks (the render loop's own code), with
    its decision cost; variance's threshold tuned on the training scenes to the same
    early-stop target the model's offset and flip's c were calibrated to."""
    from learning.evaluation.calibrate import choose_out_of_fold
    from learning.evaluation.generalisation import scene_groups, split_stacks
    from learning.inputs.halves import load_flip_calibration
    from renderer.criteria import (FlipCriterion, ModelCriterion, OracleCriterion, UniformCriterion,
                                   VarianceCriterion)
    from renderer.simulation.simulate import evaluate_criterion

    train, test = split_stacks(data, heldout)
    m = model_and_check(model, [s.scene for s in test])

    def run(stacks, factory):
        return summary(evaluate_criterion(stacks, factory))
    # variance's threshold is chosen as the model's offset and flip's c were: out of fold
    on_train = {t: evaluate_criterion(train, lambda st, t=t: VarianceCriterion(threshold=t)) for t in thresholds}
    tuned = choose_out_of_fold([{"threshold": t, **r} for t, r in on_train.items()], max_early_stop,
                               larger_is_safer=False)
    sweep = [{"threshold": t, "train": summary(on_train[t]),
              "test": run(test, lambda st, t=t: VarianceCriterion(threshold=t))} for t in thresholds]
    tuned_test = next(r["test"] for r in sweep if r["threshold"] == tuned["threshold"])
    cal = load_flip_calibration()
    c = float(cal["c"])
    rows = {
        "model": {"label": f"model ({m.name}, offset {m.offset:.2f})",
                  **run(test, lambda st: ModelCriterion(m))},
        "flip": {"label": f"flip (c {c:g})", **run(test, lambda st: FlipCriterion(c))},
        "variance": {"label": f"variance (threshold {tuned['threshold']:g})", **tuned_test},
        "oracle": {"label": "oracle", **run(test, lambda st: OracleCriterion(st.thresholds))},
        "uniform": {"label": "uniform", **run(test, lambda st: UniformCriterion())},
    }
    calib = m.manifest.get("training", {}).get("calibration", {}).get("chosen", {})
    return {"train_scenes": sorted(s.scene for s in train), "test_scenes": sorted(s.scene for s in test),
            "groups": scene_groups(test), "rows": rows, "variance_sweep": sweep,
            "converged_blocks": {s.scene: sum(t is not None for t in s.thresholds) for s in test},
            "calibration": {
                "model": {k: calib.get(k) for k in ("offset", "early_stop_rate", "spp_ratio_vs_oracle")},
                "flip": {"c": c, **{k: (cal.get("chosen") or {}).get(k)
                                    for k in ("early_stop_rate", "spp_ratio_vs_oracle")}},
                "variance": {"threshold": tuned["threshold"], "early_stop_rate": tuned["early_stop_rate"],
                             "spp_ratio_vs_oracle": tuned["spp_ratio_vs_oracle"]}}}


def md_criteria(r: dict[str, Any]) -> str:
    rows = r["rows"]
    lines = [f"Trained and calibrated on {', '.join(r['train_scenes'])}; simulated on the stored stacks "
             f"of the held-out {', '.join(r['test_scenes'])}.", "", group_line(r["groups"]), "",
             "| criterion | converging scenes: early stops / samples vs oracle | the others: early stops / "
             "samples | all: precision | all: early stops | all: samples / oracle | saved vs uniform "
             "| decision cost (ms per block asked) |", "|---|---|---|---|---|---|---|---|"]
    for x in rows.values():
        g = x.get("groups") or {}
        lines.append(f"| {x['label']} | {pair(g.get('converging'))} | {pair(g.get('not_converging'))} "
                     f"| {x['precision']:.3f} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} "
                     f"| {x['saved_vs_uniform']:.3f} | {x.get('decision_ms_per_block', 0):.2f} |")
    names = [n for n in ("model", "flip", "variance") if n in rows]
    lines += ["", "Per held-out scene (early-stop rate / samples vs oracle; blocks converged in the stack "
              "out of 16):", "",
              "| scene | converged blocks | " + " | ".join(rows[n]["label"] for n in names) + " |",
              "|---|---|" + "---|" * len(names)]
    for s in r["test_scenes"]:
        lines.append(f"| {s} | {r['converged_blocks'][s]} | "
                     + " | ".join(pair(rows[n]["per_scene"].get(s)) for n in names) + " |")
    cal = r["calibration"]
    lines += ["", "The same knobs on the training scenes they were calibrated on (out-of-fold for the "
              "model): " + "; ".join(
                  f"{n} {pair(cal[n]) if cal[n].get('early_stop_rate') is not None else '-'}"
                  for n in ("model", "flip", "variance")) + " (early stops / samples vs oracle).", "",
              "Variance threshold sweep (training / held-out: early stops, samples vs oracle):", "",
              "| threshold | training | held-out |", "|---|---|---|"]
    for row in r["variance_sweep"]:
        lines.append(f"| {row['threshold']:g} | {pair(row['train'])} | {pair(row['test'])} |")
    return "\n".join(lines)
