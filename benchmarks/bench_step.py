"""`bench step`: the render step (spp per pass) against samples, early stops and wall time
(docs/benchmarks/accuracy.md "The render step"), on the held-out stacks and in real renders.
"""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

from .decisions import model_and_check


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
    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import FlipCriterion, ModelCriterion, UniformCriterion

    from . import charts

    _, test_stacks = split_stacks(data, heldout)
    m = model_and_check(model, [s.scene for s in test_stacks])
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
