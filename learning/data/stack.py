"""Dataset format v1 (DESIGN "Dataset format v1"): one directory per scene.

```
<scene>/meta.json                 # written last: its presence means "complete"
<scene>/meta.partial.json         # only while a build is in progress: the plan
<scene>/levels/000032.exr ...     # cumulative-mean linear RGB, named by spp (%06d)
<scene>/reference.exr             # high-spp linear RGB
<scene>/quick.exr                 # the quick noise-free image (absent if meta "quick" == "none")
<scene>/quick_direct.exr          # optional, beyond format v1: direct-lighting quick image
```

Extra quick images (`EXTRA_QUICK`, only for the quick-image ablation) are not part of
format v1: readers that do not know them ignore them, a stack is complete without them,
and adding one to a complete stack leaves it complete (`write_extra_quick`).

Reading and validating here; writing, resumable, in `stack_write` (`StackWriter`, `write_stack`).

Resume rule (used by `StackWriter`, hence by `dataset build` and `import-lisic`):

* a directory with `meta.json` is a complete stack;
* a directory with `meta.partial.json` (and no `meta.json`) is a build in progress. The
  partial file holds the *plan*: every meta.json key except `labeler` and `thresholds`.
  Every image file in it is complete (all writes are atomic), so a writer reopened with an
  identical plan keeps them and only writes what is missing; a different plan is refused
  (ValueError) rather than mixing two builds in one directory;
* writing into a complete stack first removes its `meta.json` (back to "in progress").

`quick == "none"` (e.g. LISIC imports, which have no noise-free image): no quick.exr is
written and `Stack.quick()` returns a flat mid-grey image (sRGB 0.5) of the right size, so
that `features(quick) - features(current)` stays defined and carries no information
beyond `features(current)`. `Stack.has_quick` tells callers that want to know.
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

from noisefeat.errors import InputNotFound
from noisefeat.safeio import open_input, read_input, read_text

from noisefeat import split_blocks
from noisefeat.atomic import atomic_write
from noisefeat.pooling import MEAN, POOLINGS, tile_windows

from .exr import read_exr

log = logging.getLogger(__name__)

FORMAT = "noisestop-stack"
VERSION = 1
META = "meta.json"
PARTIAL = "meta.partial.json"
LEVELS_DIR = "levels"
REFERENCE = "reference.exr"
QUICK = "quick.exr"
#: optional extra quick images by kind (see module doc)
EXTRA_QUICK = {"direct": "quick_direct.exr"}
QUICK_NONE = "none"
#: linear value whose sRGB encoding is 0.5: the stand-in quick image when there is none
MID_GREY_LINEAR = 0.21404114

REQUIRED_KEYS = ("format", "version", "scene", "width", "height", "grid", "block", "spp",
                 "reference_spp", "quick", "renderer")
OPTIONAL_KEYS = ("labeler", "thresholds", "tile", "tile_thresholds")
KNOWN_KEYS = REQUIRED_KEYS + OPTIONAL_KEYS


def level_name(spp: int) -> str:
    """File name of the level with `spp` samples per pixel, relative to the stack dir."""
    return f"{LEVELS_DIR}/{int(spp):06d}.exr"


def block_shape(height: int, width: int, grid: Sequence[int] = (4, 4)) -> tuple[int, int]:
    """(bh, bw) of a `grid` cut; the image must divide exactly (as noisefeat.split_blocks)."""
    gh, gw = (int(g) for g in grid)
    if gh < 1 or gw < 1:
        raise ValueError(f"grid must be two positive integers, got {list(grid)}")
    if height % gh or width % gw:
        raise ValueError(f"a {width}x{height} image cannot be cut into a {gh}x{gw} grid "
                         f"of equal blocks (height % {gh} = {height % gh}, width % {gw} = "
                         f"{width % gw})")
    return height // gh, width // gw


# ----------------------------------------------------------------------------- validation

def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def is_pos_int(x: Any) -> bool:
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
    """The tile truth's keys (issue 41): `tile` (pixels) and `tile_thresholds`, one per tile
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


# ----------------------------------------------------------------------------- the stack

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
    #: the tile truth (issue 41): the side of the tiles each block is cut into, and each
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


def read_stacks(root: str | os.PathLike, scenes: Sequence[str] | None = None) -> list[Stack]:
    """The stacks below `root` (only `scenes`, if given), every file of each validated
    (`Stack.validate`): what commands that read a dataset open it with."""
    stacks = [read_stack(p) for p in list_stacks(root)]
    if scenes is not None:
        stacks = [st for st in stacks if st.scene in scenes]
    for st in stacks:
        st.validate()
    return stacks


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
        with open_input(path, _kind(path)) as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        digest = _DIGESTS[sig] = h.hexdigest()
        if len(_DIGESTS) > 100_000:
            _DIGESTS.clear()
    return digest


def _kind(path: Path) -> str:
    return "meta.json" if path.name == META else "EXR" if path.suffix == ".exr" else "file"


def load_json(path: Path) -> Any:
    try:
        return json.loads(read_text(path, _kind(path)))
    except RecursionError:
        raise ValueError(f"{path}: not a stack description (JSON nested too deeply)") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text: {exc}") from exc


def dump_json(path: Path, obj: Mapping) -> None:
    """One top-level key per line (diff- and grep-friendly), known keys first."""
    keys = [k for k in KNOWN_KEYS if k in obj] + [k for k in obj if k not in KNOWN_KEYS]
    body = ",\n".join(f" {json.dumps(k)}: {json.dumps(obj[k])}" for k in keys)
    atomic_write(path, ("{\n" + body + "\n}\n").encode("utf-8"))


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


def list_stacks(root: str | os.PathLike, include_incomplete: bool = False) -> list[Path]:
    """Every stack directory under `root` (root itself included), sorted.

    A directory is a stack if it holds meta.json (or, with `include_incomplete`,
    meta.partial.json); stacks are not searched for nested stacks. A meta.json that is a
    directory is a broken stack: one-line ValueError (it used to be skipped silently).
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


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """A short hash of every stack's meta.json under `root`: results computed on a dataset
    (e.g. a saved model comparison) are only reused on the very same one."""
    h = hashlib.sha256()
    for p in list_stacks(root):
        h.update(p.name.encode() + b"\0" + read_input(p / META, "meta.json"))
    return h.hexdigest()[:16]
