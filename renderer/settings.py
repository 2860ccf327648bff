"""Where each render setting comes from: command line, reference stack, scene, or default.

A render is judged against the settings a scene needs, so none of them is assumed
silently: each value is taken, in order, from

1. the command line (or the caller's keyword argument), when given;
2. the reference stack (`--reference`), whose levels the oracle's thresholds and the
   early-stop figures are measured at: its grid, its resolution, its first level
   as step and min spp (when the levels are evenly spaced) and its last level as max spp;
3. the scene itself: the resolution of a built-in scene's registry entry or of a Mitsuba
   XML file's own film (`load_scene` with resolution None);
4. the documented defaults below, and the report says so.

The report carries the source of every value (`settings_source`), and the log says it
once per render. The display exposure the criteria judge at is the criterion's (command
line, default 0 stops); the report records it too.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from learning.data.stack import Stack

#: used only when neither the command line, the reference nor the scene says. Blocks: windows
#: of DEFAULT_BLOCK pixels, the block size the bundled model and flip's threshold were
#: trained and calibrated on (data/train: 64x64 blocks), whatever the frame's size
DEFAULT_BLOCK = 64
DEFAULTS: dict[str, Any] = {"block": DEFAULT_BLOCK, "step": 16, "min_spp": 16, "max_spp": 1024}
#: documented ranges: spp settings are whole numbers in [1, MAX_SPP], and a render
#: makes at most MAX_PASSES passes (each appends a row to the checkpointed history)
MAX_SPP = 1 << 20
MAX_PASSES = 10_000
#: the longest time limit accepted on every door, seconds (a year: anything longer is a typo)
MAX_TIME_LIMIT = 365 * 24 * 3600.0
KEYS = ("resolution", "grid", "block", "step", "min_spp", "max_spp")
SCENE = "scene"
COMMAND_LINE = "command line"
DEFAULT = "default"
NOT_USED = "not used"        # grid when blocks are given by size, and block size with a grid


def reference_settings(stack: Stack) -> dict[str, Any]:
    """The settings a reference stack implies (only those it determines)."""
    out: dict[str, Any] = {"grid": tuple(stack.grid), "max_spp": int(stack.spp[-1]), "min_spp": int(stack.spp[0])}
    out["resolution"] = int(stack.width) if stack.width == stack.height else (int(stack.width), int(stack.height))
    spp = list(stack.spp)
    if all(b - a == spp[0] for a, b in zip([0, *spp[:-1]], spp)):   # spp = step, 2 step, 3 step...
        out["step"] = int(spp[0])
    return out


def resolve_settings(given: Mapping[str, Any], reference: Stack | None = None
                     ) -> tuple[dict[str, Any], dict[str, str]]:
    """(values, sources) for every key of KEYS; a None value in `given` means "not given".

    `resolution` may stay None: the scene decides it when loaded (source "scene").
    Blocks are a `grid` or a `block` size, never both: a grid from the command line or
    the reference wins, else the block size given or `DEFAULT_BLOCK` (the other is None).
    """
    unknown = set(given) - set(KEYS)
    if unknown:
        raise ValueError(f"unknown render settings {sorted(unknown)}")
    implied = reference_settings(reference) if reference is not None else {}
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    blocks = "grid" if given.get("grid") is not None else "block" if given.get("block") is not None else \
        "grid" if "grid" in implied else None
    if given.get("grid") is not None and given.get("block") is not None:
        raise ValueError("give the blocks either as --grid ROWS COLS or as --block PX, not both")
    for key in KEYS:
        if key in ("grid", "block") and key != (blocks or "block"):
            values[key], sources[key] = None, NOT_USED
            continue
        if given.get(key) is not None:
            values[key], sources[key] = given[key], COMMAND_LINE
        elif key in implied:
            values[key], sources[key] = implied[key], f"reference {reference.path}"
        elif key == "resolution":
            values[key], sources[key] = None, SCENE
        else:
            values[key], sources[key] = DEFAULTS[key], DEFAULT
    if values["min_spp"] > values["max_spp"] and sources["min_spp"] != sources["max_spp"]:
        # e.g. --max-spp 8 below the default min: the one given wins rather than an error
        loser = "min_spp" if sources["max_spp"] == COMMAND_LINE else "max_spp"
        values[loser] = values["max_spp" if loser == "min_spp" else "min_spp"]
        sources[loser] += f" (clipped to {loser.replace('_spp', '')} = the other bound)"
    return values, sources


def check_spp_settings(step: Any, min_spp: Any, max_spp: Any) -> None:
    """step, min_spp and max_spp in [1, MAX_SPP], min_spp <= max_spp, at most MAX_PASSES passes."""
    for name, v in (("step", step), ("min_spp", min_spp), ("max_spp", max_spp)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= MAX_SPP:
            raise ValueError(f"{name} must be a positive integer, at most {MAX_SPP}, got {v!r}")
    if min_spp > max_spp:
        raise ValueError(f"min_spp ({min_spp}) is above max_spp ({max_spp})")
    passes = -(-int(max_spp) // int(step))
    if passes > MAX_PASSES:
        raise ValueError(f"max_spp {max_spp} in steps of {step} is {passes} passes, more than {MAX_PASSES}: "
                         "take a larger step")


def describe(values: Mapping[str, Any], sources: Mapping[str, str]) -> str:
    """One log line: 'resolution 256x256 (scene), grid 4x4 (default), ...'."""
    def fmt(k: str, v: Any) -> str:
        if isinstance(v, (list, tuple)):
            return "x".join(str(int(x)) for x in v)
        return f"{v:g}" if isinstance(v, float) else str(v)
    return ", ".join(f"{k} {fmt(k, values[k])} ({sources[k]})" for k in KEYS if values.get(k) is not None)
