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
    """Unset properties take renderer.render's defaults (flip at tau 0.02, seed 0, exposure
    0): the plugin's channels equal renderer.render's with only the four given settings."""
    given = {"max_spp": 16, "min_spp": 8, "step": 8, "block": 32}
    scene = mi.load_dict(scene_dict(mi, {"type": "noisestop", **given}))
    integrator = scene.integrator()
    assert "PathIntegrator" in str(integrator.nested)            # no nested one: Mitsuba's path
    assert integrator.settings == given
    img = np.asarray(mi.render(scene))
    want = renderer.render(mi.load_dict(scene_dict(mi, PATH)), progress=False, **given)
    check_channels(img, want)
    assert np.array_equal(img[..., :3], want.image)
    assert integrator.result.report["criterion"] == want.report["criterion"]
    assert want.report["criterion"]["name"] == "flip" and want.report["criterion"]["tau"] == 0.02
    assert set(np.unique(want.spp)) <= {8, 16}
    with pytest.raises(RuntimeError, match="bogus"):          # Mitsuba's own check, at load
        mi.load_dict(scene_dict(mi, {"type": "noisestop", "bogus": 1}))
    # ours: one line where the integrator is used (raised while Mitsuba loads, they would
    # come wrapped in a Python traceback)
    bad = [({"criterion": "nope"}, "criterion must be one of .* got 'nope'"),
           ({"tau": -1.0}, r"tau must be a finite number in \(0, 1\]"), ({"block": 1.5}, "block must be a whole number"),
           ({"criterion": "oracle"}, "oracle criterion needs true thresholds"),
           ({"min_spp": 0}, "min_spp must be a whole number"), ({"block": 7}, "block must be at least 8x8"),
           ({"min_spp": 64, "max_spp": 32}, r"min_spp \(64\) is above max_spp \(32\)"),
           ({"a": PATH, "b": PATH}, "wraps one integrator, got 2")]
    for props, message in bad:
        broken = mi.load_dict(scene_dict(mi, {"type": "noisestop", **props}))
        with pytest.raises(ValueError, match=message) as err:
            renderer.render(broken, progress=False)
        assert "\n" not in str(err.value) and str(err.value).startswith("noisestop integrator: ")
        with pytest.raises(RuntimeError) as wrapped:                 # mi.render wraps every integrator's error
            mi.render(broken)
        assert isinstance(wrapped.value.__cause__, ValueError) and str(wrapped.value.__cause__) == str(err.value)


#: every property at a value other than its default (model and offset: with the model criterion)
CHANGED = {"criterion": "variance", "tau": 0.05, "block": 16, "min_spp": 12, "max_spp": 40, "step": 4, "seed": 7,
           "threshold": 0.1, "exposure": 0.5, "progress": True}
MODEL = {"criterion": "model", "offset": 0.25, "progress": True}      # tau: the demo model knows 0.02 only
#: run_adaptive's arguments that both routes pass
LOOP_ARGS = ("block", "step", "min_spp", "max_spp", "seed", "progress", "tau")


def _as_property(value):
    return "nested" if isinstance(value, dict) else value


def what_the_loop_gets(mi, monkeypatch, route) -> dict:
    """The criterion (its report entry and exposure) and settings the loop gets from what
    `route()` hands to run_adaptive, which is stubbed out after the one resolver and the
    one criterion factory: nothing renders."""
    import renderer.live.adaptive
    from renderer.criteria import make_criterion
    from renderer.spec import ARGUMENT, resolve

    seen = {}

    def stub(scene, criterion=None, *, source=ARGUMENT, plugin=None, progress=True, sensor=None,
             integrator=None, reference=None, **given):
        spec = resolve({"criterion": criterion, **given}, source=source, plugin=plugin)
        crit = make_criterion(spec)
        seen.update(criterion=crit.describe(), exposure=getattr(crit, "exposure", None), progress=progress,
                    **{k: getattr(spec, k) for k in LOOP_ARGS if k != "progress"})
        raise _Stop
    with monkeypatch.context() as m:
        m.setattr(renderer.live.adaptive, "run_adaptive", stub)
        with pytest.raises(_Stop):
            route()
    return seen


class _Stop(Exception):
    """Raised by the stub loop once it has seen its arguments."""


def plugin_route(mi, props: dict):
    """The plugin's render as mi.render calls it (called directly: mi.render would wrap the
    stub's exception in Dr.Jit's)."""
    def route():
        scene = mi.load_dict(scene_dict(mi, {"type": "noisestop", **props}))
        return scene.integrator().render(scene, scene.sensors()[0], 0, 0)
    return route


def api_route(mi, props: dict):
    return lambda: renderer.render(mi.load_dict(scene_dict(mi, PATH)), **props)


