"""Writing a stack (dataset format v1), atomically and resumably: `make_plan` says what a
stack will hold, `StackWriter` writes its images one by one (a rerun with the same plan
keeps what is there, a different plan is refused), `finish` writes meta.json last;
`update_labels` rewrites a complete stack's labels. The resume rule is in `stack_format`'s
module docstring."""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from noisefeat.atomic import atomic_write

from .exr import read_exr, write_exr
from .stack import Stack, from_meta, load_json, read_stack
from .stack_format import (EXTRA_QUICK, FORMAT, KNOWN_KEYS, LEVELS_DIR, META, OPTIONAL_KEYS, PARTIAL, QUICK,
                           QUICK_NONE, REFERENCE, VERSION, block_shape, level_name)
from .stack_validate import is_pos_int, validate_meta

log = logging.getLogger(__name__)


def make_plan(*, scene: str, width: int, height: int, spp: Sequence[int], reference_spp: int,
              quick: str, renderer: str, grid: Sequence[int] = (4, 4),
              **extras: Any) -> dict:
    """A meta.json without labels: what `StackWriter` needs up front."""
    bh, bw = block_shape(int(height), int(width), grid)
    plan = {"format": FORMAT, "version": VERSION, "scene": scene, "width": int(width),
            "height": int(height), "grid": [int(grid[0]), int(grid[1])], "block": [bh, bw],
            "spp": [int(s) for s in spp], "reference_spp": int(reference_spp),
            "quick": quick, "renderer": renderer}
    plan.update(extras)
    return plan


def _normalise_plan(meta: Mapping) -> dict:
    if "labeler" in meta or "thresholds" in meta:
        raise ValueError("the plan of a StackWriter has no labeler/thresholds: pass them "
                         "to finish()")
    plan = dict(meta)
    plan.setdefault("format", FORMAT)
    plan.setdefault("version", VERSION)
    plan.setdefault("grid", [4, 4])
    if "block" not in plan and all(is_pos_int(plan.get(k)) for k in ("width", "height")):
        plan["block"] = list(block_shape(plan["height"], plan["width"], plan["grid"]))
    try:
        plan = json.loads(json.dumps(plan))  # tuples -> lists; numpy scalars are refused
    except TypeError as exc:
        raise ValueError(f"stack plan is not JSON-serialisable: {exc}") from exc
    errs = validate_meta(plan)
    if errs:
        raise ValueError("invalid stack plan: " + "; ".join(errs))
    return plan


def _plan_of(meta: Mapping) -> dict:
    return {k: v for k, v in meta.items() if k not in OPTIONAL_KEYS}


