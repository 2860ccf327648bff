"""A mesh's (or volume grid's) element counts read from its header, before Mitsuba loads it:
Mitsuba sizes its buffers from the counts a header states (ply, serialized, .vol) or from the
file's size (obj). Each is read as Mitsuba's loader reads it (src/shapes/{ply.h,obj.cpp,
serialized.cpp}, src/render/volumegrid.cpp, 3.9), its counts bounded by ``CAPS["mesh elements"]``
and by the bytes the file holds; an obj is scanned in chunks for lines of `OBJ_LINE` bytes.
"""
from __future__ import annotations

import os
import struct
import zlib
from typing import BinaryIO

import numpy as np

from noisefeat.safeio import CAPS, InputFileError, open_input, read_named

#: bytes of a ply header read at most
HEAD = 1 << 20
#: Mitsuba's obj reader refuses a line this long or longer (its 1025-byte line buffer)
OBJ_LINE = 1024
#: bytes of an obj read per step of the scan
CHUNK = 4 << 20
#: bytes of a serialized mesh's name read at most
MAX_NAME = 64 << 10
#: a ply property's size in bytes, by its type (ply.h's table, the unofficial names included)
PLY_TYPES = {"char": 1, "uchar": 1, "short": 2, "ushort": 2, "int": 4, "uint": 4, "float": 4, "double": 8,
             "uint8": 1, "uint16": 2, "uint32": 4, "int8": 1, "int16": 2, "int32": 4, "long": 8, "ulong": 8,
             "half": 2, "float16": 2, "float32": 4, "float64": 8}


def _refuse(path: str | os.PathLike, kind: str, why: str) -> InputFileError:
    return InputFileError(f"{path}: {kind} {why}; refused")


def _bound(path: str | os.PathLike, kind: str, count: int, what: str) -> None:
    cap = CAPS["mesh elements"]
    if count > cap:
        raise _refuse(path, kind, f"states {count} {what}, over the limit of {cap}")


def check_ply(path: str | os.PathLike, kind: str) -> None:
    """A ply's element counts: within the cap, and within the bytes after its header."""
    with open_input(path, kind) as f:
        size = os.fstat(f.fileno()).st_size
        head = read_named(f, path, kind, HEAD)
    ascii_, elements, stop = False, [], -1            # elements: [count, row bytes, values per row]
    pos = 0
    while (newline := head.find(b"\n", pos)) >= 0:     # read_line: up to a newline, '\r' dropped
        line, pos = head[pos:newline].replace(b"\r", b""), newline + 1
        words = line.split()
        if words[:1] == [b"end_header"]:
            stop = newline
            break
        if not words or words[0] in (b"comment", b"ply"):
            continue
        if words[0] == b"format" and len(words) > 1:
            ascii_ = words[1] == b"ascii"
        elif words[0] == b"element" and len(words) == 3:
            if not words[2].isdigit():
                raise _refuse(path, kind, f"states an element count that is no plain number: {words[2][:32]!r}")
            elements.append([int(words[2]), 0, 0])
        elif words[0] == b"property" and elements and len(words) >= 3:
            is_list = words[1] == b"list"
            sizes = [PLY_TYPES.get(t.decode("ascii", "replace")) for t in words[1 + is_list:-1]]
            if None in sizes or len(sizes) != 1 + is_list:
                raise _refuse(path, kind, f"has a property Mitsuba does not read: {line[:64]!r}")
            elements[-1][1] += sizes[0] + 3 * sizes[1] if is_list else sizes[0]   # a list: count, 3 items
            elements[-1][2] += 4 if is_list else 1
        else:
            raise _refuse(path, kind, f"has a header line Mitsuba does not read: {line[:64]!r}")
    if stop < 0:
        raise _refuse(path, kind, f"has no ply header (no end_header line within {HEAD} bytes)")
    _bound(path, kind, sum(e[0] for e in elements), "elements")
    # an ASCII value takes two bytes at least (a digit and a separator); the last needs none after it
    need = sum(n * (2 * values if ascii_ else row) for n, row, values in elements) - (1 if ascii_ else 0)
    if need > size - (stop + 1):
        raise _refuse(path, kind, f"states elements of {need} bytes at least, but holds {size - stop - 1} "
                                  "after its header (a cut or forged file)")


