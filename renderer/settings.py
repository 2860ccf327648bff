"""Every setting of a render, one row each (`ROWS`): the one place a setting is defined (the kinds
of rows are `renderer.setting_kinds`). Nothing heavy is imported: the command line builds its
parser from the rows."""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

from learning.names import DEFAULT_TAU, OFFSET_LIMIT
from noisefeat.bounds import EXPOSURE_RANGE

from .setting_kinds import (API, CLI, MAX_SIDE, XML, BlockRow, CriterionRow, DefinesRow, FloatRow, GridRow, IntRow,
                            PathRow, ResolutionRow, Row, TileRow)

#: spp settings are in [1, MAX_SPP]; at most MAX_PASSES passes (each a row of the checkpointed history)
MAX_SPP = 1 << 20
MAX_PASSES = 10_000
#: a year, in seconds: a longer time limit is a typo
MAX_TIME_LIMIT = 365 * 24 * 3600.0
MAX_SEED = 2**32 - 1
#: the block size the bundled model and flip's c(tau) were trained and calibrated on
DEFAULT_BLOCK = 64
#: the observer's tile (its 16x16 tile means): the finest grain its guarantee holds at
DEFAULT_TILE = 16
#: the criterion that measured best on the held-out scenes at <= 5 % early stops (BENCHMARKS.md)
DEFAULT_CRITERION = "flip"


def _spp(name: str, default: int, doc: str) -> IntRow:
    return IntRow(name, default, doc, low=1, high=MAX_SPP)


#: every setting of a render, in the order renderer.render lists them
ROWS: tuple[Row, ...] = (
    CriterionRow("criterion", DEFAULT_CRITERION, "when a unit has converged"),
    FloatRow("tau", DEFAULT_TAU, "noise target: the largest 16x16-tile mean FLIP against the reference a converged "
             "block may show (smaller is stricter); picks flip's c(tau) or the model's offset",
             low=0.0, high=1.0, open_low=True),
    FloatRow("threshold", None, "the level a unit's noise measure must reach", low=0.0, high=1000.0, open_low=True),
    FloatRow("offset", None, "the decision offset, the speed/accuracy knob (default: the model's calibrated offset "
             "at tau; larger stops later)", low=-OFFSET_LIMIT, high=OFFSET_LIMIT),
    FloatRow("quantile", 1.0, "the fraction of a unit's pixels that must pass", low=0.0, high=1.0, open_low=True),
    PathRow("model", None, "a model bundle directory (default: the bundled model)", metavar="DIR"),
    PathRow("server", None, "a verdict server URL, e.g. http://host:8000 (token from NOISESTOP_TOKEN)",
            metavar="URL", doors=frozenset({API, CLI})),
    FloatRow("exposure", 0.0, "display exposure, in stops, the criteria judge the image at",
             low=EXPOSURE_RANGE[0], high=EXPOSURE_RANGE[1]),
    ResolutionRow("resolution", None, "frame size: N scales the film's long side to N keeping its aspect, WxH sets "
                  "both (default: the reference's, else the scene's own)", metavar="N|WxH",
                  doors=frozenset({API, CLI})),
    GridRow("grid", None, "blocks as a (rows, columns) grid dividing the frame, instead of block (default: the "
            "reference's)", doors=frozenset({API, CLI})),
    BlockRow("block", DEFAULT_BLOCK, "block side in pixels (default 64, or the frame's short side if smaller); "
             "edge windows move flush with the frame's edge", low=1, high=MAX_SIDE, metavar="PX"),
    TileRow("tile", DEFAULT_TILE, "side in pixels of the tiles each block is cut into, the unit that stops: each "
            "tile has its own samples and stop, a block is done when all its tiles are; the block's side: whole "
            "blocks", low=8, high=MAX_SIDE, metavar="PX"),
    _spp("min_spp", 16, "samples per pixel before the first decision (default: the reference's first level, else "
         "16); it takes effect at the first pass boundary at or past it"),
    _spp("max_spp", 1024, "most samples per pixel of any block (default: the reference's last level, else 1024)"),
    _spp("step", 16, "samples per pixel a pass adds to each active block (default: the reference's level step, "
         "else 16)"),
    FloatRow("decide_skip", 0.5, "how far a unit's decisions skip towards its predicted stop: a unit r times above "
             "its target is judged again only at (skip r)^2 times its spp (Monte Carlo decay), or the next pass if "
             "that is sooner; 0 judges every pass; flip and variance only, not with a budget (BENCHMARKS, "
             "decisions skipped)", low=0.0, high=1.0),
    FloatRow("decide_growth", 0.0625, "the least a unit's spp grows between two of its decisions, as a fraction of "
             "it: at 1/16 a unit judged at 1024 spp is judged next at 1088 at the earliest, so its stop is found at "
             "most that late; 0 judges every pass; flip and variance only, not with a budget (BENCHMARKS, "
             "decisions skipped)", low=0.0, high=1.0),
    IntRow("seed", 0, "base seed: the samples of (pixel, pass) depend only on it", low=0, high=MAX_SEED),
    FloatRow("time_limit", None, "Seconds: the pass under way when they run out is finished and the render "
             "returns; once the time left cannot cover every active block, passes go to the blocks farthest from "
             "their target", low=0.0, high=MAX_TIME_LIMIT, open_low=True, metavar="S"),
    FloatRow("spp_budget", None, "samples per pixel, averaged over the frame, the render may spend: passes go to "
             "the blocks farthest from their target", low=0.0, high=float(MAX_SPP), open_low=True, metavar="N"),
    _spp("quick_spp", 16, "samples of the quick image a model criterion reads (rendered once)"),
    DefinesRow("defines", None, "an XML scene's <default> parameters, as mitsuba -D KEY=VALUE",
               doors=frozenset({API, CLI}), metavar="KEY=VALUE"),
    FloatRow("checkpoint_every", 30.0, "seconds between checkpoints (also written at the end, at --time-limit and "
             "on Ctrl-C/SIGTERM); 0: after every pass", low=0.0, high=1e9, metavar="S", doors=frozenset({CLI})),
)
ROW = {r.name: r for r in ROWS}
#: the plugin's properties (it adds `progress`: how a render shows, not what it renders)
PLUGIN_ROWS = tuple(r for r in ROWS if XML in r.doors)


def declared_row(criterion: type, name: str) -> Row:
    """Row `name` with the default and range `criterion` (a class) declares for it, if any."""
    row, setting = ROW[name], criterion.settings.get(name)
    if setting is None:
        return row
    declared = {k: getattr(setting, k) for k in ("default", "low", "high")}
    return replace(row, **{k: v for k, v in declared.items() if v is not None})


def declared_values(criterion: type, given: Mapping[str, Any]) -> dict[str, Any]:
    """A criterion constructor's settings (None: not given) checked or defaulted by its `declared_row`s."""
    check_known(given)
    rows = {name: declared_row(criterion, name) for name in given}
    return {name: rows[name].default if value is None else rows[name].check(value) for name, value in given.items()}


def check_known(*layers: Mapping[str, Any] | None) -> None:
    """One-line ValueError for a setting that is no row."""
    unknown = [name for layer in layers for name in sorted(set(layer or {}) - set(ROW))]
    if unknown:
        raise ValueError(f"unknown render setting {unknown[0]!r}; the settings are {', '.join(ROW)}")
