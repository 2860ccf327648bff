"""An image's size read from its header, as Mitsuba's Bitmap reads it, before Mitsuba decodes it:
a small PNG may hold a decompression bomb, so the header, not the file's size, tells the pixels.

The format is told as ``Bitmap::detect_file_format`` tells it (src/core/bitmap.cpp, 3.9), the size
read as its reader reads it (integer casts included), from the header alone. Refused in one line:
over ``CAPS["image pixels"]``, a header not read within `HEAD` bytes, a format Mitsuba does not read.
"""
from __future__ import annotations

import os
import re
import struct
from typing import BinaryIO

from noisefeat.safeio import CAPS, InputFileError, open_input, read_named

#: bytes of a header read at most (a PFM, PPM or RGBE header, a JPEG's marker walk)
HEAD = 64 << 10
#: JPEG segments walked at most before the frame header (SOF)
MAX_JPEG_SEGMENTS = 4096
#: the JPEG start-of-frame markers (libjpeg's SOF0..SOF15, less DHT, JPG and DAC)
_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_EXR_MULTIPART = 0x1000


class _Unreadable(Exception):
    """The header is not one this module can read (turned into an InputFileError)."""


def check_image(path: str | os.PathLike, kind: str) -> None:
    """Refuse, in one line, an image (a texture or an environment map) whose header says it
    has more pixels than ``CAPS["image pixels"]``, or whose header cannot be read."""
    with open_input(path, kind) as f:
        size = os.fstat(f.fileno()).st_size
        try:
            fmt, width, height = image_size(f, size, path, kind)
        except (_Unreadable, struct.error) as exc:
            raise InputFileError(f"{path}: {kind} has no header Mitsuba could read ({exc or 'cut short'}); "
                                 "refused") from None
    cap = CAPS["image pixels"]
    if width * height > cap:
        raise InputFileError(f"{path}: {kind} is a {fmt} of {width} x {height} pixels, over the limit of "
                             f"{cap} pixels; refused")


def image_size(f: BinaryIO, size: int, path: str | os.PathLike, kind: str) -> tuple[str, int, int]:
    """(format, width, height) of the image open in `f` (`size` bytes), as Mitsuba reads them."""
    head = read_named(f, path, kind, HEAD)
    for magic, reader in ((b"BM", _bmp), (b"#?", _rgbe), (b"PF", _pfm), (b"Pf", _pfm), (b"P6", _ppm),
                          (b"\x89PNG\r\n\x1a\n", _png)):       # no magic is another's prefix
        if head.startswith(magic):
            return reader(head)
    if head[:2] == b"\xff\xd8":
        return _jpeg(f, path, kind)
    if head[:4] == _EXR_MAGIC:
        return _exr(f, size, path, kind)
    if size >= 18:
        f.seek(size - 18)
        footer = read_named(f, path, kind, 18)
        if footer == b"TRUEVISION-XFILE.\0":
            return _tga(head)
    raise _Unreadable("not a PNG, JPEG, OpenEXR, RGBE, PFM, PPM, TGA or BMP image")


def _bmp(head: bytes) -> tuple[str, int, int]:
    width, height = struct.unpack_from("<ii", head, 18)
    return "BMP", max(width, 0), abs(height)          # Mitsuba refuses width <= 0 itself


def _tga(head: bytes) -> tuple[str, int, int]:
    width, height = struct.unpack_from("<hh", head, 12)
    return "TGA", width & 0xFFFFFFFF, height & 0xFFFFFFFF     # (uint32_t) of an int16, as Mitsuba casts


def _png(head: bytes) -> tuple[str, int, int]:
    if head[12:16] != b"IHDR":
        raise _Unreadable("no IHDR chunk first")
    width, height = struct.unpack_from(">II", head, 16)
    return "PNG", width, height


def _number(token: bytes, what: str) -> int:
    """A header's integer: plain digits, below 2**32 (Mitsuba's readers cast to uint32)."""
    if not token.isdigit() or int(token) >= 1 << 32:
        raise _Unreadable(f"{what} {token[:32]!r} is not a plain 32-bit number")
    return int(token)


def _rgbe(head: bytes) -> tuple[str, int, int]:
    """Lines after the first (read_line: '\\n' ends one, '\\r' is dropped) until "-Y H +X W"."""
    lines = head.split(b"\n")
    for line in lines[1:-1]:                   # the last piece may be cut by HEAD
        tokens = [t for t in re.split(rb"[, ]", line.replace(b"\r", b"")) if t]
        if len(tokens) == 4 and tokens[0] == b"-Y" and tokens[2] == b"+X":
            return "RGBE", _number(tokens[3], "width"), _number(tokens[1], "height")
    raise _Unreadable(f'no "-Y height +X width" line in the first {HEAD} bytes')