def check_obj(path: str | os.PathLike, kind: str) -> None:
    """An obj scanned in chunks: every line under 1024 bytes, its words within the cap."""
    long_line = _refuse(path, kind, f"has a line of {OBJ_LINE} bytes or more, which Mitsuba's obj reader "
                                    "refuses only after reading it whole")
    with open_input(path, kind) as f:
        last_newline, words, offset, in_word = -1, 0, 0, False
        while chunk := read_named(f, path, kind, CHUNK):
            arr = np.frombuffer(chunk, np.uint8)
            ends = np.flatnonzero(arr == 10) + offset
            if ends.size:
                if int(np.diff(ends, prepend=last_newline).max()) > OBJ_LINE:
                    raise long_line
                last_newline = int(ends[-1])
            offset += arr.size
            if offset - last_newline - 1 >= OBJ_LINE:        # the line still open is too long already
                raise long_line
            word = arr > 32
            words += int(np.count_nonzero(word[1:] & ~word[:-1])) + int(bool(word[0]) and not in_word)
            in_word = bool(word[-1])
            _bound(path, kind, words, "elements at most (its words)")


def check_serialized(path: str | os.PathLike, kind: str, shape_index: int = 0) -> None:
    """The vertex and face counts of shape `shape_index`, from its compressed header."""
    with open_input(path, kind) as f:
        size = os.fstat(f.fileno()).st_size
        fmt, version = struct.unpack("<hh", read_named(f, path, kind, 4).ljust(4, b"\0"))
        if fmt != 0x041C or version not in (3, 4):
            raise _refuse(path, kind, "is not a Mitsuba serialized mesh (version 3 or 4)")
        start = 4
        if shape_index != 0:
            start = _dictionary_offset(f, path, kind, size, version, shape_index) + 4
        f.seek(start)
        header = _inflate_head(f, path, kind)
    name_end = header.find(b"\0", 4) if version == 4 else 3
    if name_end < 0 or len(header) < name_end + 17:
        raise _refuse(path, kind, f"has no readable shape header (a name over {MAX_NAME} bytes, or cut)")
    vertices, faces = struct.unpack_from("<QQ", header, name_end + 1)
    _bound(path, kind, vertices + faces, "vertices and faces")


def _dictionary_offset(f: BinaryIO, path: str | os.PathLike, kind: str, size: int, version: int,
                       index: int) -> int:
    """Where shape `index` starts, from the table at the file's end (as serialized.cpp seeks)."""
    if size < 12:
        raise _refuse(path, kind, "has no shape table")
    f.seek(size - 4)
    count = struct.unpack("<I", read_named(f, path, kind, 4))[0]
    if index > count:
        raise _refuse(path, kind, f"has {count} shapes; shape_index {index} is out of range")
    width = 8 if version == 4 else 4
    at = size - width * (count - index) - 4 if version == 4 else size - 4 * (count - index + 1)
    if at < 4:
        raise _refuse(path, kind, "has a shape table larger than the file")
    f.seek(at)
    offset = int.from_bytes(read_named(f, path, kind, width).ljust(width, b"\0"), "little")
    if offset > size - 4:
        raise _refuse(path, kind, f"places shape {index} past its end")
    return offset


def _inflate_head(f: BinaryIO, path: str | os.PathLike, kind: str) -> bytes:
    """The first bytes of the zlib stream at `f`'s position (flags, name, two counts)."""
    inflate, out, read = zlib.decompressobj(), b"", 0
    want = 4 + MAX_NAME + 17
    while len(out) < want and not inflate.eof and read < 16 * want:
        chunk = read_named(f, path, kind, 1 << 16)
        read += len(chunk)
        if not chunk:
            break
        try:
            out += inflate.decompress(chunk, want - len(out))
            while inflate.unconsumed_tail and len(out) < want:
                out += inflate.decompress(inflate.unconsumed_tail, want - len(out))
        except zlib.error:
            raise _refuse(path, kind, "has a shape whose compressed data cannot be read") from None
        if b"\0" in out[4:] and len(out) >= out.find(b"\0", 4) + 17:
            break
    return out


def check_grid(path: str | os.PathLike, kind: str) -> None:
    """A .vol grid: its cells times channels, as 32-bit floats, must be in the file."""
    with open_input(path, kind) as f:
        size = os.fstat(f.fileno()).st_size
        head = read_named(f, path, kind, 48)
    if len(head) < 48 or head[:3] != b"VOL":
        raise _refuse(path, kind, "is not a Mitsuba .vol grid (no VOL header)")
    x, y, z, channels = (v & 0xFFFFFFFF for v in struct.unpack_from("<4i", head, 8))   # uint32 casts
    need = 4 * x * y * z * channels
    if need > size - 48:
        raise _refuse(path, kind, f"states a {x} x {y} x {z} grid of {channels} channels ({need} bytes), "
                                  f"but holds {size - 48}")