class StackWriter:
    """Incremental, resumable writer of one stack (see the resume rule in the module doc)."""

    def __init__(self, path: str | os.PathLike, meta: Mapping, *, half: bool = False):
        self.path = Path(path)
        self.plan = _normalise_plan(meta)
        self.half = half
        self._complete = False
        self.path.mkdir(parents=True, exist_ok=True)
        meta_path, partial = self.path / META, self.path / PARTIAL
        if meta_path.is_file():
            self._same_plan(_plan_of(load_json(meta_path)), meta_path)
            self._complete = True
            log.info("%s: complete stack with the same plan", self.path)
        elif partial.is_file():
            self._same_plan(load_json(partial), partial)
            log.info("%s: resuming, %d of %d levels present", self.path,
                     len(self.plan["spp"]) - len(self.missing_levels(verify=False)),
                     len(self.plan["spp"]))
        else:
            leftovers = list((self.path / LEVELS_DIR).glob("*.exr")) if (
                self.path / LEVELS_DIR).is_dir() else []
            leftovers += [p for p in (self.path / REFERENCE, self.path / QUICK) if p.exists()]
            if leftovers:
                raise ValueError(f"{self.path}: holds images ({leftovers[0].name}, ...) but no "
                                 f"{META} or {PARTIAL}: cannot tell which build they belong "
                                 "to; remove them or choose another directory")
            dump_json(partial, self.plan)

    def _same_plan(self, old: Any, where: Path) -> None:
        if not isinstance(old, Mapping):
            raise ValueError(f"{where}: not a JSON object")
        keys = sorted(set(old) | set(self.plan))
        diff = [k for k in keys if old.get(k) != self.plan.get(k)]
        if diff:
            detail = ", ".join(f"{k}: {old.get(k)!r} -> {self.plan.get(k)!r}" for k in diff[:4])
            raise ValueError(f"{where}: the directory holds a build with a different plan "
                             f"({detail}); remove it or choose another directory")

    @property
    def is_complete(self) -> bool:
        return self._complete

    def _begin_write(self) -> None:
        if self._complete:
            dump_json(self.path / PARTIAL, self.plan)
            (self.path / META).unlink(missing_ok=True)
            self._complete = False

    def _check_image(self, img: np.ndarray, what: str) -> np.ndarray:
        arr = np.asarray(img)
        shape = (self.plan["height"], self.plan["width"], 3)
        if arr.shape != shape:
            raise ValueError(f"{self.path}: {what} has shape {arr.shape}, the plan needs {shape}")
        return arr

    def _present(self, p: Path, verify: bool) -> bool:
        if not p.is_file():
            return False
        if not verify:
            return True
        try:
            img = read_exr(p)
        except ValueError as exc:
            log.warning("%s; it will be rewritten", exc)
            return False
        if img.shape != (self.plan["height"], self.plan["width"], 3):
            log.warning("%s: wrong shape %s; it will be rewritten", p, img.shape)
            return False
        return True

    def has_level(self, spp: int, verify: bool = True) -> bool:
        """True if the level file exists (and, with `verify`, reads back with the right shape)."""
        return self._present(self.path / level_name(spp), verify)

    def missing_levels(self, verify: bool = True) -> list[int]:
        return [s for s in self.plan["spp"] if not self.has_level(s, verify)]

    def write_level(self, spp: int, img: np.ndarray) -> None:
        if spp not in self.plan["spp"]:
            raise ValueError(f"{self.path}: spp {spp} is not a level of the plan "
                             f"{self.plan['spp'][:4]}...")
        arr = self._check_image(img, f"level {spp}")
        self._begin_write()
        write_exr(self.path / level_name(spp), arr, half=self.half)

    def has_reference(self, verify: bool = True) -> bool:
        return self._present(self.path / REFERENCE, verify)

    def write_reference(self, img: np.ndarray) -> None:
        arr = self._check_image(img, "reference")
        self._begin_write()
        write_exr(self.path / REFERENCE, arr)

    def has_quick(self, verify: bool = True) -> bool:
        return self.plan["quick"] == QUICK_NONE or self._present(self.path / QUICK, verify)

    def write_quick(self, img: np.ndarray) -> None:
        if self.plan["quick"] == QUICK_NONE:
            raise ValueError(f"{self.path}: the plan says quick = 'none'; no quick image")
        arr = self._check_image(img, "quick image")
        self._begin_write()
        write_exr(self.path / QUICK, arr)

    def write_extra_quick(self, kind: str, img: np.ndarray) -> None:
        """Add an optional extra quick image; does not touch the stack's completeness."""
        if kind not in EXTRA_QUICK:
            raise ValueError(f"extra quick image kind must be one of {sorted(EXTRA_QUICK)}, got {kind!r}")
        self.path.mkdir(parents=True, exist_ok=True)
        write_exr(self.path / EXTRA_QUICK[kind], self._check_image(img, f"{kind} quick image"))

    def finish(self, thresholds: Sequence[int | None] | None = None,
               labeler: Mapping | None = None) -> Stack:
        """Check every file is there, then write meta.json (atomically) and drop the plan."""
        missing = [level_name(s) for s in self.missing_levels(verify=False)]
        if not self.has_reference(verify=False):
            missing.append(REFERENCE)
        if not self.has_quick(verify=False):
            missing.append(QUICK)
        if missing:
            raise ValueError(f"{self.path}: cannot finish, missing {len(missing)} file(s): "
                             + ", ".join(missing[:5]))
        meta = dict(self.plan)
        meta["labeler"] = None if labeler is None else dict(labeler)
        meta["thresholds"] = None if thresholds is None else [
            None if t is None else int(t) for t in thresholds]
        meta = json.loads(json.dumps(meta))
        errs = validate_meta(meta)
        if errs:
            raise ValueError(f"{self.path}: cannot finish: " + "; ".join(errs))
        dump_json(self.path / META, meta)
        (self.path / PARTIAL).unlink(missing_ok=True)
        self._complete = True
        return from_meta(meta, self.path)


