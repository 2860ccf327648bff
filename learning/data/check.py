"""Dataset checker: every problem of every stack under a root, not just the first one.

Used by tests, by `dataset build` after a build, and by users before a long training run.
Errors make a stack unusable or its labels wrong, or put files in it that the format does
not have: an image with no finite pixel (damage, not the odd NaN a renderer emits), a
stray file in a stack or its levels (none of these may pass as "0 errors").
Warnings are oddities worth a look (some non-finite pixels in a level, human thresholds
between levels, unlisted level files, leftovers of an interrupted write).
"""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from noisefeat.safeio import InputFileError, check_regular, read_text

from noisefeat.atomic import is_temporary

from .exr import read_exr
from .stack_format import EXTRA_QUICK, LEVELS_DIR, META, PARTIAL, QUICK, QUICK_NONE, REFERENCE, level_name
from .stack_validate import validate_meta

#: what a stack directory may hold besides its images (learning.inputs.table's cache, a build's
#: checkpoint directory); anything else is a stray file
KNOWN_ENTRIES = {META, PARTIAL, REFERENCE, QUICK, LEVELS_DIR, ".cache", ".build", *EXTRA_QUICK.values()}

log = logging.getLogger(__name__)

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Problem:
    """One finding: the file (or directory) concerned, what is wrong, how bad."""

    path: Path
    message: str
    severity: str = ERROR

    def __str__(self) -> str:
        return f"{self.severity}: {self.path}: {self.message}"


def _looks_like_stack(d: Path, files: set[str], dirs: set[str]) -> bool:
    return bool({META, PARTIAL, REFERENCE, QUICK} & files) or (
        LEVELS_DIR in dirs and any((d / LEVELS_DIR).glob("*.exr")))


