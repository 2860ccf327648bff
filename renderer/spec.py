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

import logging
from collections.abc import Mapping
from dataclasses import field, make_dataclass, replace
from typing import Any

from learning.names import DEFAULT_TAU, OFFSET_LIMIT
from noisefeat.bounds import EXPOSURE_RANGE, SizeBounds

from .names import DEFAULT_CRITERION
from .setting_row import API, CLI, MAX_SIDE, XML, Row, block_bounds, frame_bounds

logger = logging.getLogger(__name__)

#: spp settings are whole numbers in [1, MAX_SPP]; a render makes at most MAX_PASSES passes
#: (each appends a row to the checkpointed history)
MAX_SPP = 1 << 20
MAX_PASSES = 10_000
#: the longest time limit, seconds (a year: anything longer is a typo)
MAX_TIME_LIMIT = 365 * 24 * 3600.0
MAX_SEED = 2**32 - 1
#: the block size the bundled model and flip's c(tau) were trained and calibrated on
DEFAULT_BLOCK = 64
#: the observer's tile (its 16x16 tile means): the finest grain its guarantee holds at
DEFAULT_TILE = 16
#: the criteria whose unit is the paper's block: whole blocks unless a tile is given; the
#: model, given one, gates flip's tile verdicts with its block verdict (criteria.gated),
#: the oracle (a labelled stack's block thresholds) refuses it
BLOCK_GRAIN = ("model", "oracle")
BLOCK_ONLY = ("oracle",)

# where a value came from
ARGUMENT = "argument"
COMMAND_LINE = "command line"
PLUGIN = "scene plugin"
DEFAULT = "default"
SCENE = "scene"
NOT_USED = "not used"

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
        extra=frame_bounds),
    Row("grid", "grid", None, "blocks as a (rows, columns) grid dividing the frame, instead of block "
        "(default: the reference's)", doors=frozenset({API, CLI})),
    Row("block", "int", DEFAULT_BLOCK,
        "block side in pixels (default 64, or the frame's short side if smaller); edge windows move "
        "flush with the frame's edge", low=1, high=MAX_SIDE, metavar="PX", extra=block_bounds),
    Row("tile", "int", DEFAULT_TILE,
        "side in pixels of the tiles each block is cut into, the unit that stops: each tile has its "
        "own samples and stop, a block is done when all its tiles are; the block's side: whole blocks "
        "(the default of the model and oracle criteria; given a smaller tile, the model's block "
        "verdict gates flip's tile verdicts)", low=8, high=MAX_SIDE, metavar="PX"),
    Row("min_spp", doc="samples per pixel before the first decision (default: the reference's first "
        "level, else 16); it takes effect at the first pass boundary at or past it", default=16, **_SPP),
    Row("max_spp", doc="most samples per pixel of any block (default: the reference's last level, "
        "else 1024)", default=1024, **_SPP),
    Row("step", doc="samples per pixel a pass adds to each active block (default: the reference's "
        "level step, else 16)", default=16, **_SPP),
    Row("decide_skip", "float", 0.5,
        "how far a unit's decisions skip towards its predicted stop: a unit r times above its target "
        "is judged again only at (skip r)^2 times its spp (Monte Carlo decay), or the next pass if "
        "that is sooner; 0 judges every pass; flip and variance only, not with a budget (BENCHMARKS, "
        "decisions skipped)", low=0.0, high=1.0),
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

    def tile_grain(self) -> int | None:
        """The tile side when blocks are cut into tiles (tile smaller than the block), else
        None: whole blocks, or a grid whose block size the frame decides, not known yet."""
        side = _block_side(self.block, self.grid, self.resolution)
        return self.tile if side is not None and self.tile < side else None

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


def file_load_settings(given: Mapping[str, Any], reference: Any = None) -> tuple[Any, Any]:
    """(resolution, defines) to load a scene file with, every given row checked first (a bad
    setting fails before the file loads): what loading needs before the file's own
    ``noisestop`` integrator's properties are known; `resolve` takes them after, and checks
    the combination then. Neither row is a plugin property, so neither changes after."""
    _check_known(given)
    checked = {name: ROW[name].check(value) for name, value in given.items() if value is not None}
    resolution = checked.get("resolution")
    if resolution is None and reference is not None:
        resolution = reference_settings(reference)["resolution"]
    return resolution, checked.get("defines")


def _check_known(*layers: Mapping[str, Any] | None) -> None:
    """One-line ValueError for a setting that is no row."""
    unknown = [name for layer in layers for name in sorted(set(layer or {}) - set(ROW))]
    if unknown:
        raise ValueError(f"unknown render setting {unknown[0]!r}; the settings are {', '.join(ROW)}")


def resolve(given: Mapping[str, Any], *, source: str = ARGUMENT, plugin: Mapping[str, Any] | None = None,
            reference: Any = None, thresholds_known: bool | None = None) -> Any:
    """The `RenderSpec` of a render: each row from `given` (None: not given), else the scene
    plugin's properties, else the reference stack's implied settings, else its default;
    each checked once, then the combination. `thresholds_known`: the oracle's true
    thresholds will be there (default: a reference stack is given).
    ValueError (one line, naming the setting) for anything wrong."""
    _check_known(given, plugin)
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
    if _block_grain(crit) and sources["tile"] == DEFAULT:
        values["tile"], sources["tile"] = MAX_SIDE, f"{DEFAULT} (whole blocks: the {getattr(crit, 'name', crit)} criterion)"
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


def _block_side(block: int | None, grid: tuple[int, int] | None, resolution: Any) -> int | None:
    """A block's longer side in pixels: the block size, or a grid's block on a frame of
    (W, H) pixels; None while a grid's frame is not known."""
    if block is not None:
        return block
    if grid is not None and isinstance(resolution, tuple):
        return max(resolution[1] // grid[0], resolution[0] // grid[1])
    return None


def _block_grain(criterion: Any, only: bool = False) -> bool:
    """Whether a criterion judges whole blocks unless told otherwise (`only`: always)."""
    return criterion in (BLOCK_ONLY if only else BLOCK_GRAIN) if isinstance(criterion, str) \
        else not getattr(criterion, "per_tile", True)


def fit_frame(spec: Any, width: int, height: int) -> Any:
    """The spec for the loaded frame: its resolution, a default block no larger than the
    frame's short side, and the frame and block bounds (noisefeat.bounds) checked."""
    values, sources = spec.values(), dict(spec.sources)
    values["resolution"] = (int(width), int(height))
    if spec.block is not None and sources["block"] == DEFAULT and spec.block > min(width, height):
        values["block"] = int(min(width, height))
        sources["block"] = f"{DEFAULT} (the frame's short side)"
    block = values["block"]
    side = _block_side(block, spec.grid, values["resolution"])
    if _block_grain(spec.criterion, only=True) and values["tile"] < side:
        raise ValueError(f"the {getattr(spec.criterion, 'name', spec.criterion)} criterion decides whole blocks: "
                         f"leave tile unset or give the block's side ({side})")
    values["tile"] = min(values["tile"], side)            # a tile is at most its block
    SizeBounds.from_env().check_frame(int(height), int(width), spec.grid or (1, 1),
                                      block=None if spec.grid else (block, block))
    return replace(spec, **values, sources=sources)
