"""A ``noisestop`` integrator with two nested integrators and a property: the error names
the real cause (not Mitsuba's "unreferenced property", from the property never read once
the nesting was refused), one line, on every door. Likewise one nested in itself, and a
sensor index out of range."""
from __future__ import annotations

from pathlib import Path

import pytest

import renderer
from tests.support.errors import assert_one_line_error, run

pytestmark = pytest.mark.slow

XML = """<scene version="3.0.0">
  <integrator type="noisestop">
    <float name="tau" value="0.05"/>
    <integer name="max_spp" value="16"/>
    <integrator type="path"/>
    <integrator type="direct"/>
  </integrator>
  <sensor type="perspective">
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere"/>
</scene>
"""
CAUSE = "wraps one integrator, got 2 nested ones"


def test_two_nested_integrators_name_the_real_cause(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    renderer.register()
    import mitsuba as mi

    scene = mi.load_string(XML)             # loads: the error is raised where the integrator is used
    with pytest.raises(ValueError, match=CAUSE):
        renderer.render(scene, progress=False)
    with pytest.raises(RuntimeError) as err:
        mi.render(scene)
    assert CAUSE in str(err.value.__cause__)
    (tmp_path / "two.xml").write_text(XML)
    rc, stderr = run(capsys, "render", "--scene", str(tmp_path / "two.xml"), "--out", str(tmp_path / "out"))
    assert_one_line_error(rc, stderr, CAUSE)


SELF = XML.replace('<integrator type="path"/>\n    <integrator type="direct"/>',
                   '<integrator type="noisestop"><integrator type="path"/></integrator>')
SELF_CAUSE = "cannot wrap another noisestop integrator"


def test_the_plugin_nested_in_itself_is_one_value_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """noisestop wrapping noisestop wrapping path: it was "unexpected RuntimeError ... pure
    virtual function (a bug)" on the command line and a RuntimeError from the API."""
    renderer.register()
    import mitsuba as mi

    scene = mi.load_string(SELF)
    with pytest.raises(ValueError, match=SELF_CAUSE) as info:
        renderer.render(scene, progress=False)
    assert "\n" not in str(info.value)
    (tmp_path / "self.xml").write_text(SELF)
    rc, stderr = run(capsys, "render", "--scene", str(tmp_path / "self.xml"), "--out", str(tmp_path / "out"))
    assert_one_line_error(rc, stderr, SELF_CAUSE)


def test_a_sensor_index_out_of_range_is_one_value_error() -> None:
    """integrator.render(scene, sensor=5) on a one-sensor scene was an IndexError."""
    renderer.register()
    import mitsuba as mi

    scene = mi.load_string(XML.replace('<integrator type="direct"/>', ""))
    for sensor in (5, -1):
        with pytest.raises(ValueError, match=rf"sensor {sensor} is out of range: the scene has 1 sensor\(s\)"):
            scene.integrator().render(scene, sensor=sensor)
