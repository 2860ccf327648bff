"""Built-in scene library and XML loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from renderer.scenes.catalog import DEFAULT_SCENE, SCENES, list_scenes, load_scene, scene_dict
from renderer.settings import ROW


def _render(scene, spp: int = 4, seed: int = 0) -> np.ndarray:
    import mitsuba as mi

    return np.asarray(mi.render(scene, spp=spp, seed=seed))


def test_library_has_at_least_12_described_scenes() -> None:
    listed = list_scenes()
    assert len(listed) >= 12
    assert DEFAULT_SCENE in SCENES
    names = [n for n, _ in listed]
    assert len(set(names)) == len(names)
    for required in ("allblack", "sky", "cornell", "glass_caustic", "indirect", "checker", "mirrors"):
        assert required in names
    for name, desc in listed:
        assert isinstance(desc, str) and 10 < len(desc) < 120 and "\n" not in desc, name


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_dict_uses_shared_render_settings(name: str) -> None:
    d = scene_dict(name, 48)
    assert d["integrator"] == {"type": "path", "max_depth": 8}
    film = d["sensor"]["film"]
    assert (film["width"], film["height"]) == (48, 48)
    assert film["rfilter"] == {"type": "box"}
    assert d["sensor"]["sampler"]["type"] == "independent"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENES))
def test_every_scene_renders_tiny(name: str) -> None:
    img = _render(load_scene(name, 16))
    assert img.shape == (16, 16, 3)
    assert np.isfinite(img).all()
    assert (img >= 0).all()
    if name != "allblack":
        assert img.max() > 0


@pytest.mark.slow
def test_allblack_is_black_and_sky_is_flat() -> None:
    assert np.all(_render(load_scene("allblack", 16), spp=8) == 0)
    sky = _render(load_scene("sky", 16), spp=8)
    np.testing.assert_allclose(sky, 0.5, rtol=1e-5)


def test_unknown_scene_lists_names() -> None:
    with pytest.raises(ValueError, match="unknown scene 'nope'.*cornell"):
        load_scene("nope")
    with pytest.raises(ValueError, match="unknown scene"):
        scene_dict("nope", 16)


def test_bad_resolution_rejected() -> None:
    with pytest.raises(ValueError, match="resolution"):
        scene_dict("cornell", 0)


XML_WITH_DEFAULT = """<scene version="3.0.0">
  <default name="resolution" value="64"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <film type="hdrfilm">
      <integer name="width" value="$resolution"/><integer name="height" value="$resolution"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.25"/></emitter>
</scene>
"""

XML_FIXED = """<scene version="3.0.0">
  <sensor type="perspective">
    <film type="hdrfilm">
      <integer name="width" value="20"/><integer name="height" value="12"/>
      <rfilter type="box"/>
    </film>
  </sensor>
  <emitter type="constant"/>
</scene>
"""


def _film_size(scene) -> tuple[int, int]:
    s = scene.sensors()[0].film().size()
    return int(s[0]), int(s[1])


def test_xml_resolution_parameter_is_used(tmp_path: Path) -> None:
    path = tmp_path / "env.xml"
    path.write_text(XML_WITH_DEFAULT)
    assert _film_size(load_scene(str(path))) == (64, 64)
    scene = load_scene(str(path), 24)
    assert _film_size(scene) == (24, 24)
    np.testing.assert_allclose(_render(scene), 0.25, rtol=1e-5)


def test_xml_film_is_scaled_keeping_its_aspect(tmp_path: Path) -> None:
    path = tmp_path / "fixed.xml"
    path.write_text(XML_FIXED)
    assert _film_size(load_scene(str(path))) == (20, 12)            # its own film by default
    assert _film_size(load_scene(str(path), 32)) == (32, 19)        # long side 32, aspect 5:3 kept
    assert _film_size(load_scene(str(path), (40, 10))) == (40, 10)  # both sides given
    for bad in ("0", "12x", "axb", "1x2x3", "-4x4"):       # text is the resolution row's to read, once
        with pytest.raises(ValueError, match="resolution"):
            ROW["resolution"].check(bad)
    assert ROW["resolution"].check("40x10") == (40, 10)


XML_SPHERE = """<scene version="3.0.0">
  <integrator type="aov"><string name="aovs" value="d:depth"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="24"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><point name="center" x="0.6" y="0.2" z="0"/><float name="radius" value="0.5"/></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="5"/><translate z="-1"/></transform></shape>
</scene>
"""


def test_scaled_film_shows_the_same_view(tmp_path: Path) -> None:
    """Scaling keeps the camera's view: the 2x render, averaged down, is the 1x render."""
    import mitsuba as mi

    path = tmp_path / "sphere.xml"
    path.write_text(XML_SPHERE)
    def sphere(resolution=None, spp=16) -> np.ndarray:       # the sphere's silhouette (depth < 4.6)
        return np.asarray(mi.render(load_scene(str(path), resolution), spp=spp))[..., 0] < 4.6

    small, big = sphere(spp=64), sphere(96)
    assert small.shape == (24, 48) and big.shape == (48, 96) and small.mean() > 0.05
    down = big.reshape(24, 2, 48, 2).mean(axis=(1, 3)) > 0.5
    assert (down != small).mean() < 0.02
    # control: a stretched view (96x24, horizontal field kept) is not the same picture
    wide = sphere((96, 24)).reshape(24, 48, 2).mean(axis=2) > 0.5
    assert (wide != small).mean() > 0.04


def test_xml_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing.xml"):
        load_scene(str(tmp_path / "missing.xml"))
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='no_such_plugin'/></scene>")
    with pytest.raises(ValueError, match="bad.xml"):
        load_scene(str(bad))
    broken = tmp_path / "broken.xml"
    broken.write_text("<scene")
    with pytest.raises(ValueError, match="broken.xml"):
        load_scene(str(broken), 16)


def test_held_out_scenes_are_a_separate_set() -> None:
    train, held = list_scenes(heldout=False), list_scenes(heldout=True)
    assert len(held) == 8 and len(train) == 14 and list_scenes() == train + held
    assert not {n for n, _ in train} & {n for n, _ in held}
    assert all(SCENES[n].heldout for n, _ in held) and not any(SCENES[n].heldout for n, _ in train)


def test_procedural_textures_are_seeded_and_in_range() -> None:
    from renderer.scenes.heldout import marble, studio_environment, wood
    for make in (marble, wood, studio_environment):
        a, b = make(), make()
        assert np.array_equal(a, b) and np.isfinite(a).all() and a.min() >= 0 and a.dtype == np.float32
    assert marble().max() <= 1 and wood().max() <= 1          # reflectances
    assert studio_environment().max() > 1                     # light: soft boxes brighter than the room