def write_stack(path: str | os.PathLike, *, scene: str,
                levels: Mapping[int, np.ndarray] | Sequence[np.ndarray],
                spp: Sequence[int] | None = None, reference: np.ndarray,
                quick: np.ndarray | None, reference_spp: int,
                quick_description: str | None = None, renderer: str = "unknown",
                grid: Sequence[int] = (4, 4), labeler: Mapping | None = None,
                thresholds: Sequence[int | None] | None = None, half: bool = False,
                **extras: Any) -> Stack:
    """Write a whole stack at once in the dataset format (every file atomically, meta.json last).

    Parameters
    ----------
    path : str or os.PathLike
        The stack's directory (created).
    scene : str
        Scene name, meta.json's `scene`.
    levels : mapping or sequence of numpy.ndarray
        Cumulative-mean linear RGB images [H, W, 3]: {spp: image}, or a sequence aligned
        with `spp`.
    spp : sequence of int, optional
        Strictly increasing samples per pixel of the levels (required with a sequence).
    reference : numpy.ndarray
        The high-spp reference image [H, W, 3].
    quick : numpy.ndarray or None
        The quick noise-free image [H, W, 3]; None writes a stack without one (meta.json
        "quick": "none").
    reference_spp : int
        Samples per pixel of the reference.
    quick_description : str, optional
        meta.json's `quick` (what the quick image is).
    renderer : str, default 'unknown'
        meta.json's `renderer`.
    grid : sequence of int, default (4, 4)
        (rows, columns) of blocks; must divide the image size.
    labeler : mapping, optional
        meta.json's `labeler` (who labelled `thresholds`).
    thresholds : sequence of int or None, optional
        Per-block thresholds in spp (None: never converged), row-major.
    half : bool, default False
        Store levels as half floats (smaller; passes then cannot be recovered exactly).
    **extras
        Extra meta.json keys.

    Returns
    -------
    Stack
        The written stack, as `read_stack` opens it.

    Raises
    ------
    ValueError
        On inconsistent sizes, spp or labels.
    """
    if isinstance(levels, Mapping):
        if spp is None:
            spp = sorted(levels)
        images = [levels[s] for s in spp]
    else:
        images = list(levels)
        if spp is None:
            raise ValueError("spp is required when levels is a sequence")
        if len(images) != len(spp):
            raise ValueError(f"{len(images)} level images for {len(spp)} spp values")
    ref = np.asarray(reference)
    if ref.ndim != 3:
        raise ValueError(f"reference must be [H, W, 3], got shape {ref.shape}")
    if quick is None:
        desc = QUICK_NONE
    else:
        desc = quick_description or "unspecified"
        if desc == QUICK_NONE:
            raise ValueError("quick_description 'none' means no quick image, but one was given")
    plan = make_plan(scene=scene, width=ref.shape[1], height=ref.shape[0], spp=spp,
                     reference_spp=reference_spp, quick=desc, renderer=renderer, grid=grid,
                     **extras)
    w = StackWriter(path, plan, half=half)
    for s, img in zip(plan["spp"], images):
        w.write_level(s, img)
    w.write_reference(ref)
    if quick is not None:
        w.write_quick(quick)
    return w.finish(thresholds, labeler)


def dump_json(path: Path, obj: Mapping) -> None:
    """One top-level key per line (diff- and grep-friendly), known keys first."""
    keys = [k for k in KNOWN_KEYS if k in obj] + [k for k in obj if k not in KNOWN_KEYS]
    body = ",\n".join(f" {json.dumps(k)}: {json.dumps(obj[k])}" for k in keys)
    atomic_write(path, ("{\n" + body + "\n}\n").encode("utf-8"))


def update_labels(stack: Stack | str | os.PathLike, thresholds: Sequence[int | None] | None,
                  labeler: Mapping | None, tile: int | None = None,
                  tile_thresholds: Sequence[int | None] | None = None) -> Stack:
    """Replace a complete stack's thresholds/labeler (e.g. relabel with another tau), and
    with `tile` its tile truth (else the tile truth is dropped: it was the old labeler's)."""
    st = stack if isinstance(stack, Stack) else read_stack(stack)
    meta = st.meta()
    meta["thresholds"] = None if thresholds is None else [None if t is None else int(t)
                                                          for t in thresholds]
    meta["labeler"] = None if labeler is None else dict(labeler)
    meta.pop("tile", None)
    meta.pop("tile_thresholds", None)
    if tile is not None:
        meta["tile"] = int(tile)
        meta["tile_thresholds"] = [None if t is None else int(t) for t in tile_thresholds or []]
    errs = validate_meta(meta)
    if errs:
        raise ValueError(f"{st.path / META}: refusing to write: " + "; ".join(errs))
    dump_json(st.path / META, meta)
    return from_meta(meta, st.path)
