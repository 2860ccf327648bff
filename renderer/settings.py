"""Every setting of a render, each one row (`ROWS`): its name, kind, default, range, one line
of documentation and the doors that offer it. The one place a setting is defined.

A row's kind is its class, as scikit-learn's `Interval` and `StrOptions` are constraints
of their own: `IntRow` and `FloatRow` (a range), `PathRow`, `CriterionRow`, `GridRow`,
`ResolutionRow`, `DefinesRow`, and `BlockRow` and `TileRow` (an int row with more to say).
A row checks a value (`check`: a one-line ValueError naming the setting), reads command-line
text (`parse`, the argparse type), and explains itself (`help_text`: its documentation
with what each criterion declares of it). `renderer.spec.resolve` combines a render's rows;
a criterion takes a row by its declaration (`declared_row`, `declared_values`). Nothing
heavy is imported: the command line builds its parser from the rows.
"""
from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from learning.names import DEFAULT_TAU, OFFSET_LIMIT
from noisefeat.bounds import EXPOSURE_RANGE, SizeBounds

from .criteria.registry import TILE, declared
from .criteria.registry import names as criterion_names

#: the largest frame side and grid count a setting may name (the frame bounds of
#: noisefeat.bounds then cap the pixels)
MAX_SIDE = 65536
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
#: what `noisestop render` and `make run` use unless told: the criterion that measured best
#: on the held-out scenes at <= 5 % early stops (README "Deciding a stop", BENCHMARKS.md)
DEFAULT_CRITERION = "flip"

