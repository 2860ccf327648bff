"""Argument types and checks shared by the sub-commands: every documented range
as an argparse type, so a bad value is a one-line usage error before any work.

The choices and ranges come from their one home, in modules that import nothing heavy; frame
and block sizes are also checked against noisefeat.bounds (environment-configurable)."""
from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable

from learning.names import OFFSET_LIMIT, QUICK_MODES
from noisefeat.bounds import EXPOSURE_RANGE
from renderer.settings import MAX_SPP

from ..console import UsageError


MAX_SIDE = 65536
MAX_SEED = 2**32 - 1


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: a whole number in [low, high] (high None: no upper bound)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
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
    """argparse type: a finite number in [low, high] ((low, high] with open_low)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
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
seed = int_in(0, MAX_SEED)
offset = float_in(-OFFSET_LIMIT, OFFSET_LIMIT)
exposure = float_in(*EXPOSURE_RANGE)
fraction = float_in(0.0, 1.0, open_low=True)
rate = float_in(0.0, 1.0)
seconds = float_in(0.0, 3600.0, open_low=True)
threshold = float_in(0.0, 1000.0)
#: the noise target: any positive FLIP value up to 1 parses; the criterion then checks it
#: against the range its calibration covers (flip's c(tau), a model's offsets by tau)
tau = float_in(0.0, 1.0, open_low=True)
TAU_HELP = ("noise target: the largest 16x16-tile mean FLIP against the reference a converged block may "
            "show (smaller is stricter; default %(default)s); picks flip's c(tau) or the model's offset "
            "within their calibrated range")


def check_frame(height: int, width: int, grid: tuple[int, int], what: str) -> None:
    """The frame and block bounds of noisefeat.bounds (environment-configurable), as a usage error."""
    from noisefeat.bounds import SizeBounds
    try:
        SizeBounds.from_env().check_frame(height, width, grid)
    except ValueError as exc:
        raise UsageError(f"{what}: {exc}") from None


_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def resolution(text: str) -> int | tuple[int, int]:
    """`--resolution N|WxH`, each side within the frame bounds' range."""
    from renderer.scenes import parse_resolution

    try:
        value = parse_resolution(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    for side in value if isinstance(value, tuple) else (value,):
        if side > MAX_SIDE:
            raise argparse.ArgumentTypeError(f"a side of {side} px is over the largest, {MAX_SIDE}")
    return value


def define(text: str) -> tuple[str, str]:
    """`-D key=value`: key a name as in an XML scene's <default name=...>, value non-empty."""
    key, sep, value = text.partition("=")
    if not sep or not _DEFINE_KEY.fullmatch(key.strip()) or not value.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE with KEY a parameter name, got {text!r}")
    return key.strip(), value.strip()


def quick_modes(text: str) -> tuple[str, ...]:
    modes = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in modes if m not in QUICK_MODES]
    if not modes or bad or len(set(modes)) != len(modes):
        raise argparse.ArgumentTypeError(
            f"expected distinct quick images from {', '.join(QUICK_MODES)}, comma-separated; got {text!r}")
    return modes


def add_pool_arguments(p: argparse.ArgumentParser, purpose: str) -> None:
    """--workers N | --scheduler ADDRESS: where per-scene tasks run (renderer.farm)."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_in(1, 1024), default=None,
                       help=f"local process workers{purpose} (default: one per core)")
    where.add_argument("--scheduler", default=None,
                       help=f"Dask scheduler address{purpose}, e.g. tcp://host:8786")


def scene_list(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None