def _pfm(head: bytes) -> tuple[str, int, int]:
    tokens = head[3:].split(None, 3)           # read_token: runs between isspace() bytes
    if len(tokens) < 4:
        raise _Unreadable(f"no width, height and scale in the first {HEAD} bytes")
    return "PFM", _number(tokens[0], "width"), _number(tokens[1], "height")


def _ppm(head: bytes) -> tuple[str, int, int]:
    fields = [t for t in re.split(rb"[ \t\n\r]", head) if t]
    if len(fields) < 5 or fields[0] != b"P6":  # four fields and the pixels after them
        raise _Unreadable(f"no P6 width height maxval in the first {HEAD} bytes")
    return "PPM", _number(fields[1], "width"), _number(fields[2], "height")


def _jpeg(f: BinaryIO, path: str | os.PathLike, kind: str) -> tuple[str, int, int]:
    """The marker segments after SOI, walked (seeking past each) to the first frame header."""
    pos = 2
    for _ in range(MAX_JPEG_SEGMENTS):
        f.seek(pos)
        marker = read_named(f, path, kind, 2)
        while marker[:1] == b"\xff" and marker[1:] == b"\xff":     # fill bytes
            pos += 1
            marker = marker[1:] + read_named(f, path, kind, 1)
        if len(marker) < 2 or marker[0] != 0xFF:
            raise _Unreadable("a JPEG segment does not start with a marker")
        code = marker[1]
        if code in (0x01, *range(0xD0, 0xD8)):        # standalone markers
            pos += 2
            continue
        if code in (0xD9, 0xDA):
            raise _Unreadable("no JPEG frame header before the image data")
        length = struct.unpack(">H", read_named(f, path, kind, 2))[0]
        if code in _SOF:
            _, height, width = struct.unpack(">BHH", read_named(f, path, kind, 5))
            if height == 0:
                raise _Unreadable("a JPEG frame of height 0 (DNL, which libjpeg does not read)")
            return "JPEG", width, height
        if length < 2:
            raise _Unreadable("a JPEG segment shorter than its length field")
        pos += 2 + length
    raise _Unreadable(f"no JPEG frame header within {MAX_JPEG_SEGMENTS} segments")


def _exr(f: BinaryIO, size: int, path: str | os.PathLike, kind: str) -> tuple[str, int, int]:
    """The largest data window of the file's headers (one per part), read within
    ``CAPS["EXR header"]`` bytes; a scanline part's chunk table must fit in the file (`size`) too."""
    f.seek(0)
    cap = CAPS["EXR header"]
    data = read_named(f, path, kind, cap)
    multipart = struct.unpack_from("<I", data, 4)[0] & _EXR_MULTIPART
    pos, widest = 8, None
    while True:
        attrs: dict[bytes, bytes] = {}
        while True:                            # one header: name\0 type\0 size value ... \0
            if pos >= len(data):
                raise _Unreadable(f"an OpenEXR header longer than {cap} bytes")
            if data[pos] == 0:
                pos += 1
                break
            name_end = data.index(b"\0", pos)
            type_end = data.index(b"\0", name_end + 1)
            length = struct.unpack_from("<i", data, type_end + 1)[0]
            if length < 0 or type_end + 5 + length > len(data):
                raise _Unreadable(f"an OpenEXR header longer than {cap} bytes")
            attrs[data[pos:name_end]] = data[type_end + 5:type_end + 5 + length]
            pos = type_end + 5 + length
        if not attrs:                          # a multi-part file's empty header ends the list
            break
        if len(attrs.get(b"dataWindow", b"")) != 16:
            raise _Unreadable("an OpenEXR header without a dataWindow")
        x0, y0, x1, y1 = struct.unpack("<4i", attrs[b"dataWindow"])
        width, height = max(x1 - x0 + 1, 0), max(y1 - y0 + 1, 0)
        if width * height > CAPS["image pixels"]:
            return "OpenEXR", width, height            # refused for its pixels
        if b"tiles" not in attrs and 8 * height > size:     # one offset per line at least, if uncompressed
            lines = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256, 10: 256, 11: 32}
            if 8 * -(-height // lines.get((attrs.get(b"compression") or b"\0")[0], 1)) > size:
                raise _Unreadable(f"its chunk table ({height} lines) is larger than the file")
        if widest is None or width * height > widest[0] * widest[1]:
            widest = (width, height)
        if not multipart:
            break
    if widest is None:
        raise _Unreadable("an OpenEXR file without a part")
    return "OpenEXR", *widest
