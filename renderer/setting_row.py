"""One setting's row of the render spec (`renderer.spec.ROWS`): its kind, default, range,
documentation and doors, the one check and the one command-line parse of a value, and its
help (`help_text`: the row's documentation with what each criterion declares of it).

Kept apart from the table and the resolver (`renderer.spec`): this is how any row checks a
value; that is which rows there are and how a render's are combined. Nothing heavy is
imported: the command line builds its parser from the rows.
"""
from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from noisefeat.bounds import SizeBounds

from .criteria.registry import TILE, declared
from .criteria.registry import names as criterion_names

#: the largest frame side and grid count a setting may name (the frame bounds of
#: noisefeat.bounds then cap the pixels)
MAX_SIDE = 65536

API, CLI, XML = "api", "cli", "plugin"
ALL_DOORS = frozenset({API, CLI, XML})
_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: a number as a user types it: ASCII digits only (Python's int and float also take `１６`,
#: `٢` and `1_024`, which no one means on a command line; issue 51), spaces around it
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


def parse_resolution(text: Any) -> int | tuple[int, int]:
    """N (the long side; the film's aspect ratio is kept) or 'WxH' / (W, H) (both sides),
    each side in [1, MAX_SIDE]; ValueError with the accepted forms otherwise."""
    value: Any = None
    if isinstance(text, (int, np.integer)) and not isinstance(text, bool):
        value = int(text)
    elif isinstance(text, str):
        try:
            nums = [ascii_int(p) for p in text.lower().replace("×", "x").split("x")]
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
                try:
                    v = float(value)
                except OverflowError:       # an int past float's range (10**400): out of range, not a bug
                    v = math.inf
                ok = math.isfinite(v) and self.low <= v <= self.high and not (self.open_low and v == self.low)  # type: ignore[operator]
            if not ok:
                raise ValueError(f"{name} must be a finite number in {self.range_text()}, got {_shown(value)}")
            value = float(value)
        elif kind == "criterion":
            if not isinstance(value, str) and hasattr(value, "decide") and hasattr(value, "describe"):
                return value                    # a Criterion object (renderer.render only)
            if not isinstance(value, str) or value not in criterion_names():      # the declared ones
                raise ValueError(f"criterion must be one of {', '.join(criterion_names())} or a Criterion, "
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
                    value = (ascii_int if self.kind == "int" else ascii_float)(text)
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


def block_bounds(side: int) -> None:
    """A block side within the block bounds (noisefeat.bounds, environment-configurable)."""
    SizeBounds.from_env().check_block(side, side, what="block")


def frame_bounds(resolution: int | tuple[int, int]) -> None:
    """A frame asked for must fit the frame bounds before any scene loads (N: N x N at most)."""
    w, h = resolution if isinstance(resolution, tuple) else (resolution, resolution)
    bounds = SizeBounds.from_env()
    if w * h > bounds.max_frame_pixels:
        bounds.check_frame(h, w, (1, 1))     # its one-line message names the bound


def help_text(row: Row) -> str:
    """A row's help (the command line's, renderer.render's docstring): its documentation,
    what each criterion that takes it says of it, and its default."""
    text = row.doc
    if row.kind == "criterion":
        text += ": " + "; ".join(f"{name} ({cls.summary})" if cls.summary else name
                                 for name, cls in declared().items())
        selects = {name: [k for k, s in cls.settings.items() if s.selects] for name, cls in declared().items()}
        text += "".join(f"; {name} when {' or '.join(keys)} is given without a criterion"
                        for name, keys in selects.items() if keys)
    elif row.name == "tile":
        blocks = [name for name, cls in declared().items() if cls.grain != TILE]
        text += f" (the default of the {', '.join(blocks)} criteria)" if blocks else ""
    users = {name: cls.settings[row.name] for name, cls in declared().items() if row.name in cls.settings}
    if users:
        text = f"{'/'.join(users)}: {text}"
        for name, setting in users.items():
            said = [setting.doc] if setting.doc else []
            if setting.default is not None:
                said.append(f"default {_default(setting.default)}")
            text += f"; {name}: {', '.join(said)}" if said else ""
    if row.default is not None and "default" not in text:
        text += f" (default {_default(row.default)})"
    return text


def _default(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)
