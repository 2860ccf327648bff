"""`render -D key=value` sets an XML scene's <default> parameters,
as `mitsuba -D` does, so a published scene whose default integrator is a plugin Mitsuba
does not have still renders."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from renderer.scenes.catalog import load_scene
from service import cli
from tests.support.errors import assert_one_line_error, run   # the one error contract's checks

# A scene as papers publish them: its default integrator is the paper's own plugin.
XML_FOREIGN_INTEGRATOR = """<scene version="3.0.0">
  <default name="integrator" value="my_paper_integrator"/>
  <default name="light" value="0.25"/>
  <integrator type="$integrator"/>
  <sensor type="perspective">
    <film type="hdrfilm">
      <integer name="width" value="32"/><integer name="height" value="32"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="$light"/></emitter>
</scene>
"""


@pytest.fixture()
def xml(tmp_path: Path) -> Path:
    path = tmp_path / "paper.xml"
    path.write_text(XML_FOREIGN_INTEGRATOR)
    return path


def test_without_d_the_foreign_integrator_is_a_one_line_error(xml, tmp_path, capsys):
    rc, err = run(capsys, "render", "--scene", str(xml), "--out", str(tmp_path / "o"),
                  "--criterion", "uniform", "--max-spp", "16", "--step", "16", "--min-spp", "16")
    assert_one_line_error(rc, err, "my_paper_integrator")


def test_d_sets_the_integrator_and_is_recorded(xml, tmp_path, capsys):
    capsys.readouterr()
    rc = cli.main(["render", "--scene", str(xml), "--out", str(tmp_path / "o"), "--json",
                   "-D", "integrator=path", "-D", "light=0.5", "--criterion", "uniform",
                   "--grid", "2", "2", "--step", "8", "--min-spp", "8", "--max-spp", "16"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    report = json.loads(out.out)
    assert report["defines"] == {"integrator": "path", "light": "0.5"}
    assert report["resolution"] == [32, 32]


def test_d_values_reach_the_scene(xml):
    import mitsuba as mi
    scene = load_scene(str(xml), defines={"integrator": "path", "light": "0.5"})
    image = mi.render(scene, spp=4)
    assert abs(float(mi.TensorXf(image).numpy().mean()) - 0.5) < 1e-4    # the constant sky, as set


@pytest.mark.parametrize("arg", ["integrator", "=path", "integrator=", "bad key=1", "1x=2"])
def test_bad_d_is_a_one_line_usage_error(arg, xml, tmp_path, capsys):
    rc, err = run(capsys, "render", "--scene", str(xml), "--out", str(tmp_path / "o"), "-D", arg)
    assert_one_line_error(rc, err, "KEY=VALUE")


def test_d_on_a_built_in_scene_is_refused(tmp_path, capsys):
    rc, err = run(capsys, "render", "--scene", "cornell", "--out", str(tmp_path / "o"),
                      "-D", "integrator=path", "--criterion", "uniform", "--max-spp", "16")
    assert_one_line_error(rc, err, "built in")


@pytest.mark.parametrize("value", ["-5", "0", "nan", "soon"])
def test_bad_time_limit_is_a_one_line_usage_error(value, tmp_path, capsys):
    rc, err = run(capsys, "render", "--scene", "cornell", "--out", str(tmp_path / "o"), "--time-limit", value)
    assert_one_line_error(rc, err, "--time-limit")


def test_resume_with_other_d_values_is_refused(xml, tmp_path):
    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import UniformCriterion
    kw = dict(grid=(2, 2), step=8, min_spp=8, max_spp=32, progress=False)
    adaptive_render(str(xml), tmp_path / "o", UniformCriterion(), time_limit=1e-6,
                    defines={"integrator": "path", "light": "0.5"}, **kw)
    with pytest.raises(ValueError, match="other settings.*defines"):
        adaptive_render(str(xml), tmp_path / "o", UniformCriterion(), resume=True,
                        defines={"integrator": "path", "light": "0.9"}, **kw)
    done = adaptive_render(str(xml), tmp_path / "o", UniformCriterion(), resume=True,
                           defines={"integrator": "path", "light": "0.5"}, **kw)
    assert done["passes"] == 4
