"""The kinds of a render setting's row (`renderer.settings.ROWS`), one class each: a row checks a
value (`check`), reads command-line text (`parse`) and explains itself (`help_text`). Also the
doors and the ASCII number parsers every door shares."""
from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from noisefeat.bounds import SizeBounds

from .criteria.registry import TILE, Declared, declared
from .criteria.registry import names as criterion_names

#: the largest frame side and grid count a setting may name (noisefeat.bounds caps the pixels)
MAX_SIDE = 65536
#: the doors: renderer.render's keywords, the command line's flags, the plugin's properties
API, CLI, XML = "api", "cli", "plugin"
ALL_DOORS = frozenset({API, CLI, XML})
_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_DEFINES = "defines must be KEY=VALUE pairs, KEY a parameter name and VALUE not empty, got "
#: ASCII digits only: int and float also take `１６`, `٢` and `1_024`, which no one means
_ASCII_INT = re.compile(r"[ \t]*[+-]?[0-9]+[ \t]*")
_ASCII_FLOAT = re.compile(r"[ \t]*[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)[ \t]*",
                          re.IGNORECASE)


def ascii_int(text: str) -> int:
    """`int(text)` for ASCII digits only; ValueError otherwise."""
    if not isinstance(text, str) or not _ASCII_INT.fullmatch(text):
        raise ValueError(f"not a whole number in ASCII digits: {text!r}")
    return int(text)


def ascii_float(text: str) -> float:
    """`float(text)` for ASCII digits only (inf and nan pass: the range checks refuse them); ValueError otherwise."""
    if not isinstance(text, str) or not _ASCII_FLOAT.fullmatch(text):
        raise ValueError(f"not a number in ASCII digits: {text!r}")
    return float(text)


def _shown(value: Any) -> str:
    """A refused value as an error message shows it: short, whatever its size."""
    if _is_int(value) and abs(int(value)) >= 10**15:
        try:
            return f"a {len(str(abs(int(value))))}-digit number"
        except ValueError:          # str() refuses past 4300 digits
            return f"a number of about {int(abs(int(value)).bit_length() * math.log10(2)) + 1} digits"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _num(x: Any) -> str:
    """A bound or default as written: whole numbers in full (1048576, not 1.04858e+06)."""
    if not isinstance(x, (int, float, np.integer, np.floating)) or isinstance(x, bool):
        return str(x)
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclass(frozen=True)
class Row:
    """One setting (default None: none, or decided as `doc` says); a subclass is a kind of value."""

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
        """Command-line text as a value for `check` (unreadable text is left for `check` to refuse)."""
        return text

    def parse(self, text: str) -> Any:
        """argparse's type: command-line text as this row's value, checked."""
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
        """What the help adds to `doc` from the criteria."""
        return ""

    def help_text(self) -> str:
        """The row's help (command line, renderer.render's docstring): doc, the criteria's word, default."""
        text = self.doc + self.note()
        users = {name: cls.settings[self.name] for name, cls in declared().items() if self.name in cls.settings}
        if users:
            text = f"{'/'.join(users)}: {text}"
            for name, setting in users.items():
                said = [setting.doc] if setting.doc else []
                if setting.default is not None:
                    said.append(f"default {_num(setting.default)}")
                text += f"; {name}: {', '.join(said)}" if said else ""
        if self.default is not None and "default" not in text:
            text += f" (default {_num(self.default)})"
        return text


@dataclass(frozen=True, kw_only=True)
class Interval(Row):
    """A number in [low, high] ((low, high] with `open_low`)."""

    low: float
    high: float
    open_low: bool = False

    #: how command-line text becomes a number
    read: ClassVar[Callable[[str], Any]]

    def from_text(self, text: str) -> Any:
        try:
            return self.read(text)
        except ValueError:
            return text

    def range_text(self) -> str:
        return f"{'(' if self.open_low else '['}{_num(self.low)}, {_num(self.high)}]"


@dataclass(frozen=True, kw_only=True)
class IntRow(Interval):
    """A whole number in range."""

    type_doc: ClassVar[str] = "int"
    read = staticmethod(ascii_int)

    def check(self, value: Any) -> int:
        if not _is_int(value) or not self.low <= value <= self.high:
            raise ValueError(f"{self.name} must be a whole number in {self.range_text()}, got {_shown(value)}")
        return int(value)


@dataclass(frozen=True, kw_only=True)
class FloatRow(Interval):
    """A finite number in range."""

    type_doc: ClassVar[str] = "float"
    read = staticmethod(ascii_float)

    def check(self, value: Any) -> float:
        v = math.nan
        if not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating)):
            try:
                v = float(value)
            except OverflowError:       # an int past float's range (10**400): out of range, not a bug
                v = math.inf
        if not (math.isfinite(v) and self.low <= v <= self.high and not (self.open_low and v == self.low)):
            raise ValueError(f"{self.name} must be a finite number in {self.range_text()}, got {_shown(value)}")
        return v


@dataclass(frozen=True, kw_only=True)
class BlockRow(IntRow):
    """A block side, also within noisefeat's block bounds (environment-configurable)."""

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
    """A declared criterion's name, or a Criterion object (renderer.render only)."""

    type_doc: ClassVar[str] = "str or Criterion"

    def check(self, value: Any) -> Any:
        if isinstance(value, Declared) or isinstance(value, str) and value in criterion_names():
            return value
        raise ValueError(f"criterion must be one of {', '.join(criterion_names())} or a Criterion, "
                         f"got {_shown(value)}")

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
    """N (the long side, aspect kept) or 'WxH' / (W, H), within the frame bounds before any scene loads."""

    type_doc: ClassVar[str] = "int or (int, int) or str"

    def check(self, value: Any) -> int | tuple[int, int]:
        sides: list[int] = []       # N, or W and H
        if _is_int(value):
            sides = [int(value)]
        elif isinstance(value, str):
            try:
                sides = [ascii_int(p) for p in value.lower().replace("×", "x").split("x")]
            except ValueError:
                pass
        elif isinstance(value, Sequence) and len(value) == 2 and all(_is_int(v) for v in value):
            sides = [int(v) for v in value]
        if len(sides) not in (1, 2):
            raise ValueError(f"resolution must be N (long side, aspect kept) or WxH, e.g. 512 or 1280x720, "
                             f"got {_shown(value)}")
        if any(not 1 <= v <= MAX_SIDE for v in sides):
            raise ValueError(f"resolution sides must be whole numbers in [1, {MAX_SIDE}], got {_shown(value)}")
        w, h = sides[0], sides[-1]
        bounds = SizeBounds.from_env()
        if w * h > bounds.max_frame_pixels:
            bounds.check_frame(h, w, (1, 1))     # its one-line message names the bound
        return w if len(sides) == 1 else (w, h)


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
            raise ValueError(_DEFINES + _shown(value))
        return {k: v.strip() for k, v in value.items()}

    def from_text(self, text: str) -> Any:
        key, sep, val = text.partition("=")
        if not sep:
            raise ValueError(_DEFINES + _shown(text))
        return {key.strip(): val}

    def cli_options(self) -> dict[str, Any]:
        return {**super().cli_options(), "action": "append"}

    def from_cli(self, value: Any) -> Any:
        return None if value is None else {k: v for d in value for k, v in d.items()}
