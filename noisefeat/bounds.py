"""Size bounds on the images the method is asked about, checked before anything is allocated.

Why: one request of 3.8 MB declaring a [1, 8, 40000, 3] tensor can otherwise take a server
to 23.7 GB (measured). The feature base's cost is linear in the pixels of a block, but a block,
a request and a rendered frame still need a ceiling that is named in the error a caller
gets. The defaults are generous for the method (the paper's blocks are 128 and 200
pixels, renders default to the model's training block) and each can be changed through
the environment; the verdict service also takes them as `serve` options.

* `max_block_side`: the longest side of one block, in pixels (NOISESTOP_MAX_BLOCK_SIDE,
  default 2048). Blocks are at least `MIN_SIDE` (8) pixels a side: the feature base's
  smallest, and what keeps a render from being cut into 1-pixel blocks that the flat rule
  stops at once.
* `max_pixels`: pixels of one request, blocks x height x width (NOISESTOP_MAX_PIXELS,
  default 4 Mi = 16 blocks of 512x512); the service's memory per request follows it.
* `max_frame_pixels`: pixels of one rendered frame (NOISESTOP_MAX_FRAME_PIXELS, default
  16 Mi = 4096x4096); the render loop keeps about 200 bytes a pixel (float64 sums, half
  buffers, checkpoint).
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

#: display exposure, in stops, every entry point accepts (noisefeat.display)
EXPOSURE_RANGE = (-64.0, 64.0)
MIN_SIDE = 8
DEFAULT_MAX_BLOCK_SIDE = 2048
DEFAULT_MAX_PIXELS = 4 * 1024 * 1024
DEFAULT_MAX_FRAME_PIXELS = 16 * 1024 * 1024
ENV = {"max_block_side": "NOISESTOP_MAX_BLOCK_SIDE", "max_pixels": "NOISESTOP_MAX_PIXELS",
       "max_frame_pixels": "NOISESTOP_MAX_FRAME_PIXELS"}


def env_int(environ: Mapping[str, str], key: str, default: int, minimum: int | None = None) -> int:
    """A whole number from the environment (`default` when unset or blank): the one parser of
    every NOISESTOP_* size, budget and cache setting, with the variable named in its error."""
    text = environ.get(key, "").strip()
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{key}={text!r}: expected a whole number") from None
    if minimum is not None and value < minimum:
        raise ValueError(f"{key}={value}: expected a number >= {minimum}")
    return value


def env_seconds(environ: Mapping[str, str], key: str, default: float, most: float, zero: bool = False) -> float:
    """A number of seconds in (0, most] ([0, most] with `zero`) from the environment
    (`default` when unset or blank): the one parser of every NOISESTOP_* time setting."""
    raw = environ.get(key, "")
    if not raw.strip():
        return default
    try:
        value = float(raw)
    except ValueError:
        value = float("nan")
    if not (0 <= value <= most) or (value == 0 and not zero):
        raise ValueError(f"{key} must be a number of seconds in {'[' if zero else '('}0, {most:g}], got {raw!r}")
    return value


@dataclass(frozen=True)
class SizeBounds:
    """The three ceilings above; every check raises ValueError naming the bound it hit."""

    max_block_side: int = DEFAULT_MAX_BLOCK_SIDE
    max_pixels: int = DEFAULT_MAX_PIXELS
    max_frame_pixels: int = DEFAULT_MAX_FRAME_PIXELS

    def __post_init__(self) -> None:
        for name in ENV:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < MIN_SIDE:
                raise ValueError(f"{name} must be a whole number >= {MIN_SIDE}, got {value!r}")

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **given: int | None) -> "SizeBounds":
        """Explicit values win over the environment, which wins over the defaults."""
        environ = os.environ if environ is None else environ
        values = {name: given[name] if given.get(name) is not None
                  else env_int(environ, key, getattr(cls, name)) for name, key in ENV.items()}
        unknown = set(given) - set(ENV)
        if unknown:
            raise TypeError(f"unknown bounds {sorted(unknown)}")
        return cls(**values)

    def check_block(self, height: int, width: int, what: str = "blocks") -> None:
        """MIN_SIDE <= each side <= max_block_side."""
        if min(height, width) < MIN_SIDE:
            raise ValueError(f"{what} must be at least {MIN_SIDE}x{MIN_SIDE} pixels, got {height}x{width}")
        if max(height, width) > self.max_block_side:
            raise ValueError(f"{what} of {height}x{width} pixels exceed the largest block side, "
                             f"max_block_side = {self.max_block_side} ({ENV['max_block_side']})")

    def check_request(self, n: int, height: int, width: int) -> None:
        """One request of n blocks of height x width: block sides, then the pixel budget."""
        self.check_block(height, width)
        pixels = n * height * width
        if pixels > self.max_pixels:
            raise ValueError(f"{n} blocks of {height}x{width} are {pixels} pixels, over the pixel "
                             f"budget of a request, max_pixels = {self.max_pixels} ({ENV['max_pixels']})")

    def check_frame(self, height: int, width: int, grid: tuple[int, int],
                    block: tuple[int, int] | None = None) -> None:
        """A rendered frame and its blocks: the frame's pixels, and the blocks of `grid`
        (or, when given, the `block` windows (height, width) it is cut into)."""
        if height < 1 or width < 1:
            raise ValueError(f"frame must be at least 1x1 pixels, got {width}x{height}")
        if height * width > self.max_frame_pixels:
            raise ValueError(f"a {width}x{height} frame is {width * height} pixels, over the largest "
                             f"frame, max_frame_pixels = {self.max_frame_pixels} "
                             f"({ENV['max_frame_pixels']})")
        if block is not None:
            self.check_block(block[0], block[1], what=f"blocks on a {width}x{height} frame")
            return
        gh, gw = grid
        self.check_block(height // gh, width // gw, what=f"blocks of a {gh}x{gw} grid on a {width}x{height} frame")
