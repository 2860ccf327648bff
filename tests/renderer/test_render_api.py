"""`renderer.render`: in memory, the command line's very loop, mi.Scene input, reference images."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

import renderer
from learning.data.exr import read_exr_channels, write_exr
from renderer.live.adaptive import adaptive_render
from service import cli

pytestmark = pytest.mark.slow

TINY = {"resolution": 64, "block": 32, "step": 8, "min_spp": 8, "max_spp": 32, "progress": False}
TIMING_KEYS = {"wall_s", "timing", "render_calls"}


def without_timing(report: dict) -> dict:
    return {k: v for k, v in report.items() if k not in TIMING_KEYS}


@pytest.fixture(scope="module")
def flip_result():
    return renderer.render("cornell", **TINY)


def assert_adaptive(res, max_spp: int) -> None:
    """The arrays are the report's units, its blocks' tiles (each tile's window carries its
    spp and its converged flag), and the render was adaptive: some tile stopped before
    max_spp, where a uniform render would have sampled every one to it."""
    for b in res.report.get("tiles", res.report["blocks"]):
        x, y, w, h = b["window"]
        assert (res.spp[y:y + h, x:x + w] == b["spp"]).all(), b["id"]
        assert (res.converged[y:y + h, x:x + w] == b["converged"]).all(), b["id"]
        if b["converged"]:
            assert b["spp"] == b["stop_spp"] <= max_spp
    spp = [b["spp"] for b in res.report.get("tiles", res.report["blocks"])]
    assert min(spp) < max_spp and len(set(spp)) > 1, spp
    saved = 1 - sum(spp) / (len(spp) * max_spp)
    assert saved > 0 and res.report["saved_vs_uniform"] == pytest.approx(saved)


def test_render_returns_arrays_and_writes_nothing(flip_result, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = renderer.render("cornell", **{**TINY, "criterion": "variance", "threshold": 0.3})
    assert list(tmp_path.iterdir()) == []                       # in memory: no file anywhere
    for res in (r, flip_result):
        assert res.image.shape == (64, 64, 3) and res.image.dtype == np.float32
        assert res.spp.shape == (64, 64) and res.spp.dtype.kind == "i"
        assert res.converged.shape == (64, 64) and res.converged.dtype == bool
        assert res.report["resolution"] == [64, 64] and len(res.report["blocks"]) == 4
        assert set(np.unique(res.spp)) <= {8, 16, 24, 32}
    assert flip_result.report["criterion"]["name"] == "flip" and r.report["criterion"]["name"] == "variance"
    assert "RenderResult(64x64" in repr(r)
    assert_adaptive(r, TINY["max_spp"])
    assert r.converged.any() and not r.converged.all()


def test_the_adaptive_check_refuses_a_uniform_render():
    """Control: the same call sampling uniformly has the right shapes and spp values, and
    fails assert_adaptive."""
    uniform = renderer.render("cornell", **{**TINY, "criterion": "uniform"})
    assert uniform.spp.shape == (64, 64) and set(np.unique(uniform.spp)) <= {8, 16, 24, 32}
    with pytest.raises(AssertionError):
        assert_adaptive(uniform, TINY["max_spp"])


def test_save_writes_the_command_line_files(flip_result, tmp_path):
    files = flip_result.save(tmp_path / "out")
    assert set(files) == {"final.exr", "final.png", "spp_map.png", "report.json"}
    ch = read_exr_channels(tmp_path / "out" / "final.exr")
    assert np.array_equal(np.stack([ch[c] for c in "RGB"], -1), flip_result.image)
    assert np.array_equal(ch["spp"], flip_result.spp) and np.array_equal(ch["converged"] > 0, flip_result.converged)
    assert json.loads((tmp_path / "out" / "report.json").read_text()) == json.loads(
        json.dumps(flip_result.report))
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match="not a directory"):
        flip_result.save(tmp_path / "file")


def test_render_is_the_command_lines_loop(flip_result, tmp_path):
    """adaptive_render (noisestop render) and render: same stops, same image, same report."""
    report = adaptive_render("cornell", tmp_path, checkpoint_every=0.0,
                             **{k: v for k, v in TINY.items()})
    ch = read_exr_channels(tmp_path / "final.exr")
    assert np.array_equal(np.stack([ch[c] for c in "RGB"], -1), flip_result.image)
    a, b = without_timing(report), without_timing(flip_result.report)
    # the checkpoint interval is the command line's own setting: given here, a default there
    a["settings_source"], b["settings_source"] = dict(a["settings_source"]), dict(b["settings_source"])
    assert (a["settings_source"].pop("checkpoint_every"), b["settings_source"].pop("checkpoint_every")) == \
        ("argument", "default")
    assert a == b
    assert report["render_calls"]["checkpoints"] > 0 and flip_result.report["render_calls"]["checkpoints"] == 0


def test_a_loaded_scene_renders_as_its_name(flip_result):
    import mitsuba as mi

    from renderer.scenes.catalog import scene_dict

    scene = mi.load_dict(scene_dict("cornell", 64))
    r = renderer.render(scene, **{k: v for k, v in TINY.items() if k != "resolution"})
    assert np.array_equal(r.image, flip_result.image) and np.array_equal(r.spp, flip_result.spp)
    assert r.report["scene"] == "scene" and r.report["settings_source"]["resolution"] == "scene"
    with pytest.raises(ValueError, match=r"^resolution cannot be changed on an already-loaded mi.Scene"):
        renderer.render(scene, resolution=32)
    with pytest.raises(ValueError, match=r"^defines \(-D\) set parameters while an XML file loads"):
        renderer.render(scene, defines={"spp": "4"})


@pytest.mark.parametrize("kwargs, message", [
    ({"scene": 42}, "scene must be an mi.Scene, an XML file path or a built-in scene name, got int"),
    ({"criterion": "bogus"}, "criterion must be one of flip, estimate, model, oracle, uniform, variance"),   # + any declared since
    ({"tau": -1.0}, "tau must be a finite number in (0, 1], got -1.0"),
    ({"max_spp": 0}, "max_spp must be a whole number in [1, 1048576], got 0"),
    ({"time_limit": -1.0}, "time_limit must be a finite number in (0, 31536000], got -1.0"),
    ({"scene": "nope"}, "unknown scene 'nope'"),
    ({"criterion": "oracle"}, "the oracle criterion needs true thresholds"),
], ids=["scene-type", "criterion", "tau", "max-spp", "time-limit", "scene-name", "oracle"])
def test_bad_arguments_are_one_line_value_errors(kwargs, message):
    args = {"scene": "cornell", **TINY, **kwargs}
    with pytest.raises(ValueError) as info:
        renderer.render(args.pop("scene"), **args)
    assert message in str(info.value) and "\n" not in str(info.value)


# --- a reference image -------------------------------------------------------------------

def test_a_reference_image_gives_final_vs_reference_without_oracle_figures(tmp_path):
    uniform = {**TINY, "criterion": "uniform"}
    ref = renderer.render("cornell", **uniform)
    write_exr(tmp_path / "ref.exr", ref.image)
    for reference in (tmp_path / "ref.exr", str(tmp_path / "ref.exr"), ref.image):
        r = renderer.render("cornell", reference=reference, **uniform)
        f = r.report["final_vs_reference"]
        assert f["worst_error"] == 0.0 and f["mean_error"] == 0.0 and len(f["errors"]) == 4   # itself
        assert "early_stop_rate" not in r.report and "spp_ratio_vs_oracle" not in r.report
        assert r.report["reference"]["width"] == 64 and "thresholds" not in r.report["reference"]
    noisy = renderer.render("cornell", reference=tmp_path / "ref.exr", **{**TINY, "max_spp": 8})
    f = noisy.report["final_vs_reference"]
    assert 0 < f["mean_error"] <= f["worst_error"] and f["tau"] == 0.02
    assert set(noisy.save(tmp_path / "o")) >= {"compare.png"}


def test_a_reference_image_on_overlapping_windows(tmp_path):
    """80x48 in 32 px blocks: edge windows overlap; each window is pooled on its own."""
    settings = {**TINY, "resolution": "80x48", "criterion": "uniform", "max_spp": 8}
    ref = renderer.render("cornell", **{**settings, "max_spp": 32})
    r = renderer.render("cornell", reference=ref.image, **settings)
    f = r.report["final_vs_reference"]
    assert len(f["errors"]) == 6 and all(e > 0 for e in f["errors"])


def test_a_reference_image_of_another_size_is_refused(tmp_path):
    write_exr(tmp_path / "small.exr", np.zeros((32, 32, 3), np.float32))
    with pytest.raises(ValueError, match=r"^the reference image is 32x32, the render 64x64"):
        renderer.render("cornell", reference=tmp_path / "small.exr", **TINY)
    with pytest.raises(FileNotFoundError, match="missing.exr: reference image not found"):
        renderer.render("cornell", reference=tmp_path / "missing.exr", **TINY)


@pytest.fixture
def _quiet_cli(monkeypatch):
    monkeypatch.setattr(cli, "_setup_logging", lambda verbose, quiet: None)


def test_the_command_line_takes_a_reference_exr(tmp_path, capsys, _quiet_cli):
    ref = renderer.render("cornell", **{**TINY, "criterion": "uniform"})
    write_exr(tmp_path / "ref.exr", ref.image)
    common = ["render", "--scene", "cornell", "--resolution", "64", "--block", "32", "--step", "8",
              "--min-spp", "8", "--max-spp", "16", "--criterion", "uniform"]
    capsys.readouterr()
    assert cli.main([*common, "--out", str(tmp_path / "a"), "--reference", str(tmp_path / "ref.exr"),
                     "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["final_vs_reference"]["worst_error"] > 0
    assert "early_stop_rate" not in report and (tmp_path / "a" / "compare.png").exists()
    write_exr(tmp_path / "small.exr", np.zeros((32, 32, 3), np.float32))
    rc = cli.main([*common, "--out", str(tmp_path / "b"), "--reference", str(tmp_path / "small.exr")])
    err = capsys.readouterr().err
    lines = [line for line in re.split(r"[\r\n]", err) if line.strip() and "%|" not in line]
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert "the reference image is 32x32, the render 64x64" in lines[0]


def test_no_block_the_default_criterion_stops_holds_visible_dots():
    """Dots on black on a live render: `make run`'s dark scene (black background, one spot
    light), the shipped criterion at its defaults, judged against the shipped 8192-spp
    reference: no stopped block holds more than 16 pixels over 0.05 display error (at tau
    0.02), and blocks do stop, the near-black ones among them (else the check says
    nothing)."""
    from examples.showcase import shipped_reference

    ref = shipped_reference("spot_stage")
    r = renderer.render("spot_stage", reference=ref, resolution=256, block=64, step=32, min_spp=32,
                        max_spp=1024, progress=False)
    f = r.report["final_vs_reference"]
    stopped = [b["converged"] for b in r.report["blocks"]]
    assert sum(stopped[:4]) >= 2, stopped              # the black top row stops
    assert f["dotted_stopped_blocks"] == 0 and f["max_stopped_dots"] <= 16, (f["dots"], stopped)
