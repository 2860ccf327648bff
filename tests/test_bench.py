"""The BENCHMARKS.md machinery: marked sections and the trade-off chart."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from learning.bundle import save_model
from learning.table import load_table
from learning.train import train_model
from learning.knobs import measure_knobs
from service.bench import bench_models, bench_tradeoff, md_tradeoff, update_markdown

FIXTURE = Path(__file__).parent / "fixtures" / "dataset"


def test_update_markdown_replaces_only_its_section(tmp_path):
    doc = tmp_path / "B.md"
    doc.write_text("intro\n<!-- bench:a -->\nold a\n<!-- /bench:a -->\nmiddle\n"
                   "<!-- bench:b -->\nold b\n<!-- /bench:b -->\nend\n")
    update_markdown(doc, {"a": "new a"})
    text = doc.read_text()
    assert "new a" in text and "old a" not in text and "old b" in text
    assert text.startswith("intro") and "middle" in text and text.endswith("end\n")
    update_markdown(doc, {"c": "fresh"})
    assert "<!-- bench:c -->\nfresh\n<!-- /bench:c -->" in doc.read_text()


def fixture_model(tmp_path) -> Path:
    """A quick-'none' DSVM trained on the fixture, 'cornell' held out (in its manifest)."""
    table = load_table(FIXTURE, progress=False, quick="none")
    est, summary = train_model("dsvm", str(FIXTURE), table=table, cv=False, quick="none",
                               progress=False)
    return save_model(est, tmp_path / "m", kind="dsvm", input="features", training=summary,
                      extra={"quick": "none"})


@pytest.mark.slow
def test_tradeoff_draws_the_saved_comparison_on_the_fixture(tmp_path):
    model = fixture_model(tmp_path)
    saved = tmp_path / "bench"
    kw = dict(out_dir=saved, model=str(model), thresholds=(0.05, 0.2))
    with pytest.raises(ValueError, match="bench models"):
        bench_tradeoff(str(FIXTURE), out_png=str(tmp_path / "p.png"), **kw)
    (saved).mkdir()
    (saved / "models-stale.json").write_text(json.dumps({"fingerprint": "another dataset", "rows": []}))
    comp = bench_models(str(FIXTURE), saved, arches=(), kinds=("dsvm", "svm_as"), quick="none",
                        plots_dir=str(tmp_path))
    assert json.loads((saved / "models-none.json").read_text())["rows"][1]["model"] == "svm_as"
    assert all(len(row["offset_curve"]) == 41 for row in comp["rows"])
    r = bench_tradeoff(str(FIXTURE), out_png=str(tmp_path / "p.png"), **kw)
    assert r["test_scenes"] == ["cornell"] and Path(r["plot"]).stat().st_size > 1000
    assert set(r["curves"]) == {"dsvm quick none (bundled)", "dsvm quick none", "svm_as"}
    assert r["drawn"] == ["dsvm quick none (bundled)", "svm_as"]     # the bundle's twin is not drawn
    for rows in r["curves"].values():
        early = [row["early_stop_rate"] for row in rows]
        assert early == sorted(early, reverse=True)     # a larger offset never stops earlier
        assert all(np.isfinite(row["spp_ratio_vs_oracle"]) for row in rows)
    assert r["default"]["offset"] == 0 and len(r["variance"]) == 2
    assert Path(r["spp_maps"]).stat().st_size > 1000
    (scene,) = r["spp_by_scene"]
    assert scene["scene"] == "cornell" and 0 < scene["model_spp"] <= scene["uniform_spp"]
    assert 0 < scene["oracle_spp"] <= scene["uniform_spp"]
    md = md_tradeoff(r)
    assert "| svm_as |" in md and "| cornell |" in md and "offset 0.0" in md


@pytest.mark.slow
def test_ablation_rows_cover_every_switch(tmp_path):
    from service.bench import bench_ablation, md_ablation
    r = bench_ablation(str(FIXTURE), out_png=str(tmp_path / "a.png"))
    combos = {(x["weights"], x["quick"], x["wavelet"]) for x in r["rows"]}
    assert len(combos) == 12 and {q for _, q, _ in combos} == {"albedo", "direct", "none"}
    assert all(0 <= x["precision"] <= 1 and np.isfinite(x["spp_ratio_vs_oracle"]) for x in r["rows"])
    cost = {x["quick"]: x["quick_render_s"] for x in r["rows"]}
    assert cost["none"] == 0 and cost["albedo"] > 0 and cost["direct"] > 0
    assert md_ablation(r).count("\n") == 15 and Path(r["plot"]).stat().st_size > 1000


@pytest.mark.slow
def test_step_sizes_thin_the_decisions(tmp_path):
    from service.bench import bench_step, md_step
    model = fixture_model(tmp_path)
    r = bench_step(str(FIXTURE), multiples=(1, 2), scene="cornell", model=str(model),
                   resolution=32, max_spp=192, out_png=str(tmp_path / "s.png"))
    steps = [x["step"] for x in r["rows"]]
    assert steps == [48, 96] and [x["passes"] for x in r["rows"]][1] <= 2
    # deciding less often can only stop later: never fewer samples
    assert r["rows"][1]["spp_ratio_vs_oracle"] >= r["rows"][0]["spp_ratio_vs_oracle"] - 1e-12
    assert md_step(r).count("\n") == 5 and Path(r["plot"]).stat().st_size > 1000


def test_cost_accuracy_plot_needs_rows_with_both_axes(tmp_path):
    from learning.plots import plot_cost_accuracy
    rows = [{"model": "dsvm", "precision": 0.8, "test_101_s": 0.05},
            {"model": "vgg19 (untrained base)", "precision": 0.7, "test_101_s": 1.5},
            {"model": "resnet50 (unavailable: no torchvision)"}]
    png = plot_cost_accuracy(rows, tmp_path / "c.png")
    assert png.stat().st_size > 1000
    with pytest.raises(ValueError, match="no model row"):
        plot_cost_accuracy(rows[2:], tmp_path / "d.png")


def test_run_all_hands_each_section_over_as_it_finishes(tmp_path):
    from renderer.dataset import append_build_log
    from service.bench import run_all
    with pytest.raises(ValueError, match="criteria, models needs --data"):
        run_all(only=("models", "criteria"))
    run = {"wall_s": 754.2, "sub_images": 32, "finished": "2026-11-23T12:00:00+00:00", "cpus": 2,
           "workers": None, "scheduler": None, "failed": {},
           "settings": {"resolution": 32, "step": 4, "levels": 2, "reference_spp": 64},
           "scenes": [{"scene": "sky", "seconds": 3.0, "censored": 0, "variant": "scalar_rgb",
                       "resumed": False, "already_built": False}]}
    missing = run_all(only=("dataset",), data=str(tmp_path))       # reported, not raised
    assert "no build run on record" in missing["failed"]["dataset"] and not missing["markdown"]
    append_build_log(tmp_path, run)
    seen = []
    r = run_all(only=("dataset",), data=str(tmp_path), on_section=lambda n, md: seen.append((n, md)))
    assert [n for n, _ in seen] == ["dataset"] and "**12 min 34 s** wall" in seen[0][1]
    assert r["seconds"]["dataset"] >= 0 and r["markdown"]["dataset"] == seen[0][1] and not r["failed"]


@pytest.mark.slow
def test_render_bench_alternates_runs_and_reports_medians(tmp_path):
    from service.bench import bench_render, md_render
    r = bench_render(scene="cornell", resolution=32, max_spp=64, step=16,
                     model=str(fixture_model(tmp_path)), repeats=3)
    for name in ("model", "uniform"):
        walls = r[name]["walls_s"]
        assert len(walls) == 3 and r[name]["wall_s"] == sorted(walls)[1]
    assert r["uniform"]["saved_vs_uniform"] == 0 and 0 <= r["model"]["saved_vs_uniform"] < 1
    assert r["speedup_vs_uniform"] == pytest.approx(r["uniform"]["wall_s"] / r["model"]["wall_s"])
    assert "median of 3" in md_render(r)


@pytest.mark.slow
def test_knobs_train_each_setting_and_mark_the_default():
    from learning.train import CV_MAX_SAMPLES
    from service.bench import md_knobs
    r = measure_knobs(str(FIXTURE), cv_caps=(100, CV_MAX_SAMPLES, 0), batches=(16, 64))
    cv = [x for x in r["rows"] if x["kind"] == "dsvm"]
    assert [x["value"] for x in cv] == [100, CV_MAX_SAMPLES, "all"] and [x["default"] for x in cv] == [0, 1, 0]
    assert cv[0]["cv_rows"] <= 112 < cv[2]["cv_rows"]         # whole groups of 16, up to the cap
    al = [x for x in r["rows"] if x["kind"] == "dsvm_as"]
    assert [x["default"] for x in al] == [True, False]
    assert all(0 <= x["precision"] <= 1 and np.isfinite(x["spp_ratio_vs_oracle"]) for x in r["rows"])
    md = md_knobs(r)
    assert md.count("\n") == 2 + 2 + len(r["rows"]) - 1 and "16 *" in md