def ignoring(mi, monkeypatch, key: str) -> None:
    """Make the plugin read `key` (Mitsuba refuses an unread property) and then ignore it:
    the class is built from the properties without it."""
    from renderer import plugin

    cls = plugin.integrator_class()
    init = cls.__init__

    def forgetful(self, props):
        kept = mi.Properties(props.plugin_name())
        for k in props.keys():
            value = props[k]
            if k != key:
                kept[k] = value
        init(self, kept)
    monkeypatch.setattr(cls, "__init__", forgetful)


@pytest.fixture(scope="module")
def demo_model(tmp_path_factory) -> str:
    from tests.support.demo import make_demo_bundle

    return str(make_demo_bundle(tmp_path_factory.mktemp("demo") / "bundle"))


def test_every_property_reaches_the_render(mi, monkeypatch, demo_model):
    """Each property, set away from its default, reaches the loop as renderer.render's
    keyword of the same name does; and, control, a plugin that ignores any one of them
    hands the loop something else."""
    for props in (CHANGED, {**MODEL, "model": demo_model}):
        want = what_the_loop_gets(mi, monkeypatch, api_route(mi, props))
        assert what_the_loop_gets(mi, monkeypatch, plugin_route(mi, props)) == want
        defaults = what_the_loop_gets(mi, monkeypatch, api_route(mi, {"criterion": props["criterion"]}))
        for key in props:
            if key == "criterion":
                continue
            with monkeypatch.context() as m:
                ignoring(mi, m, key)
                got = what_the_loop_gets(mi, monkeypatch, plugin_route(mi, props))
            assert got != want, f"a plugin ignoring {key} passes"
            rest = {"progress": False, **{k: v for k, v in props.items() if k != key}}   # the plugin's one default
            assert got == what_the_loop_gets(mi, monkeypatch, api_route(mi, rest)), key   # of its own
        assert defaults != want
    with monkeypatch.context() as m:                  # the criterion too: flip instead of variance
        ignoring(mi, m, "criterion")
        assert what_the_loop_gets(mi, monkeypatch, plugin_route(mi, CHANGED))["criterion"]["name"] == "flip"


def test_changed_properties_render_as_renderer_render(mi):
    """The same non-default settings, rendered: the plugin's channels are renderer.render's."""
    props = {k: v for k, v in CHANGED.items() if k != "progress"}
    scene = mi.load_dict(scene_dict(mi, {"type": "noisestop", **props}))
    img = np.asarray(mi.render(scene))
    want = direct(mi, **{k: v for k, v in props.items() if k not in SETTINGS or v != SETTINGS[k]})
    check_channels(img, want)
    assert np.array_equal(img[..., :3], want.image)
    assert 0 < want.report["blocks_converged"] < len(want.report["blocks"])
    assert want.report["criterion"]["name"] == "variance" and want.report["criterion"]["threshold"] == 0.1


def registrations(mi, monkeypatch, register, times: int = 3) -> tuple[list[str], list[object]]:
    """Mitsuba registrations made while `register` is called `times` times, and the
    variants it returned (the registrations still reach Mitsuba)."""
    calls: list[str] = []
    real = mi.register_integrator
    with monkeypatch.context() as m:
        m.setattr(mi, "register_integrator", lambda name, factory: (calls.append(name), real(name, factory))[1])
        returned = [register() for _ in range(times)]
    return calls, returned


def test_register_is_idempotent(mi, monkeypatch):
    """Registered once per variant (by the fixture): more calls register nothing and keep
    the one class; control: a register that re-registers on every call is caught."""
    from renderer import plugin

    cls = type(mi.load_dict(scene_dict(mi, {"type": "noisestop"})).integrator())
    assert cls is plugin.integrator_class()
    calls, returned = registrations(mi, monkeypatch, renderer.register)
    assert calls == [] and returned == [mi.variant()] * 3
    assert type(mi.load_dict(scene_dict(mi, {"type": "noisestop"})).integrator()) is cls

    def reregistering() -> str:
        plugin._registered.clear()
        return renderer.register()
    monkeypatch.setattr(plugin, "_registered", set(plugin._registered))
    calls, returned = registrations(mi, monkeypatch, reregistering)
    assert calls == ["noisestop"] * 3 and returned == [mi.variant()] * 3     # same strings: the old test passed


def test_the_docstring_names_every_property() -> None:
    """The module docstring names each property the plugin reads (it once left out ``tile``)."""
    from renderer import plugin
    from renderer.plugin_schema import PROPERTIES

    doc = plugin.__doc__ or ""
    assert [p for p in PROPERTIES if f"``{p}``" not in doc] == []
