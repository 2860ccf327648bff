"""Bench sections that judge stopping decisions: criteria, speed/accuracy trade-off, step.

All three follow the generalisation protocol (`learning.evaluation.generalisation`): every knob is
calibrated on the training scenes (`--data`), every figure is measured on the held-out
scenes (`--heldout`, scenes no model or threshold was fitted on), per scene, with the
scenes that converge inside their stacks pooled apart from those that never do. Every
stop goes through the one stop rule (`learning.stoprule`).
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

VARIANCE_THRESHOLDS = (0.002, 0.005, 0.01, 0.02, 0.05, 0.07, 0.1, 0.15, 0.2)
KEYS = ("precision", "early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform")
#: the comparison's model kinds drawn on the Pareto chart (every kind is in the table)
PARETO_KINDS = ("dsvm_as", "svm_as", "dsvm", "svm")


def _summary(r: dict[str, Any]) -> dict[str, Any]:
    """Metrics, per scene and per group, and the decision cost per block asked."""
    c = r.get("counters") or {}
    asked = max(1.0, float(c.get("blocks_asked", 0)))
    return {**{k: r[k] for k in KEYS},
            "per_scene": {s: {k: m[k] for k in KEYS} for s, m in r["per_scene"].items()},
            "groups": {g: {k: m[k] for k in (*KEYS, "scenes")} for g, m in (r.get("groups") or {}).items()},
            "decision_ms_per_block": 1e3 * (c.get("features_s", 0.0) + c.get("decisions_s", 0.0)) / asked,
            "blocks_asked": int(c.get("blocks_asked", 0))}


def _model_and_check(model: str | None, test_scenes: list[str]):
    from learning.models.bundle import load_model
    from learning.evaluation.generalisation import check_disjoint

    m = load_model(model)
    check_disjoint(m.manifest.get("training", {}).get("train_scenes") or [], test_scenes)
    return m


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
    from renderer.simulate import evaluate_criterion

    train, test = split_stacks(data, heldout)
    m = _model_and_check(model, [s.scene for s in test])

    def run(stacks, factory):
        return _summary(evaluate_criterion(stacks, factory))
    # variance's threshold is chosen as the model's offset and flip's c were: out of fold
    on_train = {t: evaluate_criterion(train, lambda st, t=t: VarianceCriterion(threshold=t)) for t in thresholds}
    tuned = choose_out_of_fold([{"threshold": t, **r} for t, r in on_train.items()], max_early_stop,
                               larger_is_safer=False)
    sweep = [{"threshold": t, "train": _summary(on_train[t]),
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
    from renderer.simulate import evaluate_criterion

    from . import charts
    from .bench_models import saved_comparisons

    train_stacks, test_stacks = split_stacks(data, heldout)
    bundled = _model_and_check(model, [s.scene for s in test_stacks])
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


def bench_step(data: str, heldout: str | None = None, multiples: tuple[int, ...] = (1, 2, 4, 8),
               scene: str = "env_spheres", model: str | None = None, resolution: int = 256,
               max_spp: int = 640, out_png: str = "docs/step.png") -> dict[str, Any]:
    """Render step (spp per pass) against samples, early stops and wall time.

    Samples and early stops on the held-out stacks, deciding only every k-th level (step =
    k x the dataset's step): the bundled model and flip (approximate for inputs read from
    half buffers: a k-times step pairs passes into other halves; the stored half-buffer
    scores of every k-th level stand in for them; exact for a quick-image model, whose
    input is the cumulative mean). Wall time: real renders of
    `scene` with each criterion."""
    from learning.evaluation.evaluate import by_scene, scores_by_scene
    from learning.evaluation.generalisation import split_stacks, split_tables
    from learning.inputs.halves import flip_offset, guarded_flip_scores, load_flip_calibration
    from learning.evaluation.metrics import evaluate_verdicts
    from learning.stoprule import StopRule
    from learning.inputs.halves import stack_flat
    from renderer.adaptive import adaptive_render
    from renderer.criteria import FlipCriterion, ModelCriterion, UniformCriterion

    from . import charts

    _, test_stacks = split_stacks(data, heldout)
    m = _model_and_check(model, [s.scene for s in test_stacks])
    test = split_tables(data, heldout, **m.table_options())[1]
    c = float(load_flip_calibration()["c"])
    # as the live loop reads them: no input yet, no stop; the dot guard holds its blocks
    model_scores, flat = scores_by_scene(test, m.decision_function(test.X)), by_scene(test, test.flat)
    flip_scores = {s.scene: guarded_flip_scores(s) for s in test_stacks}
    flats = {s.scene: stack_flat(s) for s in test_stacks}
    rules = {"model": (m.rule(), model_scores, flat), "flip": (StopRule(flip_offset(c)), flip_scores, flats)}
    with tempfile.TemporaryDirectory() as tmp:   # warm-up: every block's kernel compiled once
        adaptive_render(scene, Path(tmp), UniformCriterion(), step=multiples[0] * int(test_stacks[0].spp[0]),
                        min_spp=1, max_spp=multiples[0] * int(test_stacks[0].spp[0]), resolution=resolution,
                        progress=False)
    rows = []
    for k in multiples:
        step = int(test_stacks[0].spp[0]) * k
        row: dict[str, Any] = {"step": step, "render_scene": scene}
        for name, (rule, scores, fl) in rules.items():
            per = {}
            for st in test_stacks:
                sl = slice(k - 1, None, k)
                spp = list(st.spp)[sl]
                per[st.scene] = (rule.stops(scores[st.scene][sl], spp, fl[st.scene][sl]), st.labels()[sl],
                                 st.thresholds, spp)
            r = evaluate_verdicts(per)
            row[name] = {"early_stop_rate": r["early_stop_rate"], "spp_ratio_vs_oracle": r["spp_ratio_vs_oracle"]}
            crit = ModelCriterion(m) if name == "model" else FlipCriterion(c)
            with tempfile.TemporaryDirectory() as tmp:
                rep = adaptive_render(scene, Path(tmp), crit, step=step, min_spp=step, max_spp=max_spp,
                                      resolution=resolution, progress=False)
            row[name].update(wall_s=rep["wall_s"], saved_vs_uniform=rep["saved_vs_uniform"], passes=rep["passes"])
        rows.append(row)
    return {"test_scenes": [s.scene for s in test_stacks], "rows": rows,
            "plot": charts.step_size(rows, scene, out_png)}


# --- markdown ------------------------------------------------------------------------------

def _group_line(groups: dict[str, list[str]]) -> str:
    from learning.evaluation.generalisation import CONVERGING_SHARE
    return (f"Held-out scenes that converge inside their stacks (at least {CONVERGING_SHARE:.0%} of the blocks "
            f"reach the observer's threshold by the last level): {', '.join(groups.get('converging') or ['none'])}; "
            f"that mostly never converge (they only test 'never stop early'): "
            f"{', '.join(groups.get('not_converging') or ['none'])}.")


def _pair(m: dict | None) -> str:
    return "-" if not m else f"{m['early_stop_rate']:.3f} / {m['spp_ratio_vs_oracle']:.3f}"


def md_criteria(r: dict[str, Any]) -> str:
    rows = r["rows"]
    lines = [f"Trained and calibrated on {', '.join(r['train_scenes'])}; simulated on the stored stacks "
             f"of the held-out {', '.join(r['test_scenes'])}.", "", _group_line(r["groups"]), "",
             "| criterion | converging scenes: early stops / samples vs oracle | the others: early stops / "
             "samples | all: precision | all: early stops | all: samples / oracle | saved vs uniform "
             "| decision cost (ms per block asked) |", "|---|---|---|---|---|---|---|---|"]
    for x in rows.values():
        g = x.get("groups") or {}
        lines.append(f"| {x['label']} | {_pair(g.get('converging'))} | {_pair(g.get('not_converging'))} "
                     f"| {x['precision']:.3f} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} "
                     f"| {x['saved_vs_uniform']:.3f} | {x.get('decision_ms_per_block', 0):.2f} |")
    names = [n for n in ("model", "flip", "variance") if n in rows]
    lines += ["", "Per held-out scene (early-stop rate / samples vs oracle; blocks converged in the stack "
              "out of 16):", "",
              "| scene | converged blocks | " + " | ".join(rows[n]["label"] for n in names) + " |",
              "|---|---|" + "---|" * len(names)]
    for s in r["test_scenes"]:
        lines.append(f"| {s} | {r['converged_blocks'][s]} | "
                     + " | ".join(_pair(rows[n]["per_scene"].get(s)) for n in names) + " |")
    cal = r["calibration"]
    lines += ["", "The same knobs on the training scenes they were calibrated on (out-of-fold for the "
              "model): " + "; ".join(
                  f"{n} {_pair(cal[n]) if cal[n].get('early_stop_rate') is not None else '-'}"
                  for n in ("model", "flip", "variance")) + " (early stops / samples vs oracle).", "",
              "Variance threshold sweep (training / held-out: early stops, samples vs oracle):", "",
              "| threshold | training | held-out |", "|---|---|---|"]
    for row in r["variance_sweep"]:
        lines.append(f"| {row['threshold']:g} | {_pair(row['train'])} | {_pair(row['test'])} |")
    return "\n".join(lines)


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
    lines = [f"![samples vs early stops]({r['plot']}){conv}", "", _group_line(r["groups"]), "",
             f"Defaults: bundled model at offset {d['model']['offset']:.2f}: all held-out scenes "
             f"{_pair(d['model'])}, converging ones {_pair(d['model']['groups'].get('converging'))}; "
             f"flip at c {d['flip']['c']:g}: all {_pair(d['flip'])}, converging "
             f"{_pair(d['flip']['groups'].get('converging'))} (early stops / samples vs oracle).", "",
             "| criterion | fewest samples, early stops <= 5 % (all) | the same, converging scenes "
             "| fewest samples, no early stop (all) |", "|---|---|---|---|"]
    for name, rows in r["curves"].items():
        key = "threshold" if name in ("flip", "variance") else "offset"
        lines.append(f"| {name} | {_best(rows, 0.05, key)} | {_best(rows, 0.05, key, 'converging')} "
                     f"| {_best(rows, 0.0, key)} |")
    lines += ["", "Per held-out scene at the defaults (early-stop rate / samples vs oracle):", "",
              "| scene | converged blocks | bundled model | flip |", "|---|---|---|---|"]
    for s in r["test_scenes"]:
        lines.append(f"| {s} | {r['converged_blocks'][s]} | {_pair(d['model']['per_scene'].get(s))} "
                     f"| {_pair(d['flip']['per_scene'].get(s))} |")
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
            lines.append(f"| flip | c {row['threshold']:g} | {_pair(row)} | {_pair(row['groups'].get('converging'))} |")
    for row in r["curves"]["model"]:
        if abs(round(row["offset"] * 2) - row["offset"] * 2) < 1e-9:  # every 0.5
            lines.append(f"| {r['bundled']} | offset {row['offset']:.1f} | {_pair(row)} "
                         f"| {_pair(row['groups'].get('converging'))} |")
    for row in r["curves"]["variance"]:
        lines.append(f"| variance | threshold {row['threshold']:g} | {_pair(row)} "
                     f"| {_pair((row.get('groups') or {}).get('converging'))} |")
    lines += ["", f"Where the samples went, per held-out scene, at the defaults: ![spp maps]({r['spp_maps']})"]
    return "\n".join(lines)


def md_step(r: dict[str, Any]) -> str:
    scene = r["rows"][0]["render_scene"]
    lines = [f"![step size]({r['plot']})", "",
             f"| step (spp per pass) | criterion | held-out early stops | held-out samples / oracle "
             f"| {scene}: wall (s) | {scene}: saved vs uniform | passes |", "|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        for name in ("model", "flip"):
            m = x[name]
            lines.append(f"| {x['step']} | {name} | {m['early_stop_rate']:.3f} | {m['spp_ratio_vs_oracle']:.3f} "
                         f"| {m['wall_s']:.1f} | {m['saved_vs_uniform']:.3f} | {m['passes']} |")
    return "\n".join(lines)
