"""The render spec: `resolve` defaults and checks a render's settings (`renderer.settings.ROWS`)
in one place, into a frozen `RenderSpec` recording where each value came from (DESIGN "Render
spec"). A door checks what it was given first (`checked`): a bad value fails before anything
loads, and is not checked again. Each criterion declares the rows it takes; no table here does.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from noisefeat.bounds import SizeBounds

from .criteria.registry import BLOCK_ONLY, TILE, Declared, criterion_class, declared
from .setting_kinds import MAX_SIDE
from .settings import MAX_PASSES, ROW, ROWS, check_known, declared_row

logger = logging.getLogger(__name__)

# where a value came from
ARGUMENT = "argument"
COMMAND_LINE = "command line"
PLUGIN = "scene plugin"
DEFAULT = "default"
SCENE = "scene"
NOT_USED = "not used"

__all__ = ["ARGUMENT", "COMMAND_LINE", "PLUGIN", "DEFAULT", "SCENE", "NOT_USED", "RenderSpec", "FIELDS", "resolve",
           "Checked", "checked", "reference_settings"]


@dataclass(frozen=True)
class RenderSpec:
    """A render's settings, one field per row of ROWS in their order, and where each came from."""

    criterion: str | Declared
    tau: float
    threshold: float | None
    offset: float | None
    quantile: float
    model: str | None
    server: str | None
    exposure: float
    resolution: int | tuple[int, int] | None
    grid: tuple[int, int] | None
    block: int | None
    tile: int
    min_spp: int
    max_spp: int
    step: int
    decide_skip: float
    decide_growth: float
    seed: int
    time_limit: float | None
    spp_budget: float | None
    quick_spp: int
    defines: Mapping[str, str] | None
    checkpoint_every: float
    sources: Mapping[str, str] = field(compare=False)

    def describe(self) -> str:
        """One log line: 'resolution 256x256 (scene), block 64 (default), ...'."""
        def fmt(v: Any) -> str:
            if isinstance(v, (list, tuple)):
                return "x".join(str(int(x)) for x in v)
            return f"{v:g}" if isinstance(v, float) else str(v)
        return ", ".join(f"{k} {fmt(getattr(self, k))} ({self.sources[k]})" for k in
                         ("resolution", "grid", "block", "step", "min_spp", "max_spp", "tau", "exposure")
                         if getattr(self, k) is not None)

    def cut(self) -> dict[str, Any]:
        """How the frame is cut into blocks and tiles, as `BlockWindows` takes it."""
        return {"grid": self.grid, "block": self.block, "tile": self.tile}

    def tile_grain(self) -> int | None:
        """The tile side when blocks are cut into tiles, else None (whole blocks, or not known yet)."""
        side = _block_side(self.block, self.grid, self.resolution)
        return self.tile if side is not None and self.tile < side else None

    def unit_side(self) -> int | None:
        """The side of the units the loop decides on (None: not known yet)."""
        return self.tile_grain() or _block_side(self.block, self.grid, self.resolution)

    def settings_source(self) -> dict[str, str]:
        """report.json ``settings_source``: where each setting in use came from."""
        return {r.name: self.sources[r.name] for r in ROWS
                if getattr(self, r.name) is not None and self.sources[r.name] != NOT_USED}


FIELDS = tuple(f.name for f in fields(RenderSpec) if f.name != "sources")


def _grain_of(criterion: str | Declared) -> str:
    """A criterion's grain, by name or of an object."""
    return criterion_class(criterion).grain if isinstance(criterion, str) else criterion.grain


def reference_settings(stack: Any) -> dict[str, Any]:
    """The settings a reference stack determines."""
    spp = [int(s) for s in stack.spp]
    out: dict[str, Any] = {"grid": tuple(int(g) for g in stack.grid), "max_spp": spp[-1], "min_spp": spp[0]}
    out["resolution"] = int(stack.width) if stack.width == stack.height else (int(stack.width), int(stack.height))
    if all(b - a == spp[0] for a, b in zip([0, *spp[:-1]], spp)):   # spp = step, 2 step, 3 step...
        out["step"] = spp[0]
    return out


class Checked(dict[str, Any]):
    """Settings a door checked (`checked`): `resolve` takes them as they are."""


def checked(given: Mapping[str, Any]) -> Checked:
    """`given`'s values (None: not given, left out), each checked by its row, unknown names refused."""
    check_known(given)
    return Checked({name: ROW[name].check(value) for name, value in given.items() if value is not None})


def resolve(given: Mapping[str, Any], *, source: str = ARGUMENT, plugin: Mapping[str, Any] | None = None,
            reference: Any = None, frame: tuple[int, int] | None = None,
            thresholds_known: bool | None = None) -> RenderSpec:
    """Each row from `given` (None: not given), else the scene `plugin`'s, else the `reference`
    stack's, else its default (the criterion's, for the rows it declares); then the
    combination, and with `frame` (the loaded film's (width, height)) the blocks fitted to it.
    `thresholds_known` (default: a reference is given): a criterion that needs true
    thresholds will have them. A one-line ValueError naming the setting for anything wrong."""
    check_known(given, plugin)
    ref_source = f"reference {getattr(reference, 'path', '')}".rstrip()
    implied = Checked(reference_settings(reference) if reference is not None else {})
    layers = [(given, source), (plugin or {}, PLUGIN), (implied, ref_source)]
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for layer, src in layers:
        for name, value in layer.items():
            if value is not None and name not in values:
                values[name] = value if isinstance(layer, Checked) else ROW[name].check(value)
                sources[name] = src
    # blocks are a grid or a block size: the highest layer that names either decides
    unused = "grid"
    for layer, _ in layers:
        named = [k for k in ("grid", "block") if layer.get(k) is not None]
        if len(named) == 2:
            raise ValueError("give the blocks either as a grid (--grid ROWS COLS) or as a block size "
                             "(--block PX), not both")
        if named:
            unused = "block" if named[0] == "grid" else "grid"
            break
    values[unused], sources[unused] = None, NOT_USED
    for row in ROWS:
        if row.name not in values:
            values[row.name], sources[row.name] = row.default, SCENE if row.name == "resolution" else DEFAULT
    _combine(values, sources, [src for _, src in layers] + [DEFAULT],
             reference is not None if thresholds_known is None else thresholds_known)
    if frame is not None:
        _fit_frame(values, sources, *frame)
    return RenderSpec(**values, sources=sources)