#: the doors: renderer.render's keywords, the command line's flags, the plugin's properties
API, CLI, XML = "api", "cli", "plugin"
ALL_DOORS = frozenset({API, CLI, XML})
_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: a number as a user types it: ASCII digits only (Python's int and float also take `１６`,
#: `٢` and `1_024`, which no one means on a command line), spaces around it
_ASCII_INT = re.compile(r"[ \t]*[+-]?[0-9]+[ \t]*")
_ASCII_FLOAT = re.compile(r"[ \t]*[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)[ \t]*",
                          re.IGNORECASE)


def ascii_int(text: str) -> int:
    """`int(text)` for ASCII digits only; ValueError otherwise."""
    if not isinstance(text, str) or not _ASCII_INT.fullmatch(text):
        raise ValueError(f"not a whole number in ASCII digits: {text!r}")
    return int(text)


def ascii_float(text: str) -> float:
    """`float(text)` for ASCII digits only (inf and nan are spelled out, for the range
    checks to refuse in their own words); ValueError otherwise."""
    if not isinstance(text, str) or not _ASCII_FLOAT.fullmatch(text):
        raise ValueError(f"not a number in ASCII digits: {text!r}")
    return float(text)


def _shown(value: Any) -> str:
    """A refused value as an error message shows it: short, whatever its size."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool) and abs(int(value)) >= 10**15:
        try:
            return f"a {len(str(abs(int(value))))}-digit number"
        except ValueError:          # str() refuses past 4300 digits
            return f"a number of about {int(abs(int(value)).bit_length() * math.log10(2)) + 1} digits"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _num(x: Any) -> str:
    """A bound as written: whole numbers in full (1048576, not 1.04858e+06)."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _default(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclass(frozen=True)
class Row:
    """One setting: name, default (None: none, or decided as `doc` says), one line of
    documentation, the doors that offer it and its command line's metavar. A subclass is a
    kind of value: how it is checked, read from text and shown in renderer.render's help."""

    name: str
    default: Any
    doc: str
    doors: frozenset[str] = ALL_DOORS
    metavar: str | None = None

    #: the value's type in renderer.render's numpydoc
    type_doc: ClassVar[str] = "object"

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def check(self, value: Any) -> Any:
        """`value` as this row's type, or a one-line ValueError naming the setting."""
        raise NotImplementedError

    def from_text(self, text: str) -> Any:
        """Command-line text as a value for `check` (text it cannot read is left for `check`
        to refuse in the row's own words)."""
        return text

    def parse(self, text: str) -> Any:
        """Command-line text as this row's value, checked: argparse's type."""
        try:
            return self.check(self.from_text(text))
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    def cli_options(self) -> dict[str, Any]:
        """`add_argument`'s keywords for this row's flag (not given: None)."""
        return {"default": None, "type": self.parse, "metavar": self.metavar, "help": self.help_text()}

    def from_cli(self, value: Any) -> Any:
        """What argparse stored for the flag, as the value the door hands on."""
        return value

    def note(self) -> str:
        """What the help adds to `doc` (criteria-dependent text)."""
        return ""

    def help_text(self) -> str:
        """The row's help (the command line's, renderer.render's docstring): its documentation,
        what each criterion that takes it says of it, and its default."""
        text = self.doc + self.note()
        users = {name: cls.settings[self.name] for name, cls in declared().items() if self.name in cls.settings}
        if users:
            text = f"{'/'.join(users)}: {text}"
            for name, setting in users.items():
                said = [setting.doc] if setting.doc else []
                if setting.default is not None:
                    said.append(f"default {_default(setting.default)}")
                text += f"; {name}: {', '.join(said)}" if said else ""
        if self.default is not None and "default" not in text:
            text += f" (default {_default(self.default)})"
        return text


@dataclass(frozen=True, kw_only=True)
class Interval(Row):
    """A number in [low, high] ((low, high] with `open_low`)."""

    low: float
    high: float
    open_low: bool = False

    def range_text(self) -> str:
        return f"{'(' if self.open_low else '['}{_num(self.low)}, {_num(self.high)}]"


@dataclass(frozen=True, kw_only=True)
class IntRow(Interval):
    """A whole number in range."""

    type_doc: ClassVar[str] = "int"

    def check(self, value: Any) -> int:
        if not _is_int(value) or not self.low <= value <= self.high:
            raise ValueError(f"{self.name} must be a whole number in {self.range_text()}, got {_shown(value)}")
        return int(value)

    def from_text(self, text: str) -> Any:
        try:
            return ascii_int(text)
        except ValueError:
            return text


@dataclass(frozen=True, kw_only=True)
class FloatRow(Interval):
    """A finite number in range."""

    type_doc: ClassVar[str] = "float"

    def check(self, value: Any) -> float:
        ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
        if ok:
            try:
                v = float(value)
            except OverflowError:       # an int past float's range (10**400): out of range, not a bug
                v = math.inf
            ok = math.isfinite(v) and self.low <= v <= self.high and not (self.open_low and v == self.low)
        if not ok:
            raise ValueError(f"{self.name} must be a finite number in {self.range_text()}, got {_shown(value)}")
        return float(value)

    def from_text(self, text: str) -> Any:
        try:
            return ascii_float(text)
        except ValueError:
            return text


@dataclass(frozen=True, kw_only=True)
class BlockRow(IntRow):
    """A block side: in range, and within the block bounds (noisefeat.bounds,
    environment-configurable)."""

    def check(self, value: Any) -> int:
        side = super().check(value)
        SizeBounds.from_env().check_block(side, side, what="block")
        return side


@dataclass(frozen=True, kw_only=True)
class TileRow(IntRow):
    """The unit's side: its help names the criteria it defaults to whole blocks for."""

    def note(self) -> str:
        blocks = [name for name, cls in declared().items() if cls.grain != TILE]
        return f" (the default of the {', '.join(blocks)} criteria)" if blocks else ""


@dataclass(frozen=True)
class PathRow(Row):
    """A non-empty path or string."""

    type_doc: ClassVar[str] = "str"

    def check(self, value: Any) -> str:
        if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
            raise ValueError(f"{self.name} must be a non-empty path or string, got {_shown(value)}")
        return os.fspath(value)


@dataclass(frozen=True)
class CriterionRow(Row):
    """A declared criterion's name (`renderer.criteria.registry`), or a Criterion object
    (renderer.render only)."""

    type_doc: ClassVar[str] = "str or Criterion"

    def check(self, value: Any) -> Any:
        if not isinstance(value, str) and hasattr(value, "decide") and hasattr(value, "describe"):
            return value
        if not isinstance(value, str) or value not in criterion_names():
            raise ValueError(f"criterion must be one of {', '.join(criterion_names())} or a Criterion, "
                             f"got {_shown(value)}")
        return value

    def cli_options(self) -> dict[str, Any]:
        return {**super().cli_options(), "metavar": "{" + ",".join(criterion_names()) + "}"}

    def note(self) -> str:
        text = ": " + "; ".join(f"{name} ({cls.summary})" if cls.summary else name
                                for name, cls in declared().items())
        selects = {name: [k for k, s in cls.settings.items() if s.selects] for name, cls in declared().items()}
        return text + "".join(f"; {name} when {' or '.join(keys)} is given without a criterion"
                              for name, keys in selects.items() if keys)


@dataclass(frozen=True)
class GridRow(Row):
    """Blocks as (rows, columns), each in [1, MAX_SIDE]."""

    type_doc: ClassVar[str] = "sequence of two ints"

    def check(self, value: Any) -> tuple[int, int]:
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2 or any(
                not _is_int(g) or not 1 <= g <= MAX_SIDE for g in value):
            raise ValueError(f"grid must be two whole numbers (rows, columns) in [1, {MAX_SIDE}], "
                             f"got {_shown(value)}")
        return int(value[0]), int(value[1])

    def cli_options(self) -> dict[str, Any]:
        return {**super().cli_options(), "type": self.side, "nargs": 2, "metavar": ("ROWS", "COLS")}

    @staticmethod
    def side(text: str) -> int:
        """One of the flag's two numbers (the pair is checked by `check`)."""
        try:
            return ascii_int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"grid must be two whole numbers, got {repr(text[:40])}") from None

    def from_cli(self, value: Any) -> Any:
        return None if value is None else tuple(value)


