"""The rules of a stack's meta.json (DESIGN "Dataset format v1"): every problem, never a raise.

Why apart from the reader: `read_stack` refuses a meta.json that breaks them, the writer
refuses to write one (`stack_write`), and `dataset check` lists them all; each asks
`validate_meta` for the same list.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from noisefeat.pooling import MEAN, POOLINGS, tile_windows

from .stack_format import FORMAT, REQUIRED_KEYS, VERSION, block_shape


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def is_pos_int(x: Any) -> bool:
    """Whether `x` is an int above 0 (a bool is not one)."""
    return _is_int(x) and x > 0


def _pair(x: Any) -> bool:
    return isinstance(x, (list, tuple)) and len(x) == 2 and all(is_pos_int(v) for v in x)


def validate_meta(meta: Any) -> list[str]:
    """Every problem of a meta.json dict (empty list if none). Never raises."""
    if not isinstance(meta, Mapping):
        return [f"meta must be a JSON object, got {type(meta).__name__}"]
    errs: list[str] = []
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        errs.append(f"missing required keys: {', '.join(missing)}")
    if "format" in meta and meta["format"] != FORMAT:
        errs.append(f"format is {meta['format']!r}, expected {FORMAT!r}")
    if "version" in meta and not (_is_int(meta["version"]) and meta["version"] == VERSION):
        errs.append(f"version is {meta['version']!r}, only version {VERSION} is supported")
    if "scene" in meta:
        s = meta["scene"]
        if not isinstance(s, str) or not s or "/" in s or "\\" in s:
            errs.append(f"scene must be a non-empty name without path separators, got {s!r}")
    for key in ("width", "height"):
        if key in meta and not is_pos_int(meta[key]):
            errs.append(f"{key} must be a positive integer, got {meta[key]!r}")
    for key in ("grid", "block"):
        if key in meta and not _pair(meta[key]):
            errs.append(f"{key} must be two positive integers, got {meta[key]!r}")
    if all(is_pos_int(meta.get(k)) for k in ("width", "height")) and _pair(meta.get("grid")):
        w, h, grid = meta["width"], meta["height"], meta["grid"]
        try:
            expected = list(block_shape(h, w, grid))
        except ValueError as exc:
            errs.append(f"block size does not match grid: {exc}")
        else:
            if _pair(meta.get("block")) and list(meta["block"]) != expected:
                errs.append(f"block size {list(meta['block'])} does not match grid "
                            f"{list(grid)} for a {w}x{h} image (expected {expected})")
    spp_ok = False
    if "spp" in meta:
        spp = meta["spp"]
        if not isinstance(spp, list) or not spp:
            errs.append(f"spp must be a non-empty list of positive integers, got {spp!r}")
        elif not all(is_pos_int(v) for v in spp):
            bad = [v for v in spp if not is_pos_int(v)]
            errs.append(f"spp must hold positive integers only, got {bad[:5]!r}")
        else:
            bad_at = [i for i in range(1, len(spp)) if spp[i] <= spp[i - 1]]
            if bad_at:
                i = bad_at[0]
                errs.append(f"spp is not strictly increasing: spp[{i - 1}] = {spp[i - 1]} "
                            f">= spp[{i}] = {spp[i]} ({len(bad_at)} such place(s))")
            else:
                spp_ok = True
    if "reference_spp" in meta:
        r = meta["reference_spp"]
        if not is_pos_int(r):
            errs.append(f"reference_spp must be a positive integer, got {r!r}")
        elif spp_ok and r < meta["spp"][-1]:
            errs.append(f"reference_spp {r} is below the last level's spp {meta['spp'][-1]}")
    for key in ("quick", "renderer"):
        if key in meta and not isinstance(meta[key], str):
            errs.append(f"{key} must be a string, got {meta[key]!r}")
    lab = meta.get("labeler")
    if lab is not None and not isinstance(lab, Mapping):
        errs.append(f"labeler must be an object or null, got {lab!r}")
    elif isinstance(lab, Mapping) and lab.get("pooling", MEAN) not in POOLINGS:
        errs.append(f"labeler pooling {lab.get('pooling')!r} is unknown (known: {', '.join(POOLINGS)}); "
                    "its labels cannot be read as any observer's")
    th = meta.get("thresholds")
    if th is not None:
        if not isinstance(th, list):
            errs.append(f"thresholds must be a list or null, got {type(th).__name__}")
        else:
            if _pair(meta.get("grid")):
                n = meta["grid"][0] * meta["grid"][1]
                if len(th) != n:
                    errs.append(f"thresholds has {len(th)} entries, the {meta['grid'][0]}x"
                                f"{meta['grid'][1]} grid has {n} blocks")
            bad = [(i, t) for i, t in enumerate(th) if t is not None and not is_pos_int(t)]
            if bad:
                errs.append("thresholds must be positive integers (spp) or null; bad: "
                            + ", ".join(f"block {i}: {t!r}" for i, t in bad[:5]))
    errs += _tile_errors(meta)
    return errs


def _tile_errors(meta: Mapping) -> list[str]:
    """The tile truth's keys: `tile` (pixels) and `tile_thresholds`, one per tile
    of every block (`noisefeat.pooling.tile_windows`, block-major), given together."""
    tile, th = meta.get("tile"), meta.get("tile_thresholds")
    if tile is None and th is None:
        return []
    if not is_pos_int(tile) or not isinstance(th, list):
        return [f"tile (a positive integer) and tile_thresholds (a list) go together, got {tile!r} and "
                f"{type(th).__name__}"]
    errs = []
    if _pair(meta.get("grid")) and _pair(meta.get("block")):
        n = meta["grid"][0] * meta["grid"][1] * len(tile_windows(meta["block"][0], meta["block"][1], tile))
        if len(th) != n:
            errs.append(f"tile_thresholds has {len(th)} entries, the blocks' {tile}-pixel tiles are {n}")
    bad = [(i, t) for i, t in enumerate(th) if t is not None and not is_pos_int(t)]
    if bad:
        errs.append("tile_thresholds must be positive integers (spp) or null; bad: "
                    + ", ".join(f"tile {i}: {t!r}" for i, t in bad[:5]))
    return errs
