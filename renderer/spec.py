"""The render spec: every setting of a render is one row of `ROWS`, and `resolve` is the
one place a setting is defaulted and checked (DESIGN "Render spec").

Why one table: settings used to be defaulted and range-checked in five layers (the API,
the command line's types, the plugin, `run_adaptive`, the budget), and the copies drifted
into bugs. The doors only collect what they were given ("not given" is None):
`renderer.render` and `run_adaptive` (keyword arguments: source ``argument``), ``noisestop
render`` (flags made from the rows, `service.commands.render.add_arguments`: ``command
line``) and the ``noisestop`` Mitsuba integrator (its properties, `PLUGIN_ROWS`: ``scene
plugin``, also under `renderer.render`'s arguments for a scene that has one).

`resolve` takes, for each row, the value given, else the scene plugin's, else what the
reference stack implies, else the row's default, checks it (one-line ValueError naming the
setting), then the combination; `RenderSpec` records where each value came from. This
module imports nothing heavy: the command line builds its parser from it.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, make_dataclass, replace
from typing import Any

import numpy as np

from learning.names import DEFAULT_TAU, OFFSET_LIMIT
from noisefeat.bounds import EXPOSURE_RANGE, SizeBounds

from .names import CRITERIA, DEFAULT_CRITERION

logger = logging.getLogger(__name__)

#: spp settings are whole numbers in [1, MAX_SPP]; a render makes at most MAX_PASSES passes
#: (each appends a row to the checkpointed history)
MAX_SPP = 1 << 20
MAX_PASSES = 10_000
#: the longest time limit, seconds (a year: anything longer is a typo)
MAX_TIME_LIMIT = 365 * 24 * 3600.0
#: the largest frame side and grid count a setting may name (the frame bounds of
#: noisefeat.bounds then cap the pixels)
MAX_SIDE = 65536
MAX_SEED = 2**32 - 1
#: the block size the bundled model and flip's c(tau) were trained and calibrated on
DEFAULT_BLOCK = 64

# where a value came from
ARGUMENT = "argument"
COMMAND_LINE = "command line"
PLUGIN = "scene plugin"
DEFAULT = "default"
SCENE = "scene"
NOT_USED = "not used"

API, CLI, XML = "api", "cli", "plugin"
ALL_DOORS = frozenset({API, CLI, XML})
_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _shown(value: Any) -> str:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool) and abs(int(value)) >= 10**15:
        return f"a {len(str(abs(int(value))))}-digit number"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _num(x: Any) -> str:
    """A bound as written: whole numbers in full (1048576, not 1.04858e+06)."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def parse_resolution(text: Any) -> int | tuple[int, int]:
    """N (the long side; the film's aspect ratio is kept) or 'WxH' / (W, H) (both sides),
    each side in [1, MAX_SIDE]; ValueError with the accepted forms otherwise."""
    value: Any = None
    if isinstance(text, (int, np.integer)) and not isinstance(text, bool):
        value = int(text)
    elif isinstance(text, str):
        try:
            nums = [int(p) for p in text.lower().replace("×", "x").split("x")]
        except ValueError:
            nums = []
        value = None if len(nums) not in (1, 2) else nums[0] if len(nums) == 1 else (nums[0], nums[1])
    elif isinstance(text, Sequence) and len(text) == 2 and all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in text):
        value = (int(text[0]), int(text[1]))
    if value is None:
        raise ValueError(f"resolution must be N (long side, aspect kept) or WxH, e.g. 512 or 1280x720, "
                         f"got {_shown(text)}")
    if any(not 1 <= v <= MAX_SIDE for v in (value if isinstance(value, tuple) else (value,))):
        raise ValueError(f"resolution sides must be whole numbers in [1, {MAX_SIDE}], got {_shown(text)}")
    return value


