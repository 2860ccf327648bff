"""--resolution WxH frames the view as Mitsuba frames that film size under the sensor's fov_axis."""
from __future__ import annotations

import numpy as np
import pytest

from renderer.scenes.catalog import load_scene, scene_dict

XML = """<scene version="3.0.0">
  <default name="axis" value="smaller"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <string name="fov_axis" value="$axis"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/>
      <rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <shape type="cube"><transform name="to_world"><scale value="0.3"/><translate x="1.2" y="0.6"/></transform></shape>
  <emitter type="constant"/>
</scene>
"""


@pytest.fixture(scope="module")
def mi():
    from learning.data.variant import select_variant

    select_variant()
    import mitsuba

    return mitsuba


def render(mi, scene) -> np.ndarray:
    return np.asarray(mi.render(scene, spp=4, seed=1))


@pytest.mark.parametrize("axis", ["smaller", "larger", "x", "y", "diagonal"])
@pytest.mark.parametrize("size", [(64, 40), (40, 64)], ids=["wide", "tall"])
def test_a_resized_film_is_the_view_mitsuba_renders_at_that_size(tmp_path, mi, axis, size):
    path = tmp_path / "scene.xml"
    path.write_text(XML.format(w=64, h=64))
    w, h = size
    ours = render(mi, load_scene(str(path), (w, h), defines={"axis": axis}))
    mitsuba_own = render(mi, mi.load_string(XML.format(w=w, h=h), axis=axis))
    assert ours.shape == mitsuba_own.shape == (h, w, 3)
    assert np.array_equal(ours, mitsuba_own)


def test_smaller_axis_control_keeping_the_horizontal_field_differs(tmp_path, mi):
    """The old framing (horizontal field kept) is not Mitsuba's for fov_axis=smaller."""
    path = tmp_path / "scene.xml"
    path.write_text(XML.format(w=64, h=64))
    kept = load_scene(str(path))
    params = mi.traverse(kept.sensors()[0])
    params["film.size"] = mi.ScalarVector2u(64, 40)
    params["film.crop_size"] = mi.ScalarVector2u(64, 40)
    params.update()
    mitsuba_own = render(mi, mi.load_string(XML.format(w=64, h=40)))
    assert np.abs(render(mi, kept) - mitsuba_own).max() > 0.1


def test_built_in_scenes_frame_as_their_dict_at_that_size(mi):
    d = scene_dict("cornell", 64)                         # fov_axis smaller, as Mitsuba's cbox.xml
    d["sensor"]["film"].update(width=64, height=40)
    assert np.array_equal(render(mi, load_scene("cornell", (64, 40))), render(mi, mi.load_dict(d)))
