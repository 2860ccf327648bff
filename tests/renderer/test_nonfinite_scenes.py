"""Non-finite samples never converge: a unit whose pixels have no finite sample
renders to max spp under every criterion, and the render's end says so (stderr, the
summary, report.json, exit status 3)."""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learning.data.accumulator import UnitAccumulator
from renderer.criteria import UnitBatch, UnitView, FlipCriterion, UniformCriterion, VarianceCriterion

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--block", "16", "--step", "4", "--min-spp", "4", "--max-spp", "16"]
CRITERIA = [lambda: FlipCriterion(0.02), lambda: VarianceCriterion(0.01)]


def emitter_scene(tmp_path: Path, value: str) -> Path:
    """A 32x32 frame that sees only a constant emitter of radiance `value`."""
    path = tmp_path / f"emit_{value}.xml"
    path.write_text(f"""<scene version="3.0.0"><integrator type="path"/>
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="32"/>
    <integer name="height" value="32"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="{value}, {value}, {value}"/></emitter>
</scene>""")
    return path


def sphere_scene(tmp_path: Path) -> Path:
    """A grey sky with a sphere of NaN reflectance in the middle (the corners stay clean)."""
    path = tmp_path / "nan_sphere.xml"
    path.write_text("""<scene version="3.0.0"><integrator type="path"/>
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film></sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5, 0.5, 0.5"/></emitter>
  <shape type="sphere"><float name="radius" value="0.7"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="nan, nan, nan"/></bsdf></shape>
</scene>""")
    return path


# ------------------------------------------------------------------- the rule, on the accumulator


def _loop_batch(passes: list[np.ndarray]) -> UnitBatch:
    acc = UnitAccumulator((1, 1), (8, 8))
    for p in passes:
        acc.add(0, p, 4)
    return UnitBatch.from_accumulator(acc, [0])


@pytest.mark.parametrize("make", CRITERIA)
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_block_whose_samples_were_all_dropped_is_never_converged(make, bad):
    """Every pass non-finite: the accumulator's mean is a flat black 0, which the flat test
    used to stop at once."""
    crit = make()
    d = crit.decide([0], _loop_batch([np.full((8, 8, 3), bad)] * 4))
    assert d.verdict.tolist() == [-1] and np.isnan(d.ratio[0])
    assert d.counts["converged"] == 0


@pytest.mark.parametrize("make", CRITERIA)
def test_one_pixel_without_a_finite_sample_holds_the_block(make):
    """A grey block converges (flat); one pixel NaN in every pass (its halves agree on a
    black 0, which no criterion saw as missing) holds it, as does one NaN in every even pass."""
    grey = np.full((8, 8, 3), 0.5)
    assert make().decide([0], _loop_batch([grey] * 4)).verdict.tolist() == [1]
    holed = grey.copy()
    holed[3, 3] = np.nan
    assert make().decide([0], _loop_batch([holed] * 4)).verdict.tolist() == [-1]
    assert make().decide([0], _loop_batch([holed, grey, holed, grey])).verdict.tolist() == [-1]


@pytest.mark.parametrize("make", CRITERIA)
def test_a_pixel_with_some_finite_passes_is_judged_as_usual(make):
    """One NaN pass among finite ones leaves an estimate: the grey block still converges."""
    grey = np.full((8, 8, 3), 0.5)
    holed = grey.copy()
    holed[3, 3] = np.nan
    assert make().decide([0], _loop_batch([holed, grey, grey, grey])).verdict.tolist() == [1]


def test_views_with_non_finite_halves_are_noisy_as_on_the_served_route():
    black = np.zeros((8, 8, 3))
    nan = np.full((8, 8, 3), np.nan)
    views = [UnitView(mean=black, spp=8, halves=(black, black), half_spp=(4, 4)),
             UnitView(mean=black, spp=8, halves=(nan, black), half_spp=(4, 4))]
    for crit in (FlipCriterion(0.02), VarianceCriterion(0.01), UniformCriterion()):
        assert crit.decide([0, 1], views).verdict[1] == -1
    assert FlipCriterion(0.02).decide([0, 1], views).verdict.tolist() == [1, -1]


def test_the_model_criterion_holds_a_block_without_a_finite_sample():
    from learning.models.bundle import load_model
    from renderer.criteria import ModelCriterion

    crit = ModelCriterion(load_model())
    assert crit.decide([0], _loop_batch([np.full((8, 8, 3), np.nan)] * 4)).verdict.tolist() == [-1]


# ------------------------------------------------------------------- whole renders


@pytest.mark.slow
@pytest.mark.parametrize("value", ["nan", "inf", "1e38"])
def test_a_non_finite_emitter_converges_nowhere_and_the_end_says_so(value, tmp_path, capsys, monkeypatch, caplog):
    from service import cli

    monkeypatch.setattr(cli, "_setup_logging", lambda verbose, quiet: None)
    out = tmp_path / "out"
    with caplog.at_level(logging.WARNING):
        rc = cli.main(["render", "--scene", str(emitter_scene(tmp_path, value)), "--out", str(out), *SMALL])
    stdout = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert rc == 3
    assert report["tiles_converged"] == 0 and report["saved_vs_uniform"] == 0.0
    assert all(b["spp"] == 16 for b in report["blocks"])
    nf = report["nonfinite"]
    assert nf["units"] == 4 and nf["pixels"] >= 1000 and nf["dropped"] >= 4000, nf
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "non-finite" in r.getMessage()]
    assert len(warned) == 1 and "no finite sample" in warned[0].getMessage()
    assert "non-finite samples:" in stdout and "never converged" in stdout


@pytest.mark.slow
@pytest.mark.parametrize("criterion", ["flip", "model", "variance"])
def test_a_nan_reflectance_sphere_converges_only_where_pixels_have_estimates(criterion, tmp_path):
    import renderer

    r = renderer.render(str(sphere_scene(tmp_path)), criterion=criterion, block=8, step=4, min_spp=4,
                        max_spp=16, progress=False)
    rep = r.report
    units = rep.get("tiles", rep["blocks"])
    assert rep["nonfinite"]["pixels"] > 0 and rep["nonfinite"]["units"] > 0
    blank = np.all(r.image == 0, axis=-1)                      # pixels with no finite sample
    assert blank.sum() == rep["nonfinite"]["pixels"]
    held = [u for u in units if blank[u["window"][1]:u["window"][1] + u["window"][3],
                                      u["window"][0]:u["window"][0] + u["window"][2]].any()]
    assert len(held) == rep["nonfinite"]["units"] and not any(u["converged"] for u in held)
    assert all(u["spp"] == 16 for u in held)
    clean = [u for u in units if u["nonfinite"] == 0]
    assert clean and all(u["converged"] for u in clean)        # the grey sky still stops


@pytest.mark.slow
def test_the_warning_is_one_stderr_line_and_the_exit_status_3(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run([sys.executable, "-c", "from service.cli import run; run()", "--quiet", "render",
                        "--scene", str(emitter_scene(tmp_path, "nan")), "--out", str(tmp_path / "o"), *SMALL],
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if "non-finite" in ln]
    assert p.returncode == 3, p.stderr
    assert len(lines) == 1 and "WARNING" in lines[0] and "1024 pixel(s) have no finite sample" in lines[0]