@dataclass(frozen=True)
class Row:
    """One setting: name, kind, default (None: none, or decided as `doc` says), allowed
    range [low, high] ((low, high] with `open_low`), one line of documentation, and the
    doors that offer it."""

    name: str
    kind: str                  # int, float, str, grid, resolution, defines, criterion
    default: Any
    doc: str
    low: float | None = None
    high: float | None = None
    open_low: bool = False
    doors: frozenset[str] = ALL_DOORS
    metavar: str | None = None
    extra: Callable[[Any], None] | None = None     # a further check (environment-set bounds)

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def range_text(self) -> str:
        return f"{'(' if self.open_low else '['}{_num(self.low)}, {_num(self.high)}]"

    def check(self, value: Any) -> Any:
        """`value` as this row's type, or a one-line ValueError naming the setting."""
        kind, name = self.kind, self.name
        if kind == "int":
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
                    or not self.low <= value <= self.high:    # type: ignore[operator]
                raise ValueError(f"{name} must be a whole number in {self.range_text()}, got {_shown(value)}")
            value = int(value)
        elif kind == "float":
            ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
            if ok:
                v = float(value)
                ok = math.isfinite(v) and self.low <= v <= self.high and not (self.open_low and v == self.low)  # type: ignore[operator]
            if not ok:
                raise ValueError(f"{name} must be a finite number in {self.range_text()}, got {_shown(value)}")
            value = float(value)
        elif kind == "criterion":
            if not isinstance(value, str) and hasattr(value, "decide") and hasattr(value, "describe"):
                return value                    # a Criterion object (renderer.render only)
            if value not in CRITERIA:
                raise ValueError(f"criterion must be one of {', '.join(CRITERIA)} or a Criterion, "
                                 f"got {_shown(value)}")
        elif kind == "str":
            if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
                raise ValueError(f"{name} must be a non-empty path or string, got {_shown(value)}")
            value = os.fspath(value)
        elif kind == "grid":
            if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2 or any(
                    isinstance(g, bool) or not isinstance(g, (int, np.integer)) or not 1 <= g <= MAX_SIDE
                    for g in value):
                raise ValueError(f"grid must be two whole numbers (rows, columns) in [1, {MAX_SIDE}], "
                                 f"got {_shown(value)}")
            value = (int(value[0]), int(value[1]))
        elif kind == "resolution":
            value = parse_resolution(value)
        elif kind == "defines":
            if not isinstance(value, Mapping) or not all(
                    isinstance(k, str) and _DEFINE_KEY.fullmatch(k) and isinstance(v, str) and v.strip()
                    for k, v in value.items()):
                raise ValueError(f"defines must be KEY=VALUE pairs, KEY a parameter name and VALUE not empty, "
                                 f"got {_shown(value)}")
            value = {k: v.strip() for k, v in value.items()}
        if self.extra is not None:
            self.extra(value)
        return value

    def parse(self, text: str) -> Any:
        """Command-line text as this row's value (then `check`, whose message it gives for
        text that is no number at all): argparse's type."""
        value: Any = text
        try:
            if self.kind in ("int", "float"):
                try:
                    value = (int if self.kind == "int" else float)(text)
                except ValueError:
                    pass                    # `check` refuses the text in the row's own words
            elif self.kind == "defines":
                key, sep, val = text.partition("=")
                if not sep:
                    raise ValueError(f"defines must be KEY=VALUE pairs, KEY a parameter name and VALUE not "
                                     f"empty, got {_shown(text)}")
                value = {key.strip(): val}
            return self.check(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None


def _block_bounds(side: int) -> None:
    SizeBounds.from_env().check_block(side, side, what="block")


def _frame_bounds(resolution: int | tuple[int, int]) -> None:
    """A frame asked for must fit the frame bounds before any scene loads (N: N x N at most)."""
    w, h = resolution if isinstance(resolution, tuple) else (resolution, resolution)
    bounds = SizeBounds.from_env()
    if w * h > bounds.max_frame_pixels:
        bounds.check_frame(h, w, (1, 1))     # its one-line message names the bound


_SPP = dict(kind="int", low=1, high=MAX_SPP)
#: every setting of a render, in the order renderer.render lists them
ROWS: tuple[Row, ...] = (
    Row("criterion", "criterion", None,
        "when a block has converged: flip (training-free), model (the learned model), variance "
        "(Cycles' rule), uniform (never: max_spp everywhere) or oracle (a labelled reference stack's "
        "thresholds); not given: model when a model, server or offset is given, else flip"),
    Row("tau", "float", DEFAULT_TAU,
        "noise target: the largest 16x16-tile mean FLIP against the reference a converged block may "
        "show (smaller is stricter); picks flip's c(tau) or the model's offset", low=0.0, high=1.0,
        open_low=True),
    Row("threshold", "float", None,
        "flip: c, the FLIP between the half buffers a block must reach (default c(tau)); variance: "
        "Cycles' noise threshold (default 0.01)", low=0.0, high=1000.0, open_low=True),
    Row("offset", "float", None,
        "model: the decision offset, the speed/accuracy knob (default: the model's calibrated offset "
        "at tau; larger stops later)", low=-OFFSET_LIMIT, high=OFFSET_LIMIT),
    Row("quantile", "float", 1.0, "variance: the fraction of a block's pixels that must pass",
        low=0.0, high=1.0, open_low=True),
    Row("model", "str", None, "model: a model bundle directory (default: the bundled model)",
        metavar="DIR"),
    Row("server", "str", None,
        "model: a verdict server URL, e.g. http://host:8000 (token from NOISESTOP_TOKEN)", metavar="URL",
        doors=frozenset({API, CLI})),
    Row("exposure", "float", 0.0, "display exposure, in stops, the criteria judge the image at",
        low=EXPOSURE_RANGE[0], high=EXPOSURE_RANGE[1]),
    Row("resolution", "resolution", None,
        "frame size: N scales the film's long side to N keeping its aspect, WxH sets both (default: "
        "the reference's, else the scene's own)", metavar="N|WxH", doors=frozenset({API, CLI}),
        extra=_frame_bounds),
    Row("grid", "grid", None, "blocks as a (rows, columns) grid dividing the frame, instead of block "
        "(default: the reference's)", doors=frozenset({API, CLI})),
    Row("block", "int", DEFAULT_BLOCK,
        "block side in pixels (default 64, or the frame's short side if smaller); edge windows move "
        "flush with the frame's edge", low=1, high=MAX_SIDE, metavar="PX", extra=_block_bounds),
    Row("min_spp", doc="samples per pixel before the first decision (default: the reference's first "
        "level, else 16); it takes effect at the first pass boundary at or past it", default=16, **_SPP),
    Row("max_spp", doc="most samples per pixel of any block (default: the reference's last level, "
        "else 1024)", default=1024, **_SPP),
    Row("step", doc="samples per pixel a pass adds to each active block (default: the reference's "
        "level step, else 16)", default=16, **_SPP),
    Row("seed", "int", 0, "base seed: the samples of (pixel, pass) depend only on it", low=0,
        high=MAX_SEED),
    Row("time_limit", "float", None,
        "Seconds: the pass under way when they run out is finished and the render returns; once "
        "the time left cannot cover every active block, passes go to the blocks farthest from "
        "their target", low=0.0, high=MAX_TIME_LIMIT, open_low=True, metavar="S"),
    Row("spp_budget", "float", None,
        "samples per pixel, averaged over the frame, the render may spend: passes go to the blocks "
        "farthest from their target", low=0.0, high=float(MAX_SPP), open_low=True, metavar="N"),
    Row("quick_spp", doc="samples of the quick image a model criterion reads (rendered once)",
        default=16, **_SPP),
    Row("defines", "defines", None, "an XML scene's <default> parameters, as mitsuba -D KEY=VALUE",
        doors=frozenset({API, CLI}), metavar="KEY=VALUE"),
)
ROW = {r.name: r for r in ROWS}
#: the plugin's properties: the rows it offers, plus `progress` (how a render shows, not
#: what it renders)
PLUGIN_ROWS = tuple(r for r in ROWS if XML in r.doors)


class _Spec:
    """Methods of `RenderSpec` (its fields are the rows, made below)."""

    sources: Mapping[str, str]

    def values(self) -> dict[str, Any]:
        return {r.name: getattr(self, r.name) for r in ROWS}

    def describe(self) -> str:
        """One log line: 'resolution 256x256 (scene), block 64 (default), ...'."""
        def fmt(v: Any) -> str:
            if isinstance(v, (list, tuple)):
                return "x".join(str(int(x)) for x in v)
            return f"{v:g}" if isinstance(v, float) else str(v)
        return ", ".join(f"{k} {fmt(getattr(self, k))} ({self.sources[k]})" for k in
                         ("resolution", "grid", "block", "step", "min_spp", "max_spp", "tau", "exposure")
                         if getattr(self, k) is not None)

    def settings_source(self) -> dict[str, str]:
        """report.json ``settings_source``: where every setting in use came from."""
        return {r.name: self.sources[r.name] for r in ROWS
                if getattr(self, r.name) is not None and self.sources[r.name] != NOT_USED}


#: a render's settings, resolved and checked (`resolve`); frozen: nothing downstream changes them
RenderSpec = make_dataclass(
    "RenderSpec", [(r.name, Any) for r in ROWS] + [("sources", Mapping[str, str], field(compare=False))],
    bases=(_Spec,), frozen=True, namespace={"__doc__": "A render's settings: one field per row of ROWS, "
                                            "plus `sources` (where each came from)."})


def reference_settings(stack: Any) -> dict[str, Any]:
    """The settings a reference stack implies (only those it determines)."""
    out: dict[str, Any] = {"grid": tuple(int(g) for g in stack.grid), "max_spp": int(stack.spp[-1]),
                           "min_spp": int(stack.spp[0])}
    out["resolution"] = int(stack.width) if stack.width == stack.height else (int(stack.width), int(stack.height))
    spp = [int(s) for s in stack.spp]
    if all(b - a == spp[0] for a, b in zip([0, *spp[:-1]], spp)):   # spp = step, 2 step, 3 step...
        out["step"] = spp[0]
    return out


def resolve(given: Mapping[str, Any], *, source: str = ARGUMENT, plugin: Mapping[str, Any] | None = None,
            reference: Any = None, thresholds_known: bool | None = None) -> Any:
    """The `RenderSpec` of a render: each row from `given` (None: not given), else the scene
    plugin's properties, else the reference stack's implied settings, else its default;
    each checked once, then the combination. `thresholds_known`: the oracle's true
    thresholds will be there (default: a reference stack is given).
    ValueError (one line, naming the setting) for anything wrong."""
    unknown = sorted(set(given) - set(ROW)) + sorted(set(plugin or {}) - set(ROW))
    if unknown:
        raise ValueError(f"unknown render setting {unknown[0]!r}; the settings are {', '.join(ROW)}")
    ref_source = f"reference {getattr(reference, 'path', '')}".rstrip()
    layers = [(given, source), (plugin or {}, PLUGIN)]
    implied = reference_settings(reference) if reference is not None else {}
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for layer, src in layers:
        for name, value in layer.items():
            if value is not None and name not in values:
                values[name], sources[name] = ROW[name].check(value), src
    # blocks are a grid or a block size: the highest layer that names either decides
    for layer, src in layers:
        named = [k for k in ("grid", "block") if layer.get(k) is not None]
        if len(named) == 2:
            raise ValueError("give the blocks either as a grid (--grid ROWS COLS) or as a block size "
                             "(--block PX), not both")
        if named:
            unused = "block" if named[0] == "grid" else "grid"
            values.pop(unused, None)
            values[unused], sources[unused] = None, NOT_USED
            break
    else:
        if "grid" in implied:
            values["block"], sources["block"] = None, NOT_USED
        else:
            values["grid"], sources["grid"] = None, NOT_USED
    for row in ROWS:
        if row.name in values:
            continue
        if row.name in implied:
            values[row.name], sources[row.name] = implied[row.name], ref_source
        else:
            values[row.name] = row.default
            sources[row.name] = SCENE if row.name == "resolution" else DEFAULT
    _combine(values, sources, [source, PLUGIN, ref_source, DEFAULT],
             reference is not None if thresholds_known is None else thresholds_known)
    return RenderSpec(**values, sources=sources)


def _combine(values: dict[str, Any], sources: dict[str, str], rank: list[str], thresholds_known: bool) -> None:
    """The checks no row can make alone, and the criterion a render uses (on every door:
    a model, server or offset given without a criterion means `model`)."""
    def level(name: str) -> int:
        return rank.index(sources[name]) if sources[name] in rank else len(rank)

    if values["criterion"] is None:
        model_options = [k for k in ("model", "server", "offset") if values[k] is not None]
        values["criterion"] = "model" if model_options else DEFAULT_CRITERION
        sources["criterion"] = sources[model_options[0]] + f" ({model_options[0]})" if model_options else DEFAULT
    if values["model"] is not None and values["server"] is not None:
        raise ValueError("give a model bundle (model) or a verdict server (server), not both")
    crit = values["criterion"]
    if crit == "oracle" and not thresholds_known:
        raise ValueError("the oracle criterion needs true thresholds: give a labelled dataset or stack of "
                         "this scene as the reference (not an image)")
    if isinstance(crit, str):
        for name, users in (("model", "model"), ("server", "model"), ("offset", "model"),
                            ("threshold", "flip variance"), ("quantile", "variance")):
            if values[name] is not None and sources[name] != DEFAULT and crit not in users.split():
                logger.warning("%s is ignored with the %s criterion", name, crit)
    lo, hi = values["min_spp"], values["max_spp"]
    if lo > hi:
        if level("min_spp") == level("max_spp"):
            raise ValueError(f"min_spp ({lo}) is above max_spp ({hi})")
        loser = "min_spp" if level("max_spp") < level("min_spp") else "max_spp"
        values[loser] = hi if loser == "min_spp" else lo   # the one given wins over a default
        sources[loser] += f" (clipped to {'max' if loser == 'min_spp' else 'min'}_spp)"
    passes = -(-values["max_spp"] // values["step"])
    if passes > MAX_PASSES:
        raise ValueError(f"max_spp {values['max_spp']} in steps of {values['step']} is {passes} passes, "
                         f"more than {MAX_PASSES}: take a larger step")
    if values["spp_budget"] is not None and values["spp_budget"] < values["step"]:
        raise ValueError(f"spp_budget {values['spp_budget']:g} cannot buy one pass of {values['step']} "
                         "samples per pixel (the step): give a budget of at least the step, or a smaller step")


def fit_frame(spec: Any, width: int, height: int) -> Any:
    """The spec for the loaded frame: its resolution, a default block no larger than the
    frame's short side, and the frame and block bounds (noisefeat.bounds) checked."""
    values, sources = spec.values(), dict(spec.sources)
    values["resolution"] = (int(width), int(height))
    if spec.block is not None and sources["block"] == DEFAULT and spec.block > min(width, height):
        values["block"] = int(min(width, height))
        sources["block"] = f"{DEFAULT} (the frame's short side)"
    block = values["block"]
    SizeBounds.from_env().check_frame(int(height), int(width), spec.grid or (1, 1),
                                      block=None if spec.grid else (block, block))
    return replace(spec, **values, sources=sources)