@dataclass(frozen=True)
class ResolutionRow(Row):
    """N (the long side; the film's aspect ratio is kept) or 'WxH' / (W, H) (both sides),
    each side in [1, MAX_SIDE], within the frame bounds before any scene loads."""

    type_doc: ClassVar[str] = "int or (int, int) or str"

    def check(self, value: Any) -> int | tuple[int, int]:
        size: Any = None
        if _is_int(value):
            size = int(value)
        elif isinstance(value, str):
            try:
                nums = [ascii_int(p) for p in value.lower().replace("×", "x").split("x")]
            except ValueError:
                nums = []
            size = None if len(nums) not in (1, 2) else nums[0] if len(nums) == 1 else (nums[0], nums[1])
        elif isinstance(value, Sequence) and len(value) == 2 and all(_is_int(v) for v in value):
            size = (int(value[0]), int(value[1]))
        if size is None:
            raise ValueError(f"resolution must be N (long side, aspect kept) or WxH, e.g. 512 or 1280x720, "
                             f"got {_shown(value)}")
        if any(not 1 <= v <= MAX_SIDE for v in (size if isinstance(size, tuple) else (size,))):
            raise ValueError(f"resolution sides must be whole numbers in [1, {MAX_SIDE}], got {_shown(value)}")
        w, h = size if isinstance(size, tuple) else (size, size)
        bounds = SizeBounds.from_env()
        if w * h > bounds.max_frame_pixels:
            bounds.check_frame(h, w, (1, 1))     # its one-line message names the bound
        return size


@dataclass(frozen=True)
class DefinesRow(Row):
    """An XML scene's <default> parameters: KEY=VALUE pairs (`-D`, as mitsuba's)."""

    type_doc: ClassVar[str] = "mapping"

    @property
    def flag(self) -> str:
        return "-D"

    def check(self, value: Any) -> dict[str, str]:
        if not isinstance(value, Mapping) or not all(
                isinstance(k, str) and _DEFINE_KEY.fullmatch(k) and isinstance(v, str) and v.strip()
                for k, v in value.items()):
            raise ValueError(f"defines must be KEY=VALUE pairs, KEY a parameter name and VALUE not empty, "
                             f"got {_shown(value)}")
        return {k: v.strip() for k, v in value.items()}

    def from_text(self, text: str) -> Any:
        key, sep, val = text.partition("=")
        if not sep:
            raise ValueError(f"defines must be KEY=VALUE pairs, KEY a parameter name and VALUE not "
                             f"empty, got {_shown(text)}")
        return {key.strip(): val}

    def cli_options(self) -> dict[str, Any]:
        return {**super().cli_options(), "action": "append"}

    def from_cli(self, value: Any) -> Any:
        return None if value is None else {k: v for d in value for k, v in d.items()}


def _spp(name: str, default: int, doc: str) -> IntRow:
    return IntRow(name, default, doc, low=1, high=MAX_SPP)


