"""A scene file's own ``noisestop`` integrator settings on every door: loading
by path (`renderer.render(PATH)`, `noisestop render --scene PATH`) resolves given > scene
plugin > default exactly as an already-loaded ``mi.Scene`` does, and report.json's
settings_source says "scene plugin". Table-driven: each row a plugin can set, through each
door; then a given value over the plugin's, and a plain scene file as the control."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import pytest

import renderer
from renderer.spec import ARGUMENT, COMMAND_LINE, DEFAULT, PLUGIN
from service import cli

pytestmark = pytest.mark.slow

#: row: (the XML property, its value as set, report.json's value for it)
TABLE: dict[str, tuple[str, Any, Any]] = {
    "criterion": ('<string name="criterion" value="uniform"/>', "uniform", {"name": "uniform"}),
    "max_spp": ('<integer name="max_spp" value="24"/>', 24, 24),
    "tile": ('<integer name="tile" value="8"/>', 8, [8, 8]),
    "tau": ('<float name="tau" value="0.05"/>', 0.05, 0.05),
    "block": ('<integer name="block" value="16"/>', 16, [16, 16]),
    "step": ('<integer name="step" value="8"/>', 8, 8),
}
SCENE = """<scene version="3.0.0">
  {integrator}
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>
"""
NESTED = '<integrator type="path"><integer name="max_depth" value="3"/></integrator>'


def scene_file(tmp_path: Path, plugin: bool = True) -> Path:
    props = "\n    ".join(xml for xml, _, _ in TABLE.values())
    integrator = f'<integrator type="noisestop">\n    {props}\n    {NESTED}\n  </integrator>' if plugin \
        else NESTED
    path = tmp_path / ("plugin.xml" if plugin else "plain.xml")
    path.write_text(SCENE.format(integrator=integrator))
    return path


def api_path(path: Path, tmp_path: Path, **given: Any) -> dict[str, Any]:
    return renderer.render(str(path), progress=False, **given).report


def api_scene(path: Path, tmp_path: Path, **given: Any) -> dict[str, Any]:
    renderer.register()
    import mitsuba as mi

    return renderer.render(mi.load_file(str(path)), progress=False, **given).report


def command_line(path: Path, tmp_path: Path, **given: Any) -> dict[str, Any]:
    flags = [x for k, v in given.items() for x in (f"--{k.replace('_', '-')}", str(v))]
    out = tmp_path / "out"
    rc = cli.main(["render", "--scene", str(path), "--out", str(out), "--json", *flags])
    assert rc == 0
    return json.loads((out / "report.json").read_text())


#: door: (how it renders, the source a given value shows)
DOORS: dict[str, tuple[Callable[..., dict[str, Any]], str]] = {
    "api_path": (api_path, ARGUMENT), "api_scene": (api_scene, ARGUMENT), "command_line": (command_line, COMMAND_LINE),
}


@pytest.mark.parametrize("door", DOORS)
def test_the_scene_files_plugin_settings_count(door: str, tmp_path: Path) -> None:
    report = DOORS[door][0](scene_file(tmp_path), tmp_path)
    for row, (_, _, want) in TABLE.items():
        assert report[row] == want, (door, row, report[row])
        assert report["settings_source"][row] == PLUGIN, (door, row, report["settings_source"])
    assert report["settings_source"]["seed"] == DEFAULT


@pytest.mark.parametrize("door", DOORS)
def test_a_given_setting_wins_over_the_plugins(door: str, tmp_path: Path) -> None:
    render, source = DOORS[door]
    report = render(scene_file(tmp_path), tmp_path, max_spp=16, tile=16)
    assert (report["max_spp"], report["tile"]) == (16, [16, 16])
    assert report["settings_source"]["max_spp"] == report["settings_source"]["tile"] == source
    assert report["criterion"] == {"name": "uniform"} and report["settings_source"]["criterion"] == PLUGIN


def test_a_scene_file_without_the_plugin_takes_the_defaults(tmp_path: Path) -> None:
    report = api_path(scene_file(tmp_path, plugin=False), tmp_path, max_spp=16, block=16)
    assert report["settings_source"]["tau"] == DEFAULT and report["criterion"]["name"] == "flip"
