"""Every render-spec row through all three doors: `renderer.render`, `noisestop
render` and the ``noisestop`` Mitsuba plugin. At its bounds a value resolves to the same
spec value on every door; just past them, or of a wrong type, every door gives the same
one-line error naming the setting (the text before ", got", which shows the value as that
door received it). Each door runs its own code up to the one resolver, which is wrapped in
a catch that stops the render there, so no scene is loaded or traced."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import pytest

import renderer
from renderer.setting_kinds import API, CLI, MAX_SIDE, XML
from renderer.settings import MAX_PASSES, MAX_SEED, MAX_SPP, MAX_TIME_LIMIT, ROW, ROWS
from service import cli

pytestmark = pytest.mark.slow


class Resolved(BaseException):
    """Raised by the stand-in factory with the spec a door resolved (not an Exception: no
    door's error handling may swallow it)."""

    def __init__(self, spec: Any) -> None:
        self.spec = spec


@pytest.fixture
def caught(monkeypatch):
    import renderer.live.plan
    from renderer.spec import resolve

    def resolved(*args: Any, **kwargs: Any) -> Any:     # the rows' values, before the frame is fitted
        raise Resolved(resolve(*args, **{**kwargs, "frame": None}))
    monkeypatch.setattr(renderer.live.plan, "resolve", resolved)


#: per row: (values that resolve, values refused). A value is (API value, command-line
#: text, plugin value); None: not offered there. `context`: settings that make the bound a
#: valid render (a max_spp of MAX_SPP needs a step that keeps the passes <= MAX_PASSES).
def _num(low: Any, high: Any, past_low: Any, past_high: Any, wrong: str = "16") -> tuple[list, list]:
    ok = [(v, repr(v), v) for v in (low, high)]
    bad = [(v, repr(v), v) for v in (past_low, past_high)] + [(wrong, "abc", wrong)]
    return ok, bad


CASES: dict[str, tuple[list, list, dict]] = {
    "tau": (*_num(1e-9, 1.0, 0.0, 1.0 + 1e-9), {}),
    "threshold": (*_num(1e-9, 1000.0, 0.0, 1000.5), {}),
    "offset": (*_num(-1e6, 1e6, -1.5e6, 1.5e6), {}),
    "quantile": (*_num(1e-9, 1.0, 0.0, 1.5), {}),
    "exposure": (*_num(-64.0, 64.0, -64.5, 64.5), {}),
    "block": (*_num(8, 2048, 7, 2049), {}),
    "tile": (*_num(8, MAX_SIDE, 7, MAX_SIDE + 1), {}),
    "min_spp": (*_num(1, MAX_SPP, 0, MAX_SPP + 1), {"step": MAX_SPP}),
    "max_spp": (*_num(1, MAX_SPP, 0, MAX_SPP + 1), {"step": MAX_SPP}),
    "step": (*_num(1, MAX_SPP, 0, MAX_SPP + 1), {}),
    "decide_skip": (*_num(0.0, 1.0, -0.1, 1.5), {}),
    "decide_growth": (*_num(0.0, 1.0, -0.1, 1.5), {}),
    "seed": (*_num(0, MAX_SEED, -1, MAX_SEED + 1), {}),
    "time_limit": (*_num(1e-6, MAX_TIME_LIMIT, 0.0, MAX_TIME_LIMIT * 1.01, "5"), {}),
    "spp_budget": (*_num(1.0, float(MAX_SPP), 0.0, MAX_SPP * 2.0, "5"), {"step": 1}),
    "quick_spp": (*_num(1, MAX_SPP, 0, MAX_SPP + 1), {}),
    "criterion": ([("variance", "variance", "variance")], [("magic", "magic", "magic"), (3, None, 3)], {}),
    "model": ([("some/bundle", "some/bundle", "some/bundle")], [("", "", ""), (3, None, 3)], {}),
    "server": ([("http://host:8000", "http://host:8000", None)], [("", "", None), (3, None, None)], {}),
    "resolution": ([(1, "1", None), ((64, 32), "64x32", None)],
                   [(0, "0", None), ((MAX_SIDE + 1, 1), f"{MAX_SIDE + 1}x1", None), ("axb", "axb", None)], {}),
    "grid": ([((1, 1), ["1", "1"], None), ((MAX_SIDE, 1), [str(MAX_SIDE), "1"], None)],
             [((0, 1), ["0", "1"], None), ((MAX_SIDE + 1, 1), [str(MAX_SIDE + 1), "1"], None),
              ("4x4", None, None)], {}),
    "defines": ([({"res": "64"}, "res=64", None)], [({"1a": "x"}, "1a=x", None), ("res=64", None, None)], {}),
    "checkpoint_every": (*_num(0.0, 1e9, -0.5, 1.5e9), {}),
}


def test_every_row_has_its_cases() -> None:
    assert set(CASES) == {r.name for r in ROWS}
    assert MAX_SPP // MAX_SPP <= MAX_PASSES


def _scene(name: str) -> str:
    """What the doors render: cornell, or for `defines` (a scene file's parameters, set as it
    loads, before the resolver) a file that declares `res`."""
    if name != "defines":
        return "cornell"
    path = Path(tempfile.mkdtemp()) / "defines.xml"
    path.write_text(DEFINES_SCENE)
    return str(path)


DEFINES_SCENE = """<scene version="3.0.0">
  <default name="res" value="16"/>
  <sensor type="perspective">
    <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film>
  </sensor>
  <shape type="sphere"/>
</scene>
"""


def _api(name: str, value: Any, context: dict) -> Any:
    settings = {**context, name: value}
    try:
        if API in ROW[name].doors:
            renderer.render(_scene(name), progress=False, **settings)
        else:       # a render into a folder's setting: its Python door is adaptive_render
            renderer.adaptive_render(_scene(name), tempfile.mkdtemp(), progress=False, **settings)
    except Resolved as r:
        return r.spec
    raise AssertionError("renderer.render did not reach the resolver")


def _cli(name: str, text: Any, context: dict, tmp_path: Any, capsys: Any) -> Any:
    row = ROW[name]
    flag = ["-D"] if name == "defines" else [row.flag]
    argv = ["render", "--scene", _scene(name), "--out", str(tmp_path / "o")]
    for k, v in context.items():
        argv += [ROW[k].flag, str(v)]
    argv += flag + (text if isinstance(text, list) else [text])
    capsys.readouterr()
    try:
        rc = cli.main(argv)
    except Resolved as r:
        return r.spec
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def _plugin(name: str, value: Any, context: dict) -> Any:
    import mitsuba as mi

    renderer.register()
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 32
    d["integrator"] = {"type": "noisestop", "integrator": d["integrator"], **context, name: value}
    scene = mi.load_dict(d)
    try:
        scene.integrator().render(scene, 0)
    except Resolved as r:
        return r.spec
    except ValueError as exc:
        return exc
    raise AssertionError("the plugin did not reach the resolver")


def _norm(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v


@pytest.mark.parametrize("name", list(CASES))
def test_a_value_at_the_bounds_resolves_alike_on_every_door(name, caught, tmp_path, capsys) -> None:
    ok, _, context = CASES[name]
    row = ROW[name]
    for api_value, text, plugin_value in ok:
        want = _api(name, api_value, context)
        got = getattr(want, name)
        expected = row.check(api_value)
        assert _norm(got) == _norm(expected) and want.sources[name] == "argument", (name, got)
        if CLI in row.doors and text is not None:
            spec = _cli(name, text, context, tmp_path, capsys)
            assert not isinstance(spec, tuple), spec
            assert _norm(getattr(spec, name)) == _norm(got) and spec.sources[name] == "command line"
        if XML in row.doors and plugin_value is not None:
            spec = _plugin(name, plugin_value, context)
            assert not isinstance(spec, Exception), spec
            assert _norm(getattr(spec, name)) == _norm(got) and spec.sources[name] == "scene plugin"


@pytest.mark.parametrize("name", list(CASES))
def test_a_value_past_the_bounds_or_of_a_wrong_type_is_one_error_on_every_door(name, caught, tmp_path,
                                                                               capsys) -> None:
    _, bad, context = CASES[name]
    row = ROW[name]
    for api_value, text, plugin_value in bad:
        with pytest.raises(ValueError) as api:
            _api(name, api_value, context)
        message = str(api.value)
        assert "\n" not in message and message.startswith(name), message
        head = message.split(", got")[0]
        if CLI in row.doors and text is not None:
            rc, err = _cli(name, text, context, tmp_path, capsys)
            lines = [x for x in err.splitlines() if x.strip()]
            assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
            assert head in lines[0], (head, lines[0])
        if XML in row.doors and plugin_value is not None:
            exc = _plugin(name, plugin_value, context)
            assert isinstance(exc, ValueError), exc
            assert str(exc).startswith("noisestop integrator: ") and head in str(exc), (head, str(exc))


def test_the_doors_documentation_comes_from_the_rows(capsys) -> None:
    """`--help`, renderer.render's docstring and the plugin's properties are the rows'."""
    import inspect

    from renderer.plugin_schema import PROPERTIES

    doc = " ".join((renderer.render.__doc__ or "").split())
    params = inspect.signature(renderer.render).parameters
    with pytest.raises(SystemExit):
        cli.main(["render", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    for row in ROWS:
        if API in row.doors:
            assert row.name in params and params[row.name].default is None, row.name
            assert " ".join(row.doc.split()) in doc, row.name
        if CLI in row.doors:
            assert " ".join(row.doc.split())[:40] in help_text, row.name
    assert set(PROPERTIES) == {r.name for r in ROWS if XML in r.doors} | {"progress"}
    assert math.isfinite(MAX_TIME_LIMIT)
