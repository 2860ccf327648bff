"""Reading a stack (dataset format v1, `stack_format`): `read_stack` opens its meta.json,
`Stack` reads its images on demand and says what is cached next to it is valid for.

Why reading alone: writing, resumable, is `stack_write` (`StackWriter`, `write_stack`,
`update_labels`); the meta.json rules are `stack_validate`; the stacks of a dataset
directory are `dataset_dir`.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from noisefeat import split_blocks
from noisefeat.atomic import atomic_write
from noisefeat.errors import InputNotFound
from noisefeat.safeio import open_input, read_text

from .exr import read_exr
from .stack_format import (EXTRA_QUICK, FORMAT, KNOWN_KEYS, META, MID_GREY_LINEAR, OPTIONAL_KEYS, PARTIAL, QUICK,
                           QUICK_NONE, REFERENCE, VERSION, file_kind, level_name)
from .stack_validate import validate_meta

log = logging.getLogger(__name__)


@dataclass
class Stack:
    """One scene's stack on disk; images are read on demand, never cached."""

    scene: str
    width: int
    height: int
    grid: tuple[int, int]
    block: tuple[int, int]
    spp: list[int]
    reference_spp: int
    quick_description: str
    renderer: str
    labeler: dict | None
    thresholds: list[int | None] | None
    path: Path
    extras: dict = field(default_factory=dict)
    #: the tile truth: the side of the tiles each block is cut into, and each
    #: tile's threshold (block-major, `noisefeat.pooling.tile_windows`), or None
    tile: int | None = None
    tile_thresholds: list[int | None] | None = None

    @property
    def n_levels(self) -> int:
        return len(self.spp)

    @property
    def n_blocks(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def has_quick(self) -> bool:
        return self.quick_description != QUICK_NONE

    def level_path(self, k: int) -> Path:
        return self.path / level_name(self.spp[k])

    @property
    def reference_path(self) -> Path:
        return self.path / REFERENCE

    @property
    def quick_path(self) -> Path:
        return self.path / QUICK

    def _read(self, path: Path) -> np.ndarray:
        img = read_exr(path)
        if img.shape != (self.height, self.width, 3):
            raise ValueError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, meta.json says "
                             f"{self.width}x{self.height}")
        if img.size and not np.isfinite(img).any():     # a few NaN pixels happen; none finite is damage
            raise ValueError(f"{path}: no finite pixel (all NaN/Inf): a damaged image; rebuild it "
                             "(`noisestop dataset check` lists every such file)")
        return img

    def files(self) -> list[Path]:
        """Every file this stack's data is read from: meta.json, levels, reference, quick images."""
        out = [self.path / META, *(self.level_path(k) for k in range(self.n_levels)), self.reference_path]
        if self.has_quick:
            out.append(self.quick_path)
        out += [self.path / name for name in EXTRA_QUICK.values() if (self.path / name).exists()]
        return out

    def content_key(self) -> str:
        """A short hash of the bytes of every file in `files()` (of meta.json: its plan, the
        labels left out): what anything computed from the stack and cached next to it is
        valid for. A file rewritten, truncated, replaced
        or removed changes it (a missing file raises FileNotFoundError naming it); a copy of
        the stack (new modification times) keeps it. Each file is hashed once per process
        while its size and modification time stay the same (`file_digest`)."""
        h = hashlib.sha256()
        for p in self.files():
            digest = self._plan_digest() if p.name == META else file_digest(p)
            h.update(f"{p.relative_to(self.path)}\0{digest}\0".encode())
        return h.hexdigest()[:32]

    def validate(self) -> None:
        """Decode every image this stack's data comes from (levels, reference, quick
        images): a truncated, corrupt, wrongly sized or all-NaN file is a ValueError (or
        FileNotFoundError) naming it, whether or not the command at hand reads that file
        (train and evaluate read labels, not the reference, which the labels came from).

        Done once per stack content: the content key (SHA-256 of every file) is then kept
        in `<stack>/.cache/validated` and in this process, so an unchanged stack is not
        decoded again, and any change to any file makes it validated anew."""
        key = self.content_key()
        marker = self.path / VALIDATED_MARKER
        if key in _VALIDATED:
            return
        try:
            if read_text(marker, "cache marker").strip() == key:
                _VALIDATED.add(key)
                return
        except (OSError, UnicodeDecodeError):
            pass
        for path in self.files():
            if path.name != META:
                self._read(path)
        _VALIDATED.add(key)
        try:
            atomic_write(marker, (key + "\n").encode())
        except OSError as exc:            # a read-only dataset: validated again next time
            log.debug("%s: not written (%s)", marker, exc)

    def _plan_digest(self) -> str:
        """meta.json without its labels (`labeler`, `thresholds`): nothing cached next to a
        stack is computed from them, so relabelling keeps the caches."""
        plan = {k: v for k, v in self.meta().items() if k not in OPTIONAL_KEYS}
        return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()

    def level(self, k: int) -> np.ndarray:
        """Level k (index into `spp`, negative allowed): linear RGB [H, W, 3] float32."""
        return self._read(self.level_path(k))

    def iter_levels(self) -> Iterator[np.ndarray]:
        """Levels one at a time (bounded memory)."""
        for k in range(self.n_levels):
            yield self.level(k)

    def levels(self) -> np.ndarray:
        """All levels [K, H, W, 3]: K*H*W*12 bytes (512x512, 100 levels: 315 MB)."""
        return np.stack(list(self.iter_levels()))

    def reference(self) -> np.ndarray:
        return self._read(self.reference_path)

    def quick(self, kind: str | None = None) -> np.ndarray:
        """The quick image, or flat mid-grey when the stack has none (see module doc).

        `kind`: None or 'albedo' = the stack's own quick image (quick.exr; the design's
        albedo AOV, whatever meta "quick" describes); an `EXTRA_QUICK` kind = that optional
        extra image.
        """
        if kind in EXTRA_QUICK:
            path = self.path / EXTRA_QUICK[kind]
            if not path.exists():
                raise InputNotFound(f"{self.path}: no {kind} quick image ({path.name}); rerun "
                                        f"`noisestop dataset build` with the same settings to add it")
            return self._read(path)
        if kind not in (None, "albedo"):
            raise ValueError(f"quick image kind must be None, 'albedo' or one of {sorted(EXTRA_QUICK)}, "
                             f"got {kind!r}")
        if not self.has_quick:
            return np.full((self.height, self.width, 3), MID_GREY_LINEAR, np.float32)
        return self._read(self.quick_path)

    def split(self, image: np.ndarray) -> np.ndarray:
        """An image of this stack cut into its blocks [n_blocks, bh, bw, 3], row-major."""
        return split_blocks(image, tuple(self.grid))

    def blocks(self, k: int) -> np.ndarray:
        """Level k cut into blocks [n_blocks, bh, bw, 3], row-major."""
        return self.split(self.level(k))

    def labels(self) -> np.ndarray:
        """int8 [K, n_blocks]: +1 iff threshold not null and spp[k] >= T_b, else -1."""
        if self.thresholds is None:
            raise ValueError(f"{self.path / META}: stack has no thresholds (not labelled)")
        return _labels(self.spp, self.thresholds)

    def tile_labels(self) -> np.ndarray:
        """int8 [K, n_tiles]: the tile truth's labels, as `labels` are the blocks'."""
        if self.tile_thresholds is None:
            raise ValueError(f"{self.path / META}: stack has no tile thresholds (dataset relabel writes them)")
        return _labels(self.spp, self.tile_thresholds)

    def meta(self) -> dict:
        """The meta.json dict of this stack."""
        out = {"format": FORMAT, "version": VERSION, "scene": self.scene,
               "width": self.width, "height": self.height, "grid": list(self.grid),
               "block": list(self.block), "spp": list(self.spp),
               "reference_spp": self.reference_spp, "quick": self.quick_description,
               "renderer": self.renderer, "labeler": self.labeler,
               "thresholds": None if self.thresholds is None else list(self.thresholds)}
        if self.tile_thresholds is not None:
            out.update(tile=self.tile, tile_thresholds=list(self.tile_thresholds))
        out.update(self.extras)
        return out


