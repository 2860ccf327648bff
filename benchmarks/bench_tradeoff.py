"""`bench tradeoff`: samples against early stops on the held-out scenes, one curve per
criterion (docs/benchmarks/accuracy.md, docs/pareto.png), the defaults per
scene, where their early stops fell short and where their samples went.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .decisions import KEYS, VARIANCE_THRESHOLDS, group_line, model_and_check, pair

#: the comparison's model kinds drawn on the Pareto chart (every kind is in the table)
PARETO_KINDS = ("dsvm_as", "svm_as", "dsvm", "svm")


def early_stops(per: dict[str, tuple]) -> list[dict[str, Any]]:
    """Every block stopped before its true threshold: scene, block, stop spp, threshold (None:
    never converged inside the stack), how far short of it (1 - stop / threshold)."""
    from learning.evaluation.metrics import never_spp, stop_thresholds

    out = []
    for scene, (v, _, th, spp) in sorted(per.items()):
        for b, (stop, t) in enumerate(zip(stop_thresholds(v, spp), th)):
            true = never_spp(spp) if t is None else int(t)
            if stop < true:
                out.append({"scene": scene, "block": b, "stop": int(stop), "threshold": t,
                            "short": 1.0 - float(stop) / true})
    return out


def flip_at_threshold(stacks: list) -> dict[str, Any]:
    """Flip's score where the observer says a block converges: e (FLIP between the half
    buffers) at each block's true threshold level. If flip is free of scene content, its
    distribution is the same on every set of scenes."""
    from learning.inputs.halves import stack_flip_errors

    e = []
    for st in stacks:
        errors = stack_flip_errors(st)
        for b, t in enumerate(st.thresholds or []):
            if t is not None and np.isfinite(errors[st.spp.index(t), b]):
                e.append(float(errors[st.spp.index(t), b]))
    pct = np.percentile(e, [10, 50, 90]).tolist() if e else [float("nan")] * 3
    return {"blocks": len(e), "p10": pct[0], "median": pct[1], "p90": pct[2]}


def _stop_grids(per: dict[str, tuple], grids: dict[str, tuple[int, int]]) -> dict[str, np.ndarray]:
    """Per scene, the spp each block stopped at (max spp if never) as its grid."""
    from learning.evaluation.metrics import stop_thresholds

    return {s: np.minimum(stop_thresholds(v, spp), spp[-1]).reshape(grids[s]) for s, (v, _, _, spp) in per.items()}


def bench_tradeoff(data: str, heldout: str | None = None, out_dir: str | Path = "out/bench",
                   out_png: str = "docs/pareto.png", model: str | None = None,
                   thresholds: tuple[float, ...] = VARIANCE_THRESHOLDS) -> dict[str, Any]:
    """Samples (vs oracle) against early stops on the held-out scenes, one curve per criterion.

    The bundled model and every SVM kind of the saved model comparison (`bench models`, same
    datasets) along their decision offset; flip along c; variance along its threshold (the
    simulation); the oracle is (1, 0). Plus per held-out scene, the bundled model and flip
    at their calibrated defaults, and where their samples went (spp maps)."""
    from learning.evaluation.calibrate import DEFAULT_OFFSETS, sweep
    from learning.training.compare_inputs import decision_ms, flip_ms
    from learning.evaluation.evaluate import stops_by_scene
    from learning.evaluation.generalisation import scene_groups, split_stacks, split_tables
    from learning.evaluation.calibrate import FLIP_CANDIDATES, flip_sweep
    from learning.inputs.halves import flip_offset, guarded_flip_scores, load_flip_calibration
    from learning.evaluation.metrics import true_thresholds
    from learning.stoprule import StopRule
    from learning.inputs.halves import stack_flat
    from renderer.criteria import VarianceCriterion
    from renderer.simulation.simulate import evaluate_criterion

    from . import charts
    from .bench_models import saved_comparisons

    train_stacks, test_stacks = split_stacks(data, heldout)
    bundled = model_and_check(model, [s.scene for s in test_stacks])
    test = split_tables(data, heldout, **bundled.table_options())[1]
    scores = bundled.decision_function(test.X)
    model_curve = sweep(scores, test, DEFAULT_OFFSETS)
    model_default = sweep(scores, test, [bundled.offset])[0]
    c = float(load_flip_calibration()["c"])
    flip_curve = flip_sweep(test_stacks, FLIP_CANDIDATES)
    flip_default = flip_sweep(test_stacks, [c])[0]
    var = []
    for t in thresholds:
        r = evaluate_criterion(test_stacks, lambda st, t=t: VarianceCriterion(threshold=t))
        var.append({"threshold": t, **{k: r[k] for k in (*KEYS, "groups")}})
    comparisons = [x for x in saved_comparisons(data, Path(out_dir), heldout)]
    kinds: dict[str, list[dict]] = {}
    for comp in comparisons:
        for row in comp["rows"]:
            if "offset_curve" in row:        # SVM kinds; raw-pixel ones use no quick image
                k = row["model"]
                kinds.setdefault(k if k.startswith("svm") else f"{k} quick {comp['quick']}", row["offset_curve"])
    twin = f"{bundled.manifest['kind']} quick {bundled.quick}"        # the bundle's own kind, retrained
    drawn = {n: rows for n, rows in kinds.items() if n.split()[0] in PARETO_KINDS and n != twin}
    offsets = f"offset {DEFAULT_OFFSETS[0]:g}..{DEFAULT_OFFSETS[-1]:g}"
    # each criterion's decision cost next to its curve (one thread, per 64x64 block)
    model_ms, flip_cost = decision_ms(bundled), flip_ms()
    curves = [{"label": f"{bundled.name} quick {bundled.quick} (bundled), {offsets}, {model_ms:.1f} ms/block",
               "rows": model_curve, "lw": 2.2, "color": "C0"},
              {"label": f"flip (no learning), c {FLIP_CANDIDATES[0]:g}..{FLIP_CANDIDATES[-1]:g}, "
                        f"{flip_cost:.1f} ms/block",
               "rows": flip_curve, "lw": 2.2, "color": "black"},
              {"label": f"variance (Cycles), threshold {thresholds[0]:g}..{thresholds[-1]:g}", "rows": var,
               "marker": "x", "color": "grey"}]
    curves += [{"label": f"{n}, {offsets}", "rows": rows, "dashed": "albedo" in n,
                "marker": "s" if n.startswith("svm") else ".", "color": f"C{i + 1}"}
               for i, (n, rows) in enumerate(drawn.items())]
    groups = scene_groups(test_stacks)
    conv = [s for s in test_stacks if s.scene in groups["converging"]]
    points = [{"label": f"default: bundled model, offset {bundled.offset:.2f}", "row": model_default},
              {"label": f"default: flip, c {c:g}", "row": flip_default}]
    plot = charts.pareto(curves, points, [s.scene for s in test_stacks], out_png)
    plot_conv = None
    if conv and len(conv) < len(test_stacks):   # the same chart on the converging scenes alone
        def on(rows):
            return [{**r, **r["groups"]["converging"]} for r in rows]
        plot_conv = charts.pareto(
            [{**cv, "rows": on(cv["rows"])} for cv in curves[:3]],
            [{**p, "row": {**p["row"], **p["row"]["groups"]["converging"]}} for p in points],
            [s.scene for s in conv], Path(out_png).with_name("pareto-converging.png"),
            "held-out scenes that converge")
    # where the samples went, per held-out scene, at the defaults
    grids = {s.scene: tuple(s.grid) for s in test_stacks}
    per_model = stops_by_scene(test, scores, bundled.rule())
    flip_rule = StopRule(flip_offset(c))
    per_flip = {s.scene: (flip_rule.stops(guarded_flip_scores(s), s.spp, stack_flat(s)), s.labels(),
                          s.thresholds, s.spp) for s in test_stacks}
    maps: dict[str, dict[str, np.ndarray]] = {}
    g_model, g_flip = _stop_grids(per_model, grids), _stop_grids(per_flip, grids)
    for s in test_stacks:
        oracle = np.minimum(true_thresholds(s.thresholds, s.spp), s.spp[-1]).reshape(grids[s.scene])
        maps[s.scene] = {"flip": g_flip[s.scene], "model": g_model[s.scene], "oracle": oracle}
    top = max(int(s.spp[-1]) for s in test_stacks)
    png = charts.spp_maps(maps, top, f"spp per block at the defaults: flip (c {c:g}), bundled model "
                          f"(offset {bundled.offset:.2f}), oracle", Path(out_png).with_name("spp-maps.png"))
    return {"test_scenes": [s.scene for s in test_stacks], "groups": groups,
            "early_stops": {"model": early_stops(per_model), "flip": early_stops(per_flip)},
            "flip_at_threshold": {"training": flip_at_threshold(train_stacks),
                                  "held-out": flip_at_threshold(test_stacks)},
            "curves": {"model": model_curve, "flip": flip_curve, "variance": var, **kinds},
            "drawn": [cv["label"] for cv in curves], "bundled": bundled.name,
            "defaults": {"model": {"offset": bundled.offset, **model_default}, "flip": {"c": c, **flip_default}},
            "plot": plot, "plot_converging": plot_conv, "spp_maps": png,
            "converged_blocks": {s.scene: sum(t is not None for t in s.thresholds) for s in test_stacks}}


def _best(rows: list[dict], max_early: float, key: str, group: str | None = None) -> str:
    """The fewest samples whose early-stop rate is within max_early, with its setting."""
    rows = [{**r, **r["groups"][group], key: r[key]} for r in rows if group in (r.get("groups") or {})] \
        if group else rows
    ok = [r for r in rows if r["early_stop_rate"] <= max_early + 1e-12]
    if not ok:
        return "never"
    r = min(ok, key=lambda r: (r["spp_ratio_vs_oracle"], r[key]))
    return f"{r['spp_ratio_vs_oracle']:.3f} ({key} {r[key]:g})"


def md_tradeoff(r: dict[str, Any]) -> str:
    d = r["defaults"]
    conv = f" Converging scenes alone: ![converging]({r['plot_converging']})" if r.get("plot_converging") else ""
    lines = [f"![samples vs early stops]({r['plot']}){conv}", "", group_line(r["groups"]), "",
             f"Defaults: bundled model at offset {d['model']['offset']:.2f}: all held-out scenes "
             f"{pair(d['model'])}, converging ones {pair(d['model']['groups'].get('converging'))}; "
             f"flip at c {d['flip']['c']:g}: all {pair(d['flip'])}, converging "
             f"{pair(d['flip']['groups'].get('converging'))} (early stops / samples vs oracle).", "",
             "| criterion | fewest samples, early stops <= 5 % (all) | the same, converging scenes "
             "| fewest samples, no early stop (all) |", "|---|---|---|---|"]
    for name, rows in r["curves"].items():
        key = "threshold" if name in ("flip", "variance") else "offset"
        lines.append(f"| {name} | {_best(rows, 0.05, key)} | {_best(rows, 0.05, key, 'converging')} "
                     f"| {_best(rows, 0.0, key)} |")
    lines += ["", "Per held-out scene at the defaults (early-stop rate / samples vs oracle):", "",
              "| scene | converged blocks | bundled model | flip |", "|---|---|---|---|"]
    for s in r["test_scenes"]:
        lines.append(f"| {s} | {r['converged_blocks'][s]} | {pair(d['model']['per_scene'].get(s))} "
                     f"| {pair(d['flip']['per_scene'].get(s))} |")
    lines += ["", "How far short of the true threshold the early stops at the defaults fell (1 - stop spp / "
              "threshold; a level is 1/k of a threshold at level k):", ""]
    for name, label in (("model", "bundled model"), ("flip", "flip")):
        es = r["early_stops"][name]
        lines.append(f"* {label}: {len(es)} early stop(s)" + (": " + ", ".join(
            f"{x['scene']} block {x['block']} at {x['stop']} spp (threshold "
            f"{x['threshold'] if x['threshold'] is not None else 'never'}, {100 * x['short']:.0f} % short)"
            for x in sorted(es, key=lambda x: -x["short"])) if es else ""))
    at = r["flip_at_threshold"]
    lines += ["", "Flip's score where the observer says a block converges (e at the block's true threshold; "
              "blocks whose threshold lies past the first level):", "",
              "| scenes | blocks | 10th percentile | median | 90th percentile |", "|---|---|---|---|---|"]
    lines += [f"| {name} | {x['blocks']} | {x['p10']:.4f} | {x['median']:.4f} | {x['p90']:.4f} |" for name, x in at.items()]
    lines += ["", "Flip along c and the bundled model along its offset (all held-out scenes / converging ones):",
              "", "| criterion | setting | all: early stops / samples | converging: early stops / samples |",
              "|---|---|---|---|"]
    c = d["flip"]["c"]
    for row in r["curves"]["flip"]:    # every 0.005, and every step within 0.003 of the default
        t = row["threshold"]
        if abs(t * 200 - round(t * 200)) < 1e-6 or abs(t - c) <= 0.003 + 1e-9:
            lines.append(f"| flip | c {row['threshold']:g} | {pair(row)} | {pair(row['groups'].get('converging'))} |")
    for row in r["curves"]["model"]:
        if abs(round(row["offset"] * 2) - row["offset"] * 2) < 1e-9:  # every 0.5
            lines.append(f"| {r['bundled']} | offset {row['offset']:.1f} | {pair(row)} "
                         f"| {pair(row['groups'].get('converging'))} |")
    for row in r["curves"]["variance"]:
        lines.append(f"| variance | threshold {row['threshold']:g} | {pair(row)} "
                     f"| {pair((row.get('groups') or {}).get('converging'))} |")
    lines += ["", f"Where the samples went, per held-out scene, at the defaults: ![spp maps]({r['spp_maps']})"]
    return "\n".join(lines)