def find_stack_dirs(root: Path) -> list[Path]:
    """Directories that hold a stack or the remains of one (not searched further down)."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        if _looks_like_stack(d, set(filenames), set(dirnames)):
            found.append(d)
            dirnames[:] = []
        else:
            dirnames[:] = sorted(n for n in dirnames if not n.startswith("."))
    return sorted(found)


def check_dataset(root: str | os.PathLike, deep: bool = True) -> list[Problem]:
    """Check every stack under `root`. `deep=False` skips reading the images."""
    root = Path(root)
    if not root.is_dir():
        return [Problem(root, "dataset directory does not exist")]
    dirs = find_stack_dirs(root)
    if not dirs:
        return [Problem(root, "no stack found (no meta.json anywhere below)")]
    problems: list[Problem] = []
    for d in dirs:
        problems.extend(check_stack(d, deep=deep))
    return problems


def _pos_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x > 0


def _stray_entries(d: Path) -> list[Problem]:
    """Entries of a stack directory that the format does not have."""
    out = []
    for p in sorted(d.iterdir()):
        if p.name in KNOWN_ENTRIES:
            continue
        if is_temporary(p.name):
            out.append(Problem(p, "leftover of an interrupted write; safe to remove", WARNING))
        else:
            out.append(Problem(p, "stray file in a stack directory (not part of the stack format); "
                                  "remove it or move it out of the dataset"))
    return out


def nonfinite_problem(path: Path, img: np.ndarray, what: str, is_ref: bool) -> Problem | None:
    """The image's NaN/Inf values as a problem, or None if every value is finite.

    None finite is damage; some are an error in the reference (every label is measured
    against it, so the blocks around them get wrong labels) and a warning in a level or
    quick image (renderers do emit the odd NaN). `relabel` refuses what this calls an error.
    """
    bad = int(np.count_nonzero(~np.isfinite(img)))
    if bad and bad == img.size:
        return Problem(path, f"{what} has no finite value (all {bad} are NaN/Inf): damaged")
    if bad:
        return Problem(path, f"{what} has {bad} NaN/Inf value(s)", ERROR if is_ref else WARNING)
    return None


def check_stack(d: str | os.PathLike, deep: bool = True) -> list[Problem]:
    """Every problem of one stack directory."""
    d = Path(d)
    meta_path = d / META
    if not (meta_path.exists() or meta_path.is_symlink()):
        why = (f"incomplete build: {PARTIAL} present, rerun the build to finish it"
               if (d / PARTIAL).is_file() else "not a complete stack")
        return [Problem(meta_path, f"missing meta.json ({why})")]
    try:
        meta = json.loads(read_text(meta_path, "meta.json"))
    except InputFileError as exc:
        return [Problem(meta_path, str(exc).split(": ", 1)[-1])]
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        return [Problem(meta_path, f"meta.json is not valid JSON: {exc}")]
    except RecursionError:
        return [Problem(meta_path, "meta.json is nested too deeply to be a stack description")]
    problems = [Problem(meta_path, msg) for msg in validate_meta(meta)]
    if not isinstance(meta, dict):
        return problems
    if (d / PARTIAL).is_file():
        problems.append(Problem(d / PARTIAL, f"stale {PARTIAL} next to {META} (interrupted "
                                             "rewrite?)", WARNING))

    w, h = meta.get("width"), meta.get("height")
    shape = (h, w, 3) if _pos_int(w) and _pos_int(h) else None
    raw_spp = meta.get("spp")
    spp = [s for s in raw_spp if _pos_int(s)] if isinstance(raw_spp, list) else []

    images = [(d / level_name(s), f"level {s} spp", False) for s in spp]
    images.append((d / REFERENCE, "reference", True))
    quick = meta.get("quick")
    if quick == QUICK_NONE:
        if (d / QUICK).is_file():
            problems.append(Problem(d / QUICK, "quick.exr present but meta.json says quick "
                                               "is 'none'; it is ignored", WARNING))
    else:
        images.append((d / QUICK, "quick image", False))

    ref_shape = None
    for path, what, is_ref in images:
        rel = path.relative_to(d)
        if not (path.exists() or path.is_symlink()):
            kind = "level file" if what.startswith("level") else "file"
            problems.append(Problem(path, f"missing {kind} {rel} ({what})"))
            continue
        try:
            check_regular(path, "EXR")
        except (InputFileError, OSError) as exc:
            problems.append(Problem(path, f"{what}: {str(exc).split(': ', 1)[-1]}"))
            continue
        if not deep:
            continue
        try:
            img = read_exr(path)
        except (ValueError, OSError) as exc:
            problems.append(Problem(path, f"unreadable EXR ({what}): {exc}"))
            continue
        got = img.shape
        if shape is not None and got != shape:
            problems.append(Problem(path, f"shape mismatch: {what} is {got[1]}x{got[0]}, "
                                          f"meta.json width x height is {w}x{h}"))
        elif shape is None and ref_shape is not None and got != ref_shape:
            problems.append(Problem(path, f"shape mismatch: {what} is {got[1]}x{got[0]}, "
                                          f"the reference is {ref_shape[1]}x{ref_shape[0]}"))
        if is_ref:
            ref_shape = got
        nonfinite = nonfinite_problem(path, img, what, is_ref)
        if nonfinite is not None:
            problems.append(nonfinite)

    listed = {level_name(s).split("/")[1] for s in spp}
    if (d / LEVELS_DIR).is_dir():
        for p in sorted((d / LEVELS_DIR).iterdir()):
            if p.name in listed:
                continue
            if p.suffix == ".exr" and p.is_file() and not p.name.startswith("."):
                problems.append(Problem(p, "level file not listed in meta.json spp", WARNING))
            else:
                problems.append(Problem(p, "stray file in levels/ (only the level EXRs of meta.json "
                                           "belong there); remove it"))
    problems.extend(_stray_entries(d))

    th = meta.get("thresholds")
    if isinstance(th, list) and spp and spp == raw_spp:
        labeler = meta.get("labeler")
        virtual = isinstance(labeler, dict) and labeler.get("name") == "flip"
        levels = set(spp)
        for b, t in enumerate(th):
            if _pos_int(t) and t not in levels:
                problems.append(Problem(meta_path, f"threshold of block {b} ({t} spp) is not "
                                                   "in the spp list"
                                        + ("" if virtual else " (fine for human thresholds)"),
                                        ERROR if virtual else WARNING))
    return problems
