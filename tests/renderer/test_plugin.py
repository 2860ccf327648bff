"""The `noisestop` Mitsuba integrator: XML and dict forms, mi.render equals renderer.render.

Equality bound: with a box reconstruction filter (every built-in scene) the plugin's
image is bit for bit `renderer.render`'s. With a wider filter (Mitsuba's default
Gaussian) samples are splatted with atomic adds whose order varies between runs on the
JIT variants, so two runs of either route differ by float rounding: measured at most
1.2e-7 absolute on this scene; the test allows 1e-6 * max(1, |value|). Sample counts and
stops are equal in both cases.
"""
from __future__ import annotations

import numpy as np
import pytest

import renderer

pytestmark = pytest.mark.slow

SETTINGS = {"block": 16, "min_spp": 8, "max_spp": 48, "step": 8, "seed": 3}
XML = """<scene version="3.0.0">
  <integrator type="noisestop">
    <float name="tau" value="0.02"/>
    <integer name="block" value="16"/>
    <integer name="min_spp" value="8"/>
    <integer name="max_spp" value="48"/>
    <integer name="step" value="8"/>
    <integer name="seed" value="3"/>
    <string name="criterion" value="flip"/>
    <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  </integrator>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="32"/>
      <rfilter type="{rfilter}"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <shape type="sphere"><point name="center" x="1" y="1" z="0"/><float name="radius" value="0.2"/>
    <emitter type="area"><rgb name="radiance" value="30"/></emitter></shape>
  <emitter type="constant"/>
</scene>
"""


@pytest.fixture(scope="module")
def mi():
    renderer.register()
    import mitsuba

    return mitsuba


def scene_dict(mi, integrator: dict, rfilter: str = "box") -> dict:
    return {"type": "scene", "integrator": integrator,
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 48, "height": 32, "rfilter": {"type": rfilter}}},
            "sphere": {"type": "sphere", "bsdf": {"type": "diffuse"}},
            "light": {"type": "sphere", "center": [1, 1, 0], "radius": 0.2,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 30}}},
            "sky": {"type": "constant"}}


PATH = {"type": "path", "max_depth": 4}


def direct(mi, rfilter: str = "box", **overrides):
    """renderer.render on the same scene with the path tracer itself as its integrator."""
    return renderer.render(mi.load_dict(scene_dict(mi, PATH, rfilter)), progress=False,
                           **{**SETTINGS, **overrides})


def check_channels(img: np.ndarray, want) -> None:
    assert img.shape == (32, 48, 5)
    assert np.array_equal(img[..., 3], want.spp) and np.array_equal(img[..., 4] > 0, want.converged)
    assert set(np.unique(img[..., 4])) <= {0.0, 1.0}


def test_the_xml_form_equals_renderer_render(mi):
    scene = mi.load_string(XML.format(rfilter="box"))
    integrator = scene.integrator()
    assert integrator.aov_names() == ["spp", "converged"]
    img = np.asarray(mi.render(scene))
    want = direct(mi)
    check_channels(img, want)
    assert np.array_equal(img[..., :3], want.image)                  # bit for bit
    assert 0 < want.report["blocks_converged"] < len(want.report["blocks"])   # the loop did stop some
    assert integrator.result.report["blocks"] == want.report["blocks"]
    # renderer.render on a scene whose integrator is the plugin traces with the nested one
    again = renderer.render(scene, progress=False, **SETTINGS)
    assert np.array_equal(again.image, want.image)


def test_the_dict_form_and_mi_render_arguments(mi):
    plugin = {"type": "noisestop", **SETTINGS, "inner": PATH}
    scene = mi.load_dict(scene_dict(mi, plugin))
    img = np.asarray(mi.render(scene))
    check_channels(img, want := direct(mi))
    assert np.array_equal(img[..., :3], want.image)
    # mi.render's seed adds to the property's, its spp is max_spp
    img = np.asarray(mi.render(scene, seed=2, spp=24))
    want = direct(mi, seed=SETTINGS["seed"] + 2, max_spp=24)
    check_channels(img, want)
    assert np.array_equal(img[..., :3], want.image) and img[..., 3].max() <= 24


def test_a_gaussian_filter_equals_up_to_float_rounding(mi):
    plugin = {"type": "noisestop", **SETTINGS, "inner": PATH}
    img = np.asarray(mi.render(mi.load_dict(scene_dict(mi, plugin, "gaussian"))))
    want = direct(mi, "gaussian")
    check_channels(img, want)
    bound = 1e-6 * np.maximum(1.0, np.abs(want.image))
    assert (np.abs(img[..., :3] - want.image) <= bound).all()


def test_defaults_and_bad_properties(mi):
    scene = mi.load_dict(scene_dict(mi, {"type": "noisestop", "max_spp": 16, "min_spp": 8, "step": 8,
                                         "block": 32}))
    assert "PathIntegrator" in str(scene.integrator())            # no nested one: Mitsuba's path
    assert np.asarray(mi.render(scene)).shape == (32, 48, 5)
    bad = [({"bogus": 1}, "bogus"), ({"criterion": "nope"}, "unknown criterion 'nope'"),
           ({"tau": -1.0}, "tau must be a positive finite number"), ({"block": 1.5}, "block must be an integer"),
           ({"criterion": "oracle"}, "cannot use the oracle criterion"),
           ({"min_spp": 0}, "min_spp must be a positive integer"),
           ({"a": PATH, "b": PATH}, "wraps one integrator, got 2")]
    for props, message in bad:
        with pytest.raises(RuntimeError, match=message):
            mi.load_dict(scene_dict(mi, {"type": "noisestop", **props}))


def test_register_is_idempotent(mi):
    assert renderer.register() == renderer.register() == mi.variant()
