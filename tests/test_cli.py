"""The `noisestop` command line: stdout purity with --json, one-line errors, exit codes."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from learning import make_synthetic_stack


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


def test_cli_quick_modes_are_the_tables():
    from learning.table import QUICK_MODES
    from service.commands import QUICK_MODES as CLI_MODES
    assert CLI_MODES == QUICK_MODES


def test_bench_quick_list_is_parsed_and_bad_modes_are_refused():
    import argparse

    from service.commands import _quick_modes
    assert _quick_modes("albedo,none") == ("albedo", "none")
    for bad in ("", "albedo,albedo", "sky"):
        with pytest.raises(argparse.ArgumentTypeError, match="distinct quick images"):
            _quick_modes(bad)
    out = run("bench", "models", "--quick", "albedo,bogus")
    assert out.returncode == 2 and "bogus" in out.stderr and "Traceback" not in out.stderr


def test_bench_help_names_every_section():
    from service.bench import SECTIONS
    out = run("bench", "--help")
    assert out.returncode == 0
    text = " ".join(out.stdout.split())
    assert all(name in text for name in SECTIONS), text
