"""A render's front hall (`renderer.live.plan.prepare`): the spec is resolved once per render,
whatever the scene is (a built-in name, a scene file, a loaded ``mi.Scene``), the plugin is
known by its class, and the ``noisestop`` integrator is registered only for a scene file."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import renderer
import renderer.live.plan
import renderer.spec

TINY = {"criterion": "uniform", "resolution": 16, "step": 8, "min_spp": 8, "max_spp": 8, "progress": False}
SCENE = """<scene version="3.0.0">
  {integrator}
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>
"""
PATH = '<integrator type="path"><integer name="max_depth" value="2"/></integrator>'
NOISESTOP = f'<integrator type="noisestop"><integer name="max_spp" value="16"/>{PATH}</integrator>'


@pytest.fixture
def resolutions(monkeypatch) -> list[dict[str, Any]]:
    """Every resolution of a render spec, as the settings given to it (the render's and
    anything else calling the resolver through its module)."""
    calls: list[dict[str, Any]] = []
    real = renderer.spec.resolve

    def counted(given: Any, **kwargs: Any) -> Any:
        calls.append(dict(given))
        return real(given, **kwargs)
    monkeypatch.setattr(renderer.spec, "resolve", counted)
    monkeypatch.setattr(renderer.live.plan, "resolve", counted)
    return calls


def scene_file(tmp_path: Path, integrator: str = PATH) -> Path:
    path = tmp_path / "scene.xml"
    path.write_text(SCENE.format(integrator=integrator))
    return path


def test_a_built_in_scene_resolves_its_spec_once(resolutions) -> None:
    report = renderer.render("cornell", **TINY).report
    assert len(resolutions) == 1 and report["resolution"] == [16, 16]
    assert report["settings_source"]["block"] == "default (the frame's short side)"


def test_a_scene_file_resolves_its_spec_once(resolutions, tmp_path) -> None:
    settings = {k: v for k, v in TINY.items() if k != "resolution"}
    report = renderer.render(str(scene_file(tmp_path)), **settings).report
    assert len(resolutions) == 1 and report["resolution"] == [16, 16]


def test_a_loaded_scene_resolves_its_spec_once(resolutions) -> None:
    import mitsuba as mi

    from learning.data.variant import select_variant

    select_variant()
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 16
    settings = {k: v for k, v in TINY.items() if k != "resolution"}
    report = renderer.render(mi.load_dict(d), **settings).report
    assert len(resolutions) == 1 and report["resolution"] == [16, 16]


def test_a_scene_files_plugin_is_read_once_loaded_and_resolved_with_the_render(monkeypatch, tmp_path) -> None:
    """The file's ``noisestop`` properties join the one resolution of the render (its
    integrator checked its properties itself, when Mitsuba made it: the plugin's door)."""
    calls: list[dict[str, Any]] = []
    real = renderer.live.plan.resolve
    monkeypatch.setattr(renderer.live.plan, "resolve",
                        lambda given, **kw: (calls.append(dict(kw.get("plugin") or {})), real(given, **kw))[1])
    settings = {k: v for k, v in TINY.items() if k not in ("resolution", "max_spp")}
    report = renderer.render(str(scene_file(tmp_path, NOISESTOP)), **settings).report
    assert calls == [{"max_spp": 16}]
    assert report["max_spp"] == 16 and report["settings_source"]["max_spp"] == "scene plugin"


def test_the_integrator_is_registered_only_for_a_scene_file(monkeypatch, tmp_path) -> None:
    import renderer.plugin

    registered: list[int] = []
    real = renderer.plugin.register
    monkeypatch.setattr(renderer.plugin, "register", lambda: (registered.append(1), real())[1])
    renderer.render("cornell", **TINY)
    assert registered == []
    settings = {k: v for k, v in TINY.items() if k != "resolution"}
    renderer.render(str(scene_file(tmp_path)), **settings)
    assert registered == [1]


def test_the_plugin_is_known_by_its_class() -> None:
    import mitsuba as mi

    from renderer.plugin_schema import noisestop_of

    renderer.register()
    plain = mi.load_dict({"type": "path"})
    ours = mi.load_dict({"type": "noisestop", "integrator": {"type": "path"}})
    assert noisestop_of(plain) is None and noisestop_of(None) is None and noisestop_of(ours) is ours


def test_bad_blocks_for_the_frame_are_refused_where_the_spec_meets_it() -> None:
    """The block size and the grid are checked against the loaded frame by the resolver,
    once (the block windows behind it check nothing again)."""
    with pytest.raises(ValueError, match="block of 32 px is larger than the 16x16 frame"):
        renderer.render("cornell", **{**TINY, "block": 32})
    with pytest.raises(ValueError, match="cannot be cut into a 3x3 grid"):
        renderer.render("cornell", **{**TINY, "resolution": 32, "grid": (3, 3)})
