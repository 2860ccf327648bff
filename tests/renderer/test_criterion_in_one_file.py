"""A criterion is one file: `tests/support/plugin_criterion.py` declares
``halves_gap`` and nothing else in the project knows it, yet importing that file is all it
takes to render with it from all three doors (`renderer.render`, ``noisestop render`` in
process, and an XML scene whose integrator is the ``noisestop`` plugin), with its own
default and range for the threshold, in the help and in the choices; and the three renders
are the same render."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import renderer
from renderer.criteria.registry import names
from renderer.spec import resolve
from service import cli
from tests.support.plugin_criterion import GAP_DEFAULT, GAP_HIGH, HalvesGapCriterion

pytestmark = pytest.mark.slow

SETTINGS = {"block": 16, "min_spp": 8, "max_spp": 48, "step": 8, "seed": 3}
SCENE = """<scene version="3.0.0">
  {integrator}
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="1" y="1" z="0"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="30"/></emitter></shape>
  <emitter type="constant"/>
</scene>
"""
PATH = '<integrator type="path"><integer name="max_depth" value="4"/></integrator>'
PLUGIN = ('<integrator type="noisestop"><string name="criterion" value="halves_gap"/>'
          + "".join(f'<integer name="{k}" value="{v}"/>' for k, v in SETTINGS.items()) + PATH + "</integrator>")


def test_the_declaration_is_what_the_spec_reads() -> None:
    assert "halves_gap" in names()
    spec = resolve({"criterion": "halves_gap"})
    assert spec.threshold == GAP_DEFAULT and spec.sources["threshold"] == "default"    # its own default
    assert resolve({"criterion": "halves_gap", "threshold": GAP_HIGH}).threshold == GAP_HIGH
    with pytest.raises(ValueError, match=rf"threshold must be a finite number in \(0, {GAP_HIGH:g}\]"):
        resolve({"criterion": "halves_gap", "threshold": GAP_HIGH * 2})      # its own range
    assert resolve({"criterion": "flip", "threshold": GAP_HIGH * 2}).threshold == GAP_HIGH * 2   # not flip's
    with pytest.raises(ValueError, match="threshold must be a finite number"):
        HalvesGapCriterion(threshold=GAP_HIGH * 2)                            # the constructor: the same check


def test_a_criterion_declared_in_one_file_renders_from_every_door(tmp_path: Path, capsys) -> None:
    plain, wrapped = tmp_path / "plain.xml", tmp_path / "plugin.xml"
    plain.write_text(SCENE.format(integrator=PATH))
    wrapped.write_text(SCENE.format(integrator=PLUGIN))

    api = renderer.render(str(plain), criterion="halves_gap", progress=False, **SETTINGS)

    with pytest.raises(SystemExit):
        cli.main(["render", "--help"])
    assert "halves_gap (a test's" in " ".join(capsys.readouterr().out.split())      # the help lists it
    argv = ["render", "--scene", str(plain), "--out", str(tmp_path / "cli"), "--criterion", "halves_gap", "--json"]
    for k, v in SETTINGS.items():
        argv += [f"--{k.replace('_', '-')}", str(v)]
    assert cli.main(argv) == 0
    from_cli = json.loads(capsys.readouterr().out)

    import mitsuba as mi

    renderer.register()
    scene = mi.load_file(str(wrapped))
    image = np.asarray(mi.render(scene))
    plugin = scene.integrator().result

    for report in (api.report, from_cli, plugin.report):
        assert report["criterion"] == {"name": "halves_gap", "threshold": GAP_DEFAULT}
        assert report["settings_source"]["threshold"] == "default"
    assert from_cli["settings_source"]["criterion"] == "command line"
    assert plugin.report["settings_source"]["criterion"] == "scene plugin"
    blocks = [b["spp"] for b in api.report["blocks"]]
    assert 0 < api.report["blocks_converged"] < len(blocks) and min(blocks) < SETTINGS["max_spp"]
    assert [b["spp"] for b in from_cli["blocks"]] == blocks == [b["spp"] for b in plugin.report["blocks"]]
    assert np.array_equal(image[..., :3], api.image) and np.array_equal(image[..., 3], api.spp)


def test_a_criterion_not_declared_is_no_choice() -> None:
    """Control: a subclass of a declared criterion without `declare` is not offered."""
    class Undeclared(HalvesGapCriterion):
        name = "undeclared_gap"

    assert "undeclared_gap" not in names()
    with pytest.raises(ValueError, match="criterion must be one of .*halves_gap.* got 'undeclared_gap'"):
        resolve({"criterion": "undeclared_gap"})
