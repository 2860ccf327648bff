"""The BENCHMARKS.md machinery: marked sections and the trade-off chart."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from learning.models.bundle import save_model
from learning.inputs.table import load_table
from learning.training.train import train_model
from learning.training.knobs import measure_knobs
from benchmarks.marked_sections import update_markdown
from benchmarks.bench_tradeoff import bench_tradeoff, md_tradeoff
from benchmarks.bench_models import bench_models
from tests.support import FIXTURE_DATASET as FIXTURE



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


def test_a_section_on_a_detail_page_is_written_there(tmp_path):
    """The report keeps its headline; a section whose markers are on a detail page
    (docs/benchmarks/*.md beside the report) is rewritten there, its links rebased from the
    report's folder to the page's, the report untouched; one
    whose markers are nowhere is appended to the report. Control: the report's own section
    is still written in the report."""
    report = tmp_path / "B.md"
    report.write_text("# B\n<!-- bench:head -->\nold head\n<!-- /bench:head -->\nSee the details.\n")
    details = tmp_path / "docs" / "benchmarks"
    details.mkdir(parents=True)
    (details / "speed.md").write_text("# Speed\n<!-- bench:cost -->\nold cost\n<!-- /bench:cost -->\nend\n")
    (details / "other.md").write_text("# Other\nno markers\n")
    before = report.read_text()
    update_markdown(report, {"cost": "new cost"})
    assert report.read_text() == before
    assert (details / "speed.md").read_text() == "# Speed\n<!-- bench:cost -->\nnew cost\n<!-- /bench:cost -->\nend\n"
    assert (details / "other.md").read_text() == "# Other\nno markers\n"
    update_markdown(report, {"cost": "![chart](docs/cost.png), [report](B.md#head), [x](https://x.org/a.md)"})
    assert "![chart](../cost.png), [report](../../B.md#head), [x](https://x.org/a.md)" in (details / "speed.md").read_text()
    update_markdown(report, {"head": "new head", "fresh": "appended"})
    text = report.read_text()
    assert "new head" in text and "old head" not in text and text.endswith("<!-- /bench:fresh -->\n")
    assert "fresh" not in (details / "speed.md").read_text()


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> tuple[str, str]:
    """The fixture as the protocol's two datasets: 'cornell' held out, the rest to train on."""
    import shutil
    root = tmp_path_factory.mktemp("split")
    for scene in ("checker", "cornell_dark", "sky", "cornell"):
        shutil.copytree(FIXTURE / scene, root / ("heldout" if scene == "cornell" else "train") / scene)
    return str(root / "train"), str(root / "heldout")


def fixture_model(tmp_path, data=FIXTURE, test_scenes=None, quick="none") -> Path:
    """A DSVM (quick 'none' unless told) trained on `data` (default split of the fixture:
    'cornell' held out, in its manifest; `test_scenes=[]`: every scene trained on)."""
    table = load_table(data, progress=False, quick=quick)
    est, summary = train_model("dsvm", str(data), table=table, cv=False, quick=quick, progress=False,
                               test_scenes=test_scenes)
    return save_model(est, tmp_path / "m", kind="dsvm", input="features", training=summary,
                      extra={"quick": quick})


@pytest.mark.slow
def test_tradeoff_draws_every_criterion_and_the_saved_comparison(tmp_path, split):
    train, heldout = split
    model = fixture_model(tmp_path, train, [])
    saved = tmp_path / "bench"
    kw = dict(out_dir=saved, model=str(model), thresholds=(0.05, 0.2))
    saved.mkdir()
    (saved / "models-stale.json").write_text(json.dumps({"fingerprint": "another dataset", "rows": []}))
    comp = bench_models(train, saved, arches=(), kinds=("dsvm", "svm_as"), quick="none",
                        plots_dir=str(tmp_path), heldout=heldout)
    assert comp["test_scenes"] == ["cornell"] and comp["train_scenes"] == ["checker", "cornell_dark", "sky"]
    assert json.loads((saved / "models-none.json").read_text())["rows"][1]["model"] == "svm_as"
    assert all(len(row["offset_curve"]) == 71 for row in comp["rows"])
    r = bench_tradeoff(train, heldout, out_png=str(tmp_path / "p.png"), **kw)
    assert r["test_scenes"] == ["cornell"] and Path(r["plot"]).stat().st_size > 1000
    assert set(r["curves"]) == {"model", "flip", "variance", "dsvm quick none", "svm_as"}
    assert not any(d.startswith("dsvm quick none,") for d in r["drawn"])   # the bundle's twin is not drawn
    assert any(d.startswith("svm_as") for d in r["drawn"]) and any(d.startswith("flip") for d in r["drawn"])
    for name, rows in r["curves"].items():
        early = [row["early_stop_rate"] for row in rows]
        # a larger offset never stops earlier; a larger c (flip) or threshold (variance) never later
        assert early == sorted(early, reverse=name not in ("flip", "variance")), name
        assert all(np.isfinite(row["spp_ratio_vs_oracle"]) for row in rows)
    d = r["defaults"]
    assert d["model"]["offset"] == 0 and d["flip"]["c"] > 0 and len(r["curves"]["variance"]) == 2
    assert set(d["flip"]["per_scene"]) == {"cornell"} and Path(r["spp_maps"]).stat().st_size > 1000
    assert set(r["flip_at_threshold"]) == {"training", "held-out"} and r["flip_at_threshold"]["held-out"]["blocks"] > 0
    md = md_tradeoff(r)
    assert "| svm_as |" in md and "| cornell |" in md and "offset 0.0" in md and "| flip | c " in md
    with pytest.raises(ValueError, match="both trained on and held out"):   # the model saw cornell
        bench_tradeoff(train, heldout, out_png=str(tmp_path / "q.png"), out_dir=saved,
                       model=str(fixture_model(tmp_path / "all", FIXTURE, [])), thresholds=(0.05,))


@pytest.mark.slow
def test_criteria_section_simulates_every_criterion_on_held_out_scenes(tmp_path, split):
    from benchmarks.bench_criteria import bench_criteria, md_criteria
    train, heldout = split
    r = bench_criteria(train, heldout, model=str(fixture_model(tmp_path, train, [])), thresholds=(0.01, 0.2))
    assert r["test_scenes"] == ["cornell"] and set(r["rows"]) == {"model", "flip", "variance", "oracle", "uniform"}
    assert r["rows"]["oracle"]["early_stop_rate"] == 0 and r["rows"]["oracle"]["spp_ratio_vs_oracle"] == 1
    assert r["rows"]["uniform"]["saved_vs_uniform"] == 0
    assert r["rows"]["flip"]["decision_ms_per_block"] > 0 and r["rows"]["model"]["decision_ms_per_block"] > 0
    md = md_criteria(r)
    assert "| cornell |" in md and "decision cost" in md and md.count("| flip (c ") == 2


@pytest.mark.slow
def test_ablation_rows_cover_every_switch(tmp_path, split):
    from benchmarks.bench_models import bench_ablation, md_ablation
    r = bench_ablation(*split, out_png=str(tmp_path / "a.png"))
    combos = {(x["weights"], x["quick"], x["wavelet"]) for x in r["rows"]}
    assert len(combos) == 12 and {q for _, q, _ in combos} == {"albedo", "direct", "none"}
    assert all(0 <= x["precision"] <= 1 and np.isfinite(x["spp_ratio_vs_oracle"]) for x in r["rows"])
    cost = {x["quick"]: x["quick_render_s"] for x in r["rows"]}
    assert cost["none"] == 0 and cost["albedo"] > 0 and cost["direct"] > 0
    assert md_ablation(r).count("\n") == 15 and Path(r["plot"]).stat().st_size > 1000


@pytest.mark.slow
def test_step_sizes_thin_the_decisions(tmp_path, split):
    from learning.models.bundle import load_model
    from learning.evaluation.evaluate import evaluate_model
    from learning.evaluation.generalisation import split_tables
    from benchmarks.bench_step import bench_step, md_step
    model = fixture_model(tmp_path, split[0], [], quick="halves")     # the shipped kind of input
    r = bench_step(*split, multiples=(1, 2), scene="cornell", model=str(model),
                   resolution=32, max_spp=192, out_png=str(tmp_path / "s.png"))
    steps = [x["step"] for x in r["rows"]]
    assert steps == [48, 96]
    # at the stack's own step the rows are the one route's figures: no stop at the first
    # level, where the second half buffer is still empty
    m = load_model(model)
    direct = evaluate_model(m, split_tables(*split, **m.table_options())[1])
    for key in ("early_stop_rate", "spp_ratio_vs_oracle"):
        assert r["rows"][0]["model"][key] == pytest.approx(direct[key])
    for name in ("model", "flip"):
        assert r["rows"][1][name]["passes"] <= 2
        # deciding less often can only stop later: never fewer samples
        assert r["rows"][1][name]["spp_ratio_vs_oracle"] >= r["rows"][0][name]["spp_ratio_vs_oracle"] - 1e-12
    assert md_step(r).count("\n") == 3 + 2 * 2 and Path(r["plot"]).stat().st_size > 1000


def test_cost_accuracy_plot_needs_rows_with_both_axes(tmp_path):
    from learning.evaluation.plots import plot_cost_accuracy
    rows = [{"model": "dsvm", "precision": 0.8, "test_101_s": 0.05},
            {"model": "vgg19 (untrained base)", "precision": 0.7, "test_101_s": 1.5},
            {"model": "resnet50 (unavailable: no torchvision)"}]
    png = plot_cost_accuracy(rows, tmp_path / "c.png")
    assert png.stat().st_size > 1000
    with pytest.raises(ValueError, match="no model row"):
        plot_cost_accuracy(rows[2:], tmp_path / "d.png")


def test_run_all_hands_each_section_over_as_it_finishes(tmp_path):
    from renderer.dataset.build import append_build_log
    from benchmarks.bench import run_all
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
    from benchmarks.bench_passes import bench_render, md_render
    r = bench_render(scene="cornell", resolution=32, max_spp=64, step=16,
                     model=str(fixture_model(tmp_path)), repeats=3)
    for name in ("model", "flip", "uniform"):
        walls = r[name]["walls_s"]
        assert len(walls) == 3 and r[name]["wall_s"] == sorted(walls)[1]
    assert r["uniform"]["saved_vs_uniform"] == 0 and 0 <= r["model"]["saved_vs_uniform"] < 1
    for name in ("model", "flip"):
        assert r[name]["speedup_vs_uniform"] == pytest.approx(r["uniform"]["wall_s"] / r[name]["wall_s"])
        assert 0 < r[name]["decision_share"] < 1
    assert "median of 3" in md_render(r) and "| flip criterion |" in md_render(r)


@pytest.mark.slow
def test_knobs_train_each_setting_and_mark_the_default(split):
    from learning.training.train import CV_MAX_SAMPLES
    from benchmarks.bench_models import md_knobs
    r = measure_knobs(*split, cv_caps=(100, CV_MAX_SAMPLES, 0), batches=(16, 64))
    cv = [x for x in r["rows"] if x["kind"] == "dsvm"]
    assert [x["value"] for x in cv] == [100, CV_MAX_SAMPLES, "all"] and [x["default"] for x in cv] == [0, 1, 0]
    assert cv[0]["cv_rows"] <= 112 < cv[2]["cv_rows"]         # whole groups of 16, up to the cap
    al = [x for x in r["rows"] if x["kind"] == "dsvm_as"]
    assert [x["default"] for x in al] == [True, False]
    assert all(0 <= x["precision"] <= 1 and np.isfinite(x["spp_ratio_vs_oracle"]) for x in r["rows"])
    md = md_knobs(r)
    assert md.count("\n") == 2 + 2 + len(r["rows"]) - 1 and "16 *" in md


def test_flip_section_times_both_routes_on_the_same_blocks_and_restores_threads():
    import torch

    from benchmarks.bench_flip import bench_flip, md_flip
    before = torch.get_num_threads()
    r = bench_flip(repeats=1, shapes=((2, 16), (1, 24)), threads=(1, 2))
    assert torch.get_num_threads() == before
    assert [(x["threads"], x["blocks"], x["size"]) for x in r["rows"]] == [(1, 2, 16), (1, 1, 24), (2, 2, 16), (2, 1, 24)]
    for x in r["rows"]:
        assert x["evaluator_ms"] > 0 and x["torch_ms"] > 0 and x["mean_e"] > 0.01
        assert x["max_rel_diff"] < 1e-4                      # the same figure from both routes
        assert x["speedup"] == pytest.approx(x["evaluator_ms"] / x["torch_ms"])
    md = md_flip(r)
    timing, pooling = md.split("What the tile pooling adds")
    assert "| 2 | 1 of 24x24 |" in timing and "load average" in timing and timing.count("\n| ") == 5
    assert [x["blocks"] for x in r["pooling"]] == [1, 16, 16] and pooling.count("\n| ") == 4


def test_flip_section_compares_both_routes_on_labelled_stacks():
    from benchmarks.bench_flip import bench_flip, md_flip
    r = bench_flip(repeats=1, shapes=((1, 16),), threads=(1,), datasets=(str(FIXTURE),))
    (d,) = r["datasets"]
    assert d["values"] > 50 and d["max_abs_diff"] < 1e-5 and d["median_rel_diff"] < 1e-5
    assert d["flip_verdict_changes"] == 0 and d["model_verdict_changes"] == 0
    assert d["flip_candidates"] > 100 and d["model_max_score_diff"] < 1e-2
    assert f"| {FIXTURE} | {d['values']} (" in md_flip(r)


def test_the_cold_rows_xml_is_mitsubas_cornell_box() -> None:
    """bench native's cold row renders Mitsuba's Cornell box from an XML file (the plain
    script and `noisestop render` both read one): the XML written renders the very image
    `mi.cornell_box()` does."""
    import mitsuba as mi
    import numpy as np

    from benchmarks.bench_cold import cbox_xml
    from learning.data.variant import select_variant

    mi.set_variant(select_variant())
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 32
    a = np.asarray(mi.render(mi.load_string(cbox_xml(32)), spp=4, seed=3))
    b = np.asarray(mi.render(mi.load_dict(d), spp=4, seed=3))
    assert a.shape == (32, 32, 3) and np.allclose(a, b, atol=1e-5) and a.mean() > 0.05


def test_the_per_sample_split_times_each_row_against_one_mi_render() -> None:
    """benchmarks.bench_per_sample at a tiny size: every row timed, each ratio to one
    mi.render (the first row 1.0 by definition), medians of the runs kept."""
    from benchmarks.bench_per_sample import ROWS, md_per_sample, per_sample

    r = per_sample(size=16, spp=8, step=4, grown=2, repeats=1)
    assert set(r["median_s"]) == set(ROWS) and r["ratio"]["mi_render_once"] == 1.0
    assert all(v > 0 and np.isfinite(v) for v in r["ratio"].values())
    assert all(len(w) == 1 for w in r["walls"].values())
    assert r["mean_spp"]["uniform_loop"] == 8.0 and 4.0 <= r["mean_spp"]["default_loop"] <= 8.0
    table = md_per_sample(r)
    assert table.count("\n| ") == len(ROWS) + 1 and "2 passes a launch" in table
