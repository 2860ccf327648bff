"""Mitsuba XML scenes as users have them: any film size and aspect, Mitsuba's
default Gaussian filter, blocks by size with edge windows, -D for a plugin integrator, the
outputs (per-pixel spp and converged channels, spp heat map), interval checkpoints and a
clean Ctrl-C."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from learning.data.exr import read_exr, read_exr_channels
from renderer.live.adaptive import adaptive_render
from renderer.live.passloop import schedule
from renderer.live.blocks import BlockRenderer
from renderer.criteria import VarianceCriterion
from renderer.scenes.catalog import load_scene
from service import cli
from tests.support.errors import assert_one_line_error, run

# Published scenes mostly leave the reconstruction filter at Mitsuba's default, the
# Gaussian (radius 2 px): no <rfilter> element below.
SCENE = """<scene version="3.0.0">
  <default name="integrator" value="{integrator}"/>
  <integrator type="$integrator"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0.6, 3.5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.6"/></emitter>
  <shape type="sphere"><float name="radius" value="0.6"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.4, 0.2"/></bsdf></shape>
  <shape type="rectangle">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/><translate y="-0.6"/></transform>
    <bsdf type="roughconductor"/>
  </shape>
</scene>
"""
FILMS = {"wide": (96, 54, "path"), "tall": (40, 72, "path"), "paper": (72, 48, "my_paper_integrator")}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("xml")
    out = {}
    for name, (w, h, integrator) in FILMS.items():
        out[name] = root / f"{name}.xml"
        out[name].write_text(SCENE.format(w=w, h=h, integrator=integrator))
    return out


def _render(capsys, *argv: str) -> dict:
    capsys.readouterr()
    rc = cli.main(["-q", "render", "--json", "--criterion", "variance", "--threshold", "0.05",
                   "--step", "8", "--min-spp", "8", "--max-spp", "64", "--block", "32", *argv])
    out = capsys.readouterr()
    assert rc == 0, out.err
    return json.loads(out.out)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(FILMS))
def test_xml_scenes_render_at_their_own_size_and_aspect(scenes, tmp_path, capsys, name):
    w, h, integrator = FILMS[name]
    defines = ["-D", "integrator=path"] if integrator != "path" else []
    r = _render(capsys, "--scene", str(scenes[name]), "--out", str(tmp_path), *defines)
    assert r["resolution"] == [w, h] and r["block"] == [32, 32]
    # windows of 32 px cover the frame; the last row and column sit flush with its edges
    windows = [b["window"] for b in r["blocks"]]
    assert max(x + bw for x, _, bw, _ in windows) == w and max(y + bh for _, y, _, bh in windows) == h
    assert all(bw == bh == 32 for _, _, bw, bh in windows)
    ch = read_exr_channels(tmp_path / "final.exr")
    assert ch["R"].shape == (h, w) and read_exr(tmp_path / "final.exr").shape == (h, w, 3)
    # per-pixel spp: each pixel shows the most samples any window holding it received (the
    # windows that stop: the blocks' 16-pixel tiles)
    units = r["tiles"]
    assert r["tile"] == [16, 16] and len(units) == 4 * len(r["blocks"])
    for u in units:
        x, y, uw, uh = u["window"]
        assert (ch["spp"][y:y + uh, x:x + uw] >= u["spp"]).all()
    assert set(np.unique(ch["spp"])) <= {u["spp"] for u in units}
    assert set(np.unique(ch["converged"])) <= {0.0, 1.0}
    for f in ("final.png", "spp_map.png", "report.json"):
        assert (tmp_path / f).stat().st_size > 0
    assert 0 < r["render_calls"]["mitsuba_calls"] <= r["passes"]       # one call per launch, not per tile
    assert r["render_calls"]["kernel_compiles"] <= 2                    # not one per block


@pytest.mark.slow
def test_resolution_scales_the_long_side_or_sets_both(scenes, tmp_path, capsys):
    r = _render(capsys, "--scene", str(scenes["wide"]), "--out", str(tmp_path / "a"), "--resolution", "64")
    assert r["resolution"] == [64, 36]
    r = _render(capsys, "--scene", str(scenes["wide"]), "--out", str(tmp_path / "b"), "--resolution", "80x40")
    assert r["resolution"] == [80, 40]


@pytest.mark.slow
def test_live_blocks_equal_full_frame_passes_with_a_gaussian_filter(scenes, tmp_path):
    """Blocks that keep sampling after their neighbours stopped are traced alone; with the
    guard band their pixels are still exactly the full-frame estimator's (float rounding)."""
    settings = {"block": 32, "step": 8, "min_spp": 8, "max_spp": 64, "progress": False}
    r = adaptive_render(str(scenes["wide"]), tmp_path, VarianceCriterion(0.1), **settings)
    spp = [b["spp"] for b in r["blocks"]]
    assert 8 < min(spp) < max(spp), spp            # some blocks stopped, others went on alone
    br = BlockRenderer(load_scene(str(scenes["wide"])), block=32)
    assert br.guard == 2
    sizes = np.diff(schedule(8, 64), prepend=0).tolist()
    image = read_exr(tmp_path / "final.exr").astype(np.float64)
    px_spp = read_exr_channels(tmp_path / "final.exr")["spp"]
    total, count = np.zeros_like(image), 0
    for p, n in enumerate(sizes):
        total += br.render_full(n, seed=0, pass_index=p).astype(np.float64) * n
        count += n
        here = px_spp == count
        np.testing.assert_allclose(image[here], (total / count)[here], rtol=2e-5, atol=1e-6)


