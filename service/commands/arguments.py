"""Argument types and checks shared by the sub-commands: every documented range
as an argparse type, so a bad value is a one-line usage error before any work.

The choices and ranges come from their one home, in modules that import nothing heavy: a
render setting's from its row of the render spec (`renderer.settings.ROWS`, whose `parse` is the
argparse type); frame and block sizes are also checked against noisefeat.bounds
(environment-configurable)."""
from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from learning.names import QUICK_MODES
from renderer.setting_kinds import MAX_SIDE, ascii_float, ascii_int
from renderer.settings import MAX_SPP, ROW

from ..console import UsageError


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: a whole number in [low, high] (high None: no upper bound), in ASCII
    digits (`ascii_int`: `１６` and `1_024` are refused)."""
    def parse(text: str) -> int:
        try:
            value = ascii_int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text[:40]!r}") from None
        if value < low or (high is not None and value > high):
            shown = value if len(str(value)) < 30 else f"a {len(str(value))}-digit number"
            bound = f" and <= {high}" if high is not None else ""
            raise argparse.ArgumentTypeError(f"expected a number >= {low}{bound}, got {shown}")
        return value
    parse.__name__ = "whole number"
    return parse


def float_in(low: float, high: float, *, open_low: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high] ((low, high] with open_low), in ASCII
    digits (`ascii_float`)."""
    def parse(text: str) -> float:
        try:
            value = ascii_float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text[:40]!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text[:40]!r}")
        if value < low or value > high or (open_low and value == low):
            raise argparse.ArgumentTypeError(
                f"expected a number in {'(' if open_low else '['}{low:g}, {high:g}], got {value:g}")
        return value
    parse.__name__ = "number"
    return parse


positive_int = int_in(1)
spp = int_in(1, MAX_SPP)
side = int_in(1, MAX_SIDE)
fraction = float_in(0.0, 1.0, open_low=True)
rate = float_in(0.0, 1.0)
seconds = float_in(0.0, 3600.0, open_low=True)
# the render settings other commands share, parsed and checked by their render-spec rows
seed = ROW["seed"].parse
offset = ROW["offset"].parse
exposure = ROW["exposure"].parse
threshold = ROW["threshold"].parse
tile = ROW["tile"].parse
#: the noise target: any positive FLIP value up to 1 parses; the criterion then checks it
#: against the range its calibration covers (flip's c(tau), a model's offsets by tau)
tau = ROW["tau"].parse
TAU_HELP = ROW["tau"].doc + " (default %(default)s)"


def check_frame(height: int, width: int, grid: tuple[int, int], what: str) -> None:
    """The frame and block bounds of noisefeat.bounds (environment-configurable), as a usage error."""
    from noisefeat.bounds import SizeBounds
    try:
        SizeBounds.from_env().check_frame(height, width, grid)
    except ValueError as exc:
        raise UsageError(f"{what}: {exc}") from None


def quick_modes(text: str) -> tuple[str, ...]:
    modes = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in modes if m not in QUICK_MODES]
    if not modes or bad or len(set(modes)) != len(modes):
        raise argparse.ArgumentTypeError(
            f"expected distinct quick images from {', '.join(QUICK_MODES)}, comma-separated; got {text!r}")
    return modes


def names_from(known: tuple[str, ...], what: str) -> Callable[[str], tuple[str, ...]]:
    """argparse type: comma-separated names from `known` ('' for none). An unknown name is
    a one-line usage error listing the known ones, before any work (`bench --kinds zzz`
    ran for seconds, then failed on something else)."""
    def parse(text: str) -> tuple[str, ...]:
        names = tuple(n.strip() for n in text.split(",") if n.strip())
        bad = [n for n in names if n not in known]
        if bad:
            raise argparse.ArgumentTypeError(f"unknown {what} {', '.join(repr(n[:40]) for n in bad[:5])}; "
                                             f"known: {', '.join(known)}")
        return names
    return parse


def add_pool_arguments(p: argparse.ArgumentParser, purpose: str) -> None:
    """--workers N | --scheduler ADDRESS: where per-scene tasks run (renderer.farm)."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_in(1, 1024), default=None,
                       help=f"local process workers{purpose} (default: one per core)")
    where.add_argument("--scheduler", default=None,
                       help=f"Dask scheduler address{purpose}, e.g. tcp://host:8786")


def scene_list(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None
