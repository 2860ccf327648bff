"""The drifts between the render's doors, each a test that failed before it was fixed: a
model given without a criterion is rendered with, an exposure given as 0 wins over
the scene plugin's, and the time limit and the sample budget have one bound on every door."""
from __future__ import annotations

import pytest

import renderer
from learning.models.bundle import BUNDLED_DIR
from renderer.settings import MAX_TIME_LIMIT
from service.cli import build_parser
from tests.support.errors import assert_one_line_error, run

pytestmark = pytest.mark.slow

TINY = {"progress": False, "block": 16, "step": 4, "min_spp": 4, "max_spp": 8}


def _plugin_scene(**props):
    """Mitsuba's Cornell box at 32x32 whose integrator is the noisestop plugin with `props`."""
    import mitsuba as mi

    renderer.register()
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 32
    d["integrator"] = {"type": "noisestop", "integrator": d["integrator"], **props}
    return mi.load_dict(d)


def test_a_model_given_alone_means_the_model_criterion_on_every_door() -> None:
    """`renderer.render(scene, model=...)` used to render with flip, the model ignored; the
    plugin did the same; the command line already chose the model."""
    r = renderer.render("cornell", resolution=32, model=str(BUNDLED_DIR), **TINY)
    assert r.report["criterion"]["name"] == "model"
    assert r.report["criterion"]["model"]["path"] == str(BUNDLED_DIR)
    assert renderer.render("cornell", resolution=32, offset=0.5, **TINY).report["criterion"]["name"] == "model"
    plugin = renderer.render(_plugin_scene(model=str(BUNDLED_DIR)), **TINY)
    assert plugin.report["criterion"]["name"] == "model"
    assert renderer.render("cornell", resolution=32, **TINY).report["criterion"]["name"] == "flip"   # control
    from renderer.spec import COMMAND_LINE, resolve
    from service.commands.render import given_from_args

    args = build_parser().parse_args(["render", "--out", "o", "--model", str(BUNDLED_DIR)])
    spec = resolve(given_from_args(args), source=COMMAND_LINE)
    assert spec.criterion == "model" and spec.sources["criterion"] == "command line (model)"


def test_an_exposure_given_as_zero_wins_over_the_scene_plugins() -> None:
    """"Arguments given here win": exposure=0.0 used to read as "not given"."""
    scene = _plugin_scene(exposure=2.0, criterion="flip")
    assert renderer.render(scene, **TINY).report["exposure"] == 2.0           # the plugin's, when not given
    assert renderer.render(scene, exposure=0.0, **TINY).report["exposure"] == 0.0


@pytest.mark.parametrize("seconds,ok", [(MAX_TIME_LIMIT, True), (MAX_TIME_LIMIT * 1.01, False), (1e9, False)])
def test_the_time_limit_has_one_bound_on_every_door(capsys, seconds, ok) -> None:
    """The command line took up to 1e9 s, `renderer.render` refused more than a year."""
    parser = build_parser()
    if ok:
        assert parser.parse_args(["render", "--out", "o", "--time-limit", repr(seconds)]).time_limit == seconds
        return
    with pytest.raises(ValueError, match=r"time_limit must be a finite number in \(0, 31536000\]"):
        renderer.render("cornell", resolution=32, time_limit=seconds, **TINY)
    rc, err = run(capsys, "render", "--scene", "cornell", "--out", "o", "--time-limit", repr(seconds))
    assert_one_line_error(rc, err, "--time-limit")
