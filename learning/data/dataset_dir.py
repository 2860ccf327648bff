"""A dataset directory: the stacks under a root, read and validated, and its fingerprint.

Why apart from `stack`: commands open a whole dataset (`read_stacks`), find its stacks
(`list_stacks`, incomplete builds too, and one scene's: `find_stack`), and key results
computed on it (`dataset_fingerprint`); a single stack is `stack`'s.
"""
from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

from noisefeat.errors import InputNotFound
from noisefeat.safeio import read_input

from .stack import Stack, read_stack
from .stack_format import META, PARTIAL


def read_stacks(root: str | os.PathLike, scenes: Sequence[str] | None = None) -> list[Stack]:
    """The stacks below `root` (only `scenes`, if given), every file of each validated
    (`Stack.validate`): what commands that read a dataset open it with."""
    stacks = [read_stack(p) for p in list_stacks(root)]
    if scenes is not None:
        stacks = [st for st in stacks if st.scene in scenes]
    for st in stacks:
        st.validate()
    return stacks


def list_stacks(root: str | os.PathLike, include_incomplete: bool = False) -> list[Path]:
    """Every stack directory under `root` (root itself included), sorted.

    A directory is a stack if it holds meta.json (or, with `include_incomplete`,
    meta.partial.json); stacks are not searched for nested stacks. A meta.json that is a
    directory is a broken stack: one-line ValueError, never skipped silently.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputNotFound(f"{root}: no such dataset directory")
    names = {META, PARTIAL} if include_incomplete else {META}
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        odd = sorted(names & set(dirnames))
        if odd:      # a stack whose meta.json is no file: refused, not skipped as no stack
            raise ValueError(f"{Path(dirpath) / odd[0]}: a stack's {odd[0]} must be a file, this is a directory")
        if names & set(filenames):
            found.append(Path(dirpath))
            dirnames[:] = []
        else:
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
    return sorted(found)


def find_stack(reference: Stack | str | os.PathLike, scene: str) -> Stack:
    """The stack of `scene` in a dataset directory (or that stack itself), not yet labelled
    (a render's `--reference`, a simulation's stack)."""
    if isinstance(reference, Stack):
        return reference
    root = Path(reference)
    stacks = [read_stack(p) for p in list_stacks(root)]
    if not stacks:       # a folder, but no dataset: say so, not "no stack of this scene"
        raise ValueError(f"{root}: a folder with no stack in it (no {META} in it or below it): not a "
                         "labelled dataset or a stack (a reference image is a FILE.exr)")
    match = [s for s in stacks if s.scene == scene]
    if len(stacks) == 1 and not match:
        raise ValueError(f"{root}: the stack there is scene {stacks[0].scene!r}, not {scene!r}")
    if not match:
        raise ValueError(f"{root}: no stack of scene {scene!r} (found: "
                         f"{', '.join(s.scene for s in stacks[:10]) or 'none'})")
    return match[0]


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """A short hash of every stack's meta.json under `root`: results computed on a dataset
    (e.g. a saved model comparison) are only reused on the very same one."""
    h = hashlib.sha256()
    for p in list_stacks(root):
        h.update(p.name.encode() + b"\0" + read_input(p / META, "meta.json"))
    return h.hexdigest()[:16]
