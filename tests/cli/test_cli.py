"""The `noisestop` command line: stdout purity with --json, one-line errors, exit codes."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from learning import make_synthetic_stack
from tests.support import FIXTURE_DATASET as FIXTURE


def run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_scenes_lists_builtins_as_json():
    out = run("scenes", "--json")
    assert out.returncode == 0
    scenes = json.loads(out.stdout)["scenes"]
    names = {s["name"] for s in scenes}
    assert len(scenes) >= 12 and {"cornell", "allblack", "sky"} <= names
    assert all(s["description"] for s in scenes)


@pytest.mark.slow
def test_features_json_has_26_values_per_block():
    out = run("features", "--scene", "cornell", "--resolution", "32", "--spp", "4", "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)          # stdout holds exactly one JSON object
    assert len(data["features"]) == 16 and all(len(r) == 26 for r in data["features"])
    assert data["variant"] in {"llvm_ad_rgb", "scalar_rgb", "cuda_ad_rgb"}


@pytest.mark.slow
def test_features_table_is_printed():
    out = run("features", "--resolution", "32", "--spp", "2")
    assert out.returncode == 0, out.stderr
    assert "std13" in out.stdout and out.stdout.count("\n") >= 18


def test_unknown_scene_is_one_line_error_without_traceback():
    out = run("features", "--scene", "no_such_scene", "--resolution", "32")
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
    assert "no_such_scene" in out.stderr and "cornell" in out.stderr


def test_uneven_grid_is_a_clear_error():
    out = run("features", "--resolution", "30", "--spp", "1")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "grid" in out.stderr


def test_uneven_grid_is_refused_before_rendering(monkeypatch, capsys):
    from renderer.live.blocks import BlockRenderer
    from service.cli import main

    def traced(*args, **kwargs):
        raise AssertionError("rendered before the grid was checked")

    monkeypatch.setattr(BlockRenderer, "render_full", traced)
    assert main(["features", "--resolution", "66", "--grid", "4", "4", "--spp", "1"]) == 2
    err = capsys.readouterr().err
    assert "cannot be cut into a 4x4 grid" in err and "rendered before" not in err


def test_dataset_check_exit_codes(tmp_path):
    make_synthetic_stack(tmp_path / "good" / "s1", size=32, spp=(4, 8, 16))
    ok = run("dataset", "check", str(tmp_path / "good"), "--json")
    assert ok.returncode == 0 and json.loads(ok.stdout)["ok"] is True
    (tmp_path / "good" / "s1" / "levels" / "000008.exr").unlink()
    bad = run("dataset", "check", str(tmp_path / "good"))
    assert bad.returncode == 1 and "000008.exr" in bad.stdout


def test_argument_errors_exit_2():
    out = run("dataset", "build", "--out", "x", "--step", "0")
    assert out.returncode == 2 and "expected a number >= 1" in out.stderr


def test_the_parser_builds_without_torch_or_mitsuba():
    """The choices come from their one home (learning.names, the criteria's declarations in
    renderer.criteria, ...), and those homes import nothing heavy: the command line starts fast and keeps no copies."""
    code = ("import sys, service.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('torch', 'mitsuba', 'drjit', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def test_bench_quick_list_is_parsed_and_bad_modes_are_refused():
    import argparse

    from service.commands.arguments import quick_modes
    assert quick_modes("albedo,none") == ("albedo", "none")
    for bad in ("", "albedo,albedo", "sky"):
        with pytest.raises(argparse.ArgumentTypeError, match="distinct quick images"):
            quick_modes(bad)
    out = run("bench", "models", "--quick", "albedo,bogus")
    assert out.returncode == 2 and "bogus" in out.stderr and "Traceback" not in out.stderr


def test_bench_help_names_every_section():
    from benchmarks.bench import SECTIONS
    out = run("bench", "--help")
    assert out.returncode == 0
    text = " ".join(out.stdout.split())
    assert all(name in text for name in SECTIONS), text


# --- one decision route, the flip criterion, held-out scenes ----------------------------------


def test_scenes_marks_the_held_out_set():
    scenes = json.loads(run("scenes", "--json").stdout)["scenes"]
    held = {s["name"] for s in scenes if s["heldout"]}
    assert len(held) == 8 and "cornell" not in held and "studio_preview" in held
    table = run("scenes").stdout
    assert "held out" in table and "training" in table


def test_speed_knobs_must_be_finite_numbers():
    for cmd in (("evaluate", "--data", "x"), ("render", "--out", "x"), ("serve",)):
        for bad in ("nan", "inf", "fast"):
            out = run(*cmd, "--offset", bad)
            assert out.returncode == 2 and "--offset" in out.stderr and "Traceback" not in out.stderr, (cmd, bad)
    out = run("evaluate", "--data", "x", "--threshold=-inf")
    assert out.returncode == 2 and "finite" in out.stderr


def test_evaluate_flip_and_model_offset_as_json():
    out = run("evaluate", "--data", str(FIXTURE), "--criterion", "flip", "--threshold", "0.03", "--json")
    assert out.returncode == 0, out.stderr
    flip = json.loads(out.stdout)
    assert flip["threshold"] == 0.03 and set(flip["per_scene"]) == {"checker", "cornell", "cornell_dark", "sky"}
    assert flip["groups"]["converging"]["scenes"] and 0 <= flip["early_stop_rate"] <= 1
    assert flip["per_scene"]["sky"]["saved_vs_uniform"] > 0.9          # flat: stops at the first level
    stricter = json.loads(run("evaluate", "--data", str(FIXTURE), "--criterion", "flip", "--threshold", "0.005",
                              "--json").stdout)
    assert stricter["saved_vs_uniform"] <= flip["saved_vs_uniform"]    # a smaller c stops later


def test_calibrate_writes_c_and_refuses_held_out_scenes(tmp_path):
    out = run("calibrate", "--data", str(FIXTURE), "--out", str(tmp_path / "flip.json"), "--json")
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    saved = json.loads((tmp_path / "flip.json").read_text())
    assert [p["tau"] for p in got["curve"]] == [p["tau"] for p in saved["curve"]]
    assert saved["curve"][0]["tau"] <= 0.01 and saved["curve"][-1]["tau"] >= 0.05
    assert [p["c"] for p in got["curve"]] == [p["c"] for p in saved["curve"]]
    assert all(p["chosen"]["early_stop_rate"] <= 0.05 for p in saved["curve"])
    assert saved["scenes"] == ["checker", "cornell", "cornell_dark", "sky"] and saved["fingerprint"]
    assert saved["pooling"] == "tile8-max" and saved["observer_pooling"] == "tile16-max+dots"
    # a held-out scene may take no part in calibration (nor in training)
    held = tmp_path / "data" / "studio_preview"
    make_synthetic_stack(held, size=32, spp=(8, 16))
    meta = json.loads((held / "meta.json").read_text())
    meta["scene"] = "studio_preview"
    (held / "meta.json").write_text(json.dumps(meta))
    for cmd in (("calibrate", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "x.json")),
                ("train", "--data", str(tmp_path / "data"), "--model", "dsvm", "--out", str(tmp_path / "m"),
                 "--test-scenes", "")):
        out = run(*cmd)
        assert out.returncode == 2 and "studio_preview" in out.stderr and "held out" in out.stderr, out.stderr


@pytest.mark.slow
def test_calibrate_trains_the_estimate_bundle_that_evaluate_then_reads(tmp_path):
    """`calibrate --criterion estimate` writes a bundle (estimator and c(tau)); found in the
    user data directory, `evaluate --criterion estimate` decides with it. Options of the
    other criterion or that do not fit together are one line and exit 2."""
    import os

    out = run("calibrate", "--criterion", "estimate", "--data", str(FIXTURE), "--out", str(tmp_path / "ud" / "estimate"),
              "--json")
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    manifest = json.loads((tmp_path / "ud" / "estimate" / "manifest.json").read_text())
    assert got["rows"] == manifest["training"]["rows"] > 0 and manifest["tile"] == 16
    assert [p["c"] for p in got["curve"]] == [p["c"] for p in manifest["calibration"]["curve"]]
    env = {**os.environ, "NOISESTOP_DATA_DIR": str(tmp_path / "ud")}
    ev = subprocess.run([sys.executable, "-m", "service.cli", "evaluate", "--data", str(FIXTURE), "--criterion",
                         "estimate", "--tile", "16", "--json"], capture_output=True, text=True, env=env, timeout=600)
    assert ev.returncode == 0, ev.stderr
    r = json.loads(ev.stdout)
    assert r["criterion"]["name"] == "estimate" and r["criterion"]["source"] == str(tmp_path / "ud" / "estimate")
    assert set(r["per_scene"]) == {"checker", "cornell", "cornell_dark", "sky"}
    for bad, words in ((("--min-spp", "8"), "--min-spp"), (("--kind", "linear", "--quantile", "0.9"), "--kind gbm")):
        out = run("calibrate", "--criterion", "estimate", "--data", str(FIXTURE), "--out", str(tmp_path / "x"), *bad)
        assert out.returncode == 2 and words in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_tau_outside_the_calibrated_range_or_not_a_number_is_one_line_and_exit_2(tmp_path):
    for cmd in (("evaluate", "--data", str(FIXTURE), "--criterion", "flip"),
                ("evaluate", "--data", str(FIXTURE), "--criterion", "model"),
                ("render", "--scene", "cornell", "--out", str(tmp_path / "r"), "--criterion", "flip"),
                ("serve", "--port", "0", "--no-auth")):
        out = run(*cmd, "--tau", "0.5")
        assert out.returncode == 2 and "outside" in out.stderr and "[0.01, 0.05]" in out.stderr, (cmd, out.stderr)
        errors = [line for line in out.stderr.splitlines() if "error" in line]   # progress bars aside
        assert len(errors) == 1 and "outside" in errors[0] and "Traceback" not in out.stderr
        for bad in ("nan", "inf", "-0.01", "0", "strict"):
            out = run(*cmd, "--tau", bad)
            assert out.returncode == 2 and "--tau" in out.stderr and "Traceback" not in out.stderr, (cmd, bad)


def test_evaluate_labels_at_the_noise_target_and_reports_it():
    runs = {tau: json.loads(run("evaluate", "--data", str(FIXTURE), "--criterion", "oracle", "--tau", tau,
                                "--json").stdout) for tau in ("0.01", "0.04")}
    assert runs["0.01"]["tau"] == 0.01 and runs["0.04"]["tau"] == 0.04
    # a stricter target: the oracle (the labels themselves) spends at least as many samples
    assert runs["0.01"]["saved_vs_uniform"] <= runs["0.04"]["saved_vs_uniform"]
    flip = json.loads(run("evaluate", "--data", str(FIXTURE), "--criterion", "flip", "--tau", "0.04",
                          "--json").stdout)
    assert flip["tau"] == 0.04 and flip["criterion"]["tau"] == 0.04


def test_dataset_relabel_rewrites_first_observer_labels_and_keeps_human_ones(tmp_path):
    import shutil
    data = tmp_path / "d"
    shutil.copytree(FIXTURE, data, ignore=shutil.ignore_patterns(".cache"))
    meta = data / "cornell" / "meta.json"
    m = json.loads(meta.read_text())
    m["labeler"].pop("pooling")                                   # as the first observer wrote it
    meta.write_text(json.dumps(m))
    h = json.loads((data / "sky" / "meta.json").read_text())
    h["labeler"] = {"name": "human", "source": "LISIC"}
    (data / "sky" / "meta.json").write_text(json.dumps(h))
    out = json.loads(run("dataset", "relabel", str(data), "--json").stdout)
    done = {r["scene"]: r["relabelled"] for r in out["stacks"]}
    # the fixture's current labels lack the tile truth: relabel writes it too
    assert done == {"checker": True, "cornell": True, "cornell_dark": True, "sky": False}
    assert json.loads(meta.read_text())["labeler"]["pooling"] == "tile16-max+dots"
    assert len(json.loads(meta.read_text())["tile_thresholds"]) == 16   # 16-px blocks: a tile each
    again = json.loads(run("dataset", "relabel", str(data), "--json").stdout)
    assert not any(r["relabelled"] for r in again["stacks"])         # now current: nothing to do
    out = run("dataset", "relabel", str(data), "--pooling", "mean")
    assert out.returncode == 0 and "3 of 4 stacks relabelled (mean)" in out.stdout
    m = json.loads(meta.read_text())
    m["labeler"]["pooling"] = "p99"
    meta.write_text(json.dumps(m))
    out = run("evaluate", "--data", str(data), "--criterion", "oracle")
    assert out.returncode == 2 and "pooling 'p99' is unknown" in out.stderr and "Traceback" not in out.stderr