def _combine(values: dict[str, Any], sources: dict[str, str], rank: list[str], thresholds_known: bool) -> None:
    """The checks no row can make alone, and the criterion with the settings it declares."""
    def level(name: str) -> int:
        return rank.index(sources[name]) if sources[name] in rank else len(rank)

    if values["model"] is not None and values["server"] is not None:
        raise ValueError("give a model bundle (model) or a verdict server (server), not both")
    _criterion(values, sources, thresholds_known)
    lo, hi = values["min_spp"], values["max_spp"]
    if lo > hi:
        if level("min_spp") == level("max_spp"):
            raise ValueError(f"min_spp ({lo}) is above max_spp ({hi})")
        loser, winner = ("min_spp", "max_spp") if level("max_spp") < level("min_spp") else ("max_spp", "min_spp")
        values[loser] = values[winner]          # the one given wins over a default
        sources[loser] += f" (clipped to {winner})"
    passes = -(-values["max_spp"] // values["step"])
    if passes > MAX_PASSES:
        raise ValueError(f"max_spp {values['max_spp']} in steps of {values['step']} is {passes} passes, "
                         f"more than {MAX_PASSES}: take a larger step")
    if values["spp_budget"] is not None and values["spp_budget"] < values["step"]:
        raise ValueError(f"spp_budget {values['spp_budget']:g} cannot buy one pass of {values['step']} "
                         "samples per pixel (the step): give a budget of at least the step, or a smaller step")


def _criterion(values: dict[str, Any], sources: dict[str, str], thresholds_known: bool) -> None:
    """The criterion by its declaration: a setting given without a criterion chooses the one
    it `selects`; its settings take its defaults and ranges, those only other criteria take
    are ignored with a warning; whole blocks by default at block grain."""
    declarations = declared()
    if sources["criterion"] == DEFAULT:
        chosen = [(name, key) for name, cls in declarations.items() for key, setting in cls.settings.items()
                  if setting.selects and values[key] is not None and sources[key] != DEFAULT]
        if chosen:
            values["criterion"], key = chosen[0]
            sources["criterion"] = f"{sources[key]} ({key})"
    crit = values["criterion"]
    if isinstance(crit, str):               # (a Criterion object is configured already)
        cls = criterion_class(crit)
        if cls.needs_thresholds and not thresholds_known:
            raise ValueError(f"the {crit} criterion needs true thresholds: give a labelled dataset or stack of "
                             "this scene as the reference (not an image)")
        for key in cls.settings:
            row = declared_row(cls, key)
            if sources[key] == DEFAULT:
                values[key] = row.default
            elif values[key] is not None and row is not ROW[key]:
                values[key] = row.check(values[key])
        others = {key for c in declarations.values() for key in c.settings} - set(cls.settings)
        for key in sorted(others, key=list(ROW).index):
            if values[key] is not None and sources[key] != DEFAULT:
                logger.warning("%s is ignored with the %s criterion", key, crit)
    if _grain_of(crit) != TILE and sources["tile"] == DEFAULT:
        label = getattr(crit, "name", crit)
        values["tile"], sources["tile"] = MAX_SIDE, f"{DEFAULT} (whole blocks: the {label} criterion)"


def _block_side(block: int | None, grid: tuple[int, int] | None, resolution: Any) -> int | None:
    """A block's longer side in pixels (a grid's on a (W, H) frame); None while the frame is not known."""
    if block is not None:
        return block
    if grid is not None and isinstance(resolution, tuple):
        return max(resolution[1] // grid[0], resolution[0] // grid[1])
    return None


def _fit_frame(values: dict[str, Any], sources: dict[str, str], width: int, height: int) -> None:
    """The settings for the loaded frame: a default block no larger than its short side, the
    blocks and the bounds of noisefeat.bounds checked against it."""
    values["resolution"] = (int(width), int(height))
    short, block, grid = int(min(width, height)), values["block"], values["grid"]
    if block is not None and block > short:
        if sources["block"] != DEFAULT:
            raise ValueError(f"block of {block} px is larger than the {width}x{height} frame: "
                             f"take --block {short} or less")
        block = values["block"] = short
        sources["block"] = f"{DEFAULT} (the frame's short side)"
    if grid is not None and (width % grid[1] or height % grid[0]):
        raise ValueError(f"image {width}x{height} (WxH) cannot be cut into a {grid[0]}x{grid[1]} grid of equal "
                         f"blocks: width must be divisible by {grid[1]} and height by {grid[0]}")
    side = _block_side(block, grid, values["resolution"])
    crit = values["criterion"]
    if _grain_of(crit) == BLOCK_ONLY and values["tile"] < side:
        raise ValueError(f"the {getattr(crit, 'name', crit)} criterion decides whole blocks: "
                         f"leave tile unset or give the block's side ({side})")
    values["tile"] = min(values["tile"], side)            # a tile is at most its block
    SizeBounds.from_env().check_frame(int(height), int(width), grid or (1, 1),
                                      block=None if grid else (block, block))
