"""One way to open the files the commands read: regular files only, each kind size-capped.

Why: a `reference.exr` linked to /dev/zero hung `evaluate` for minutes while it was hashed,
a sparse 3 GB meta.json took 4 GiB of memory to parse, and a token file naming /dev/zero
grew the server to 20 GiB. Every input is opened here: devices, FIFOs, sockets and links
to them are refused at once (the open never blocks: O_NONBLOCK), and a file larger than
its kind's cap is refused from its size before a byte is read. Each refusal is one line
naming the file (`InputFileError`, a ValueError).
"""
from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path
from typing import Any, BinaryIO

#: largest size, in bytes, of each kind of input file (and, last, the bounds read from headers)
CAPS: dict[str, int] = {
    "meta.json": 16 << 20,        # a stack's metadata: thresholds of ~100k blocks at most
    "flip.json": 1 << 20,         # the criterion's calibrated curve
    "token file": 64 << 10,       # a bearer token
    "scene": 64 << 20,            # a scene's XML
    "included scene": 64 << 20,   # an XML file a scene <include>s
    "mesh": 2 << 30,              # a ply, obj or serialized mesh a scene names (renderer.scenes.scenefiles)
    "texture": 2 << 30,           # a bitmap texture a scene names (an EXR's cap)
    "environment map": 2 << 30,   # an envmap's image (a 16k x 8k float RGB EXR: 1.5 GiB)
    "spectrum": 16 << 20,         # a spectrum's text file (wavelength, value lines)
    "EXR": 2 << 30,               # a level, reference or final image (a 16k x 8k float RGB: 1.5 GiB)
    "EXR header": 1 << 20,        # the header of an EXR (attributes before the offset table)
    "PNG": 1 << 30,               # an 8-bit image an import reads (LISIC levels; 16k x 16k RGBA raw: 1 GiB)
    "JSON": 16 << 20,             # other small JSON records (reports, bundles' manifests)
    "markdown": 64 << 20,         # a document `bench --update` rewrites (BENCHMARKS.md: 0.2 MB)
    "bundle": 2 << 30,            # a model bundle's other files
    "manifest": 16 << 20,         # a model bundle's manifest.json
    "model": 96 << 20,            # a model.skops, packed and unpacked (the bundled one: 44 KB); under 100 MiB
    "transfer head": 256 << 20,   # a transfer bundle's tensors and state
    "weights": 256 << 20,         # safetensors weights (the feature base's: 60 KB; a transfer head's: MBs)
    "checkpoint": 4 << 30,        # a render's checkpoint.npz (its own bound is the frame's: renderer.live.checkpoint)
    "npz": 4 << 30,               # other .npz files (stack caches; each reader bounds it further)
    "file": 2 << 30,              # anything else
    # bounds a file's header states (counts, not bytes; renderer.scenes.image_headers, mesh_headers):
    "image pixels": 1 << 27,      # a texture's or envmap's width x height (16k x 8k; RGBA float: 2 GiB)
    "mesh elements": 1 << 27,     # a mesh's vertices + faces (a ply's elements, an obj's words)
}
#: deepest nesting accepted in an input JSON file (none of ours is deeper than 6)
MAX_JSON_DEPTH = 32


class InputFileError(ValueError):
    """An input file that is not a regular file, too large, or malformed: one line."""


def present(path: str | os.PathLike) -> bool:
    """Whether anything is at `path`: a file, or a link even if broken or looping.

    Why: `Path.exists` follows links, so a link to nothing, or to itself, passes for "no
    file" (a `--resume` whose checkpoint was such a link started over, exit 0); a caller
    that asks `present` hands such a link to `open_input`, which refuses it in one line."""
    return os.path.lexists(path)


def check_regular(path: str | os.PathLike, kind: str = "file") -> int:
    """The size of `path` if it is a regular file (a link to one included) within the cap
    of `kind`; InputFileError otherwise (FileNotFoundError if it does not exist)."""
    with open_input(path, kind) as f:
        return os.fstat(f.fileno()).st_size


def open_input(path: str | os.PathLike, kind: str = "file") -> BinaryIO:
    """`path` opened for binary reading, if it is a regular file within the cap of `kind`."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        what = "is a link to a missing file" if os.path.islink(path) else "does not exist"
        raise FileNotFoundError(f"{path}: {kind} {what}") from None
    except IsADirectoryError:
        raise InputFileError(f"{path}: {kind} is a directory, not a file") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputFileError(f"{path}: {kind} is a loop of symbolic links (it never reaches a file); "
                                 "refused") from None
        raise InputFileError(f"{path}: {kind} cannot be opened ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            what = ("a directory" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "a device")
            raise InputFileError(f"{path}: {kind} is {what}, not a regular file; refused")
        cap = CAPS.get(kind, CAPS["file"])
        if st.st_size > cap:
            raise InputFileError(f"{path}: {kind} is {st.st_size} bytes, over the limit of {cap} bytes "
                                 "for this kind of file; refused")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb")


def read_input(path: str | os.PathLike, kind: str = "file") -> bytes:
    """The bytes of `path` (see `open_input`); never more than the kind's cap, even if the
    file grows while it is read."""
    cap = CAPS.get(kind, CAPS["file"])
    with open_input(path, kind) as f:
        data = read_named(f, path, kind, cap + 1)
    if len(data) > cap:
        raise InputFileError(f"{path}: {kind} grew past the limit of {cap} bytes while it was read; refused")
    return data


def read_named(f: BinaryIO, path: str | os.PathLike, kind: str, size: int = -1) -> bytes:
    """`f.read(size)`, an OS error naming the file (/proc/self/mem passes as a regular file
    of size 0, and its read fails with a bare "[Errno 5] Input/output error")."""
    try:
        return f.read(size)
    except OSError as exc:
        raise InputFileError(f"{path}: {kind} cannot be read ({exc.strerror or exc})") from None


def read_text(path: str | os.PathLike, kind: str = "file") -> str:
    """`read_input` decoded as UTF-8 (an undecodable file is one line naming it)."""
    data = read_input(path, kind)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: {kind} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def read_json(path: str | os.PathLike, kind: str = "JSON") -> Any:
    """A JSON input file, parsed; too deep, not JSON, or not a regular file within its cap:
    one line naming the file."""
    text = read_text(path, kind)
    depth, deepest = 0, 0
    in_string = escaped = False
    for ch in text if len(text) < (1 << 16) else ():      # small files: exact scan below
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    if deepest > MAX_JSON_DEPTH:
        raise InputFileError(f"{path}: {kind} nests {deepest} deep (at most {MAX_JSON_DEPTH}); refused")
    try:
        return json.loads(text)
    except RecursionError:
        raise InputFileError(f"{path}: {kind} nests too deep to read; refused") from None
    except ValueError as exc:
        raise InputFileError(f"{path}: {kind} is not valid JSON ({exc})") from None