#: every setting of a render, in the order renderer.render lists them
ROWS: tuple[Row, ...] = (
    # the criteria are their own declarations (`renderer.criteria.registry`): the help lists them
    CriterionRow("criterion", DEFAULT_CRITERION, "when a unit has converged"),
    FloatRow("tau", DEFAULT_TAU,
             "noise target: the largest 16x16-tile mean FLIP against the reference a converged block may "
             "show (smaller is stricter); picks flip's c(tau) or the model's offset", low=0.0, high=1.0,
             open_low=True),
    FloatRow("threshold", None, "the level a unit's noise measure must reach", low=0.0, high=1000.0,
             open_low=True),
    FloatRow("offset", None, "the decision offset, the speed/accuracy knob (default: the model's "
             "calibrated offset at tau; larger stops later)", low=-OFFSET_LIMIT, high=OFFSET_LIMIT),
    FloatRow("quantile", 1.0, "the fraction of a unit's pixels that must pass", low=0.0, high=1.0, open_low=True),
    PathRow("model", None, "a model bundle directory (default: the bundled model)", metavar="DIR"),
    PathRow("server", None, "a verdict server URL, e.g. http://host:8000 (token from NOISESTOP_TOKEN)",
            metavar="URL", doors=frozenset({API, CLI})),
    FloatRow("exposure", 0.0, "display exposure, in stops, the criteria judge the image at",
             low=EXPOSURE_RANGE[0], high=EXPOSURE_RANGE[1]),
    ResolutionRow("resolution", None,
                  "frame size: N scales the film's long side to N keeping its aspect, WxH sets both (default: "
                  "the reference's, else the scene's own)", metavar="N|WxH", doors=frozenset({API, CLI})),
    GridRow("grid", None, "blocks as a (rows, columns) grid dividing the frame, instead of block "
            "(default: the reference's)", doors=frozenset({API, CLI})),
    BlockRow("block", DEFAULT_BLOCK,
             "block side in pixels (default 64, or the frame's short side if smaller); edge windows move "
             "flush with the frame's edge", low=1, high=MAX_SIDE, metavar="PX"),
    TileRow("tile", DEFAULT_TILE,
            "side in pixels of the tiles each block is cut into, the unit that stops: each tile has its "
            "own samples and stop, a block is done when all its tiles are; the block's side: whole blocks",
            low=8, high=MAX_SIDE, metavar="PX"),
    _spp("min_spp", 16, "samples per pixel before the first decision (default: the reference's first "
         "level, else 16); it takes effect at the first pass boundary at or past it"),
    _spp("max_spp", 1024, "most samples per pixel of any block (default: the reference's last level, "
         "else 1024)"),
    _spp("step", 16, "samples per pixel a pass adds to each active block (default: the reference's "
         "level step, else 16)"),
    FloatRow("decide_skip", 0.5,
             "how far a unit's decisions skip towards its predicted stop: a unit r times above its target "
             "is judged again only at (skip r)^2 times its spp (Monte Carlo decay), or the next pass if "
             "that is sooner; 0 judges every pass; flip and variance only, not with a budget (BENCHMARKS, "
             "decisions skipped)", low=0.0, high=1.0),
    FloatRow("decide_growth", 0.0625,
             "the least a unit's spp grows between two of its decisions, as a fraction of it: at 1/16 a unit "
             "judged at 1024 spp is judged next at 1088 at the earliest, so its stop is found at most that "
             "late; 0 judges every pass; flip and variance only, not with a budget (BENCHMARKS, decisions "
             "skipped)", low=0.0, high=1.0),
    IntRow("seed", 0, "base seed: the samples of (pixel, pass) depend only on it", low=0, high=MAX_SEED),
    FloatRow("time_limit", None,
             "Seconds: the pass under way when they run out is finished and the render returns; once "
             "the time left cannot cover every active block, passes go to the blocks farthest from "
             "their target", low=0.0, high=MAX_TIME_LIMIT, open_low=True, metavar="S"),
    FloatRow("spp_budget", None,
             "samples per pixel, averaged over the frame, the render may spend: passes go to the blocks "
             "farthest from their target", low=0.0, high=float(MAX_SPP), open_low=True, metavar="N"),
    _spp("quick_spp", 16, "samples of the quick image a model criterion reads (rendered once)"),
    DefinesRow("defines", None, "an XML scene's <default> parameters, as mitsuba -D KEY=VALUE",
               doors=frozenset({API, CLI}), metavar="KEY=VALUE"),
    # a render into a folder (the command line's; `adaptive_render`'s keyword): how often it checkpoints
    FloatRow("checkpoint_every", 30.0, "seconds between checkpoints (also written at the end, at --time-limit "
             "and on Ctrl-C/SIGTERM); 0: after every pass", low=0.0, high=1e9, metavar="S",
             doors=frozenset({CLI})),
)
ROW = {r.name: r for r in ROWS}
#: the plugin's properties: the rows it offers, plus `progress` (how a render shows, not
#: what it renders)
PLUGIN_ROWS = tuple(r for r in ROWS if XML in r.doors)


def declared_row(criterion: type, name: str) -> Row:
    """Row `name` as `criterion` (a class) takes it: its declared default and range where it
    declares them (`renderer.criteria.registry.Setting`), else the row's."""
    row = ROW[name]
    setting = getattr(criterion, "settings", {}).get(name)
    if setting is None:
        return row
    return replace(row, **{k: v for k, v in (("default", setting.default), ("low", setting.low),
                                             ("high", setting.high)) if v is not None})


def declared_values(criterion: type, given: Mapping[str, Any]) -> dict[str, Any]:
    """The settings `given` to a criterion's constructor (None: not given) by its
    declaration: each checked by its `declared_row`, or that row's default."""
    check_known(given)
    rows = {name: declared_row(criterion, name) for name in given}
    return {name: rows[name].default if value is None else rows[name].check(value) for name, value in given.items()}


def check_known(*layers: Mapping[str, Any] | None) -> None:
    """One-line ValueError for a setting that is no row."""
    unknown = [name for layer in layers for name in sorted(set(layer or {}) - set(ROW))]
    if unknown:
        raise ValueError(f"unknown render setting {unknown[0]!r}; the settings are {', '.join(ROW)}")