_DIGESTS: dict[tuple[str, int, int, int], str] = {}
#: where `Stack.validate` keeps the content key of the files it decoded
VALIDATED_MARKER = ".cache/validated"
#: content keys validated in this process
_VALIDATED: set[str] = set()


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes, remembered per (path, inode, size, mtime) for this process."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise InputNotFound(f"{path}: missing") from None
    sig = (os.fspath(path), st.st_ino, st.st_size, st.st_mtime_ns)
    digest = _DIGESTS.get(sig)
    if digest is None:
        h = hashlib.sha256()
        with open_input(path, file_kind(path)) as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        digest = _DIGESTS[sig] = h.hexdigest()
        if len(_DIGESTS) > 100_000:
            _DIGESTS.clear()
    return digest


def load_json(path: Path) -> Any:
    """A stack's JSON file (meta.json, the plan) parsed; one line naming it if it is not JSON."""
    try:
        return json.loads(read_text(path, file_kind(path)))
    except RecursionError:
        raise ValueError(f"{path}: not a stack description (JSON nested too deeply)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text: {exc}") from exc


def _stack_dir(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p.parent if p.name == META else p


def read_stack(path: str | os.PathLike) -> Stack:
    """Open a complete stack of the dataset format (DESIGN "Dataset format v1").

    Only meta.json is read and validated here; level, reference and quick images are read
    when asked for (`Stack.level`, `Stack.reference`, ...), and `Stack.validate` checks
    every file.

    Parameters
    ----------
    path : str or os.PathLike
        The stack's directory, or its meta.json.

    Returns
    -------
    Stack
        The stack: scene, size, grid, block, spp levels, labels (`thresholds`, `labeler`)
        and extra meta.json keys.

    Raises
    ------
    noisefeat.errors.InputNotFound
        If there is no meta.json (the message says whether a build was interrupted; a
        ValueError and a FileNotFoundError).
    ValueError
        If meta.json is not valid JSON or breaks the format.
    """
    d = _stack_dir(path)
    meta_path = d / META
    if not meta_path.is_file():
        if (d / PARTIAL).is_file():
            raise InputNotFound(f"{meta_path}: missing: incomplete build ({PARTIAL} "
                                    "present); rerun the build to finish it")
        raise InputNotFound(f"{meta_path}: missing: {d} is not a noisestop stack")
    meta = load_json(meta_path)
    errs = validate_meta(meta)
    if errs:
        raise ValueError(f"{meta_path}: invalid: " + "; ".join(errs))
    return from_meta(meta, d)


def from_meta(meta: Mapping, d: Path) -> Stack:
    """The `Stack` of directory `d` whose meta.json is `meta` (already validated)."""
    th = meta.get("thresholds")
    return Stack(scene=meta["scene"], width=meta["width"], height=meta["height"],
                 grid=(meta["grid"][0], meta["grid"][1]),
                 block=(meta["block"][0], meta["block"][1]), spp=list(meta["spp"]),
                 reference_spp=meta["reference_spp"], quick_description=meta["quick"],
                 renderer=meta["renderer"], labeler=meta.get("labeler"),
                 thresholds=None if th is None else list(th), path=d,
                 extras={k: v for k, v in meta.items() if k not in KNOWN_KEYS}, tile=meta.get("tile"),
                 tile_thresholds=None if meta.get("tile_thresholds") is None else list(meta["tile_thresholds"]))


def _labels(spp: Sequence[int], thresholds: Sequence[int | None]) -> np.ndarray:
    """int8 [K, n]: +1 iff a threshold is not null and spp[k] >= it, else -1."""
    s = np.asarray(spp, np.int64)[:, None]
    never = np.iinfo(np.int64).max
    t = np.array([never if v is None else v for v in thresholds], np.int64)[None, :]
    return np.where(s >= t, 1, -1).astype(np.int8)