def test_bad_input_is_one_line(scenes, tmp_path, capsys):
    base = ["render", "--criterion", "uniform", "--max-spp", "8", "--step", "8", "--min-spp", "8"]
    out = ["--out", str(tmp_path / "o")]
    rc, err = run(capsys, *base, *out, "--scene", str(tmp_path / "missing.xml"))
    assert_one_line_error(rc, err, "missing.xml", "not found")
    rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "-D", "integrator")
    assert_one_line_error(rc, err, "KEY=VALUE")
    rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "--block", "64")
    assert_one_line_error(rc, err, "larger than the 96x54 frame")
    rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "--time-limit", "-5")
    assert_one_line_error(rc, err, "--time-limit")
    rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "--block", "4")
    assert_one_line_error(rc, err, "--block")
    for bad in ("0", "64x", "wide", "64x0"):
        rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "--resolution", bad)
        assert_one_line_error(rc, err, "--resolution")
    rc, err = run(capsys, *base, *out, "--scene", str(scenes["wide"]), "--checkpoint-every", "-1")
    assert_one_line_error(rc, err, "--checkpoint-every")


# uniform traces its passes in launches of up to LAUNCH_LANES (8M) lanes: 4 of them, a few seconds
RENDER = ["render", "--scene", "cornell", "--resolution", "64", "--grid", "2", "2", "--criterion", "uniform",
          "--step", "4", "--min-spp", "4", "--max-spp", "8192", "--json", "--checkpoint-every", "1000"]


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "service.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_ctrl_c_finishes_the_pass_checkpoints_and_resume_is_bit_identical(tmp_path):
    """With a long checkpoint interval, only the interrupt writes the checkpoint."""
    ref = _cli("-q", *RENDER, "--out", str(tmp_path / "ref"))
    out, err = ref.communicate(timeout=600)
    assert ref.returncode == 0, err
    proc = _cli(*RENDER, "--out", str(tmp_path / "run"))
    deadline = time.monotonic() + 120
    seen = ""
    while "exposure" not in seen and time.monotonic() < deadline:   # the settings line, just before the loop
        seen += proc.stderr.readline()
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    last = [line for line in err.splitlines() if line.strip()][-1]
    assert "checkpoint written" in last and "--resume" in last and "Traceback" not in err
    assert (tmp_path / "run" / "checkpoint.npz").exists() and not (tmp_path / "run" / "final.exr").exists()
    done = _cli("-q", *RENDER, "--out", str(tmp_path / "run"), "--resume")
    out2, err2 = done.communicate(timeout=600)
    assert done.returncode == 0, err2
    a, b = json.loads(out), json.loads(out2)
    assert b["render_calls"]["checkpoints"] >= 2 and a["passes"] == b["passes"]
    np.testing.assert_array_equal(read_exr(tmp_path / "run" / "final.exr"), read_exr(tmp_path / "ref" / "final.exr"))
