"""Image files of the dataset: EXR (linear RGB) and PNG (8-bit sRGB), read and written safely.

EXR goes through the OpenEXR project's own Python bindings (`OpenEXR`), PNG through Pillow:
neither needs Mitsuba, so the dataset format reads and writes with the core install. Both
decode bytes that `noisefeat.safeio` read (regular files only, a size cap per kind); neither
library opens a path itself.
Files written here use the layout Mitsuba writes (scanlines, PIZ compression, channels
R, G, B plus any named extras), and files Mitsuba wrote read back bit for bit as
`mitsuba.Bitmap` read them (tests/learning/test_exr_io.py checks both ways when Mitsuba is there).

Writes are atomic: the file is encoded in memory, written to a temporary name in the
target directory, fsync'ed and renamed over the final name, so a reader never sees a
half-written image (DESIGN "Dataset format v1"). Reads check a single-part scanline EXR's
header and chunk table against the file's length before decoding, so a truncated file is
a ValueError naming it (and nothing from the C library on stderr); any other decoding
failure is a ValueError naming the file too.

Limit worth knowing: OpenEXR has no checksum, so bytes flipped *inside* a complete file
can decode to wrong pixels without any error; truncation is always detected.
"""
from __future__ import annotations

import io
import logging
import math
import os
import struct
from pathlib import Path

import numpy as np

from noisefeat.atomic import atomic_write
from noisefeat.safeio import CAPS, read_input

log = logging.getLogger(__name__)

#: rows of pixels per chunk of a scanline EXR, by the header's compression code
_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256,
                    10: 256, 11: 32}
_PIZ = 4
_MAGIC = 20000630
_TILED, _NON_IMAGE, _MULTIPART = 0x200, 0x800, 0x1000
#: channels Mitsuba puts first, in this order, when it reads a file (the rest keep file order)
_FIRST = ("R", "G", "B", "A")


def _openexr():
    from noisefeat.extras import require

    return require("OpenEXR")


def _pil_image():
    from noisefeat.extras import require

    return require("PIL.Image")


def _check_rgb(arr: np.ndarray, what: str, path: Path) -> None:
    if not isinstance(arr, np.ndarray):
        raise ValueError(f"{path}: {what} must be a numpy array, got {type(arr).__name__}")
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: {what} must have shape [H, W, 3] with H, W > 0, got {arr.shape}")


# ----------------------------------------------------------------------------- EXR

def _encode_exr(channels: dict[str, np.ndarray]) -> bytes:
    """One single-part scanline EXR, PIZ-compressed as Mitsuba writes it, in memory."""
    exr = _openexr()
    header = {"compression": exr.PIZ_COMPRESSION, "type": exr.scanlineimage,
              "generatedBy": "noisestop"}
    buf = io.BytesIO()
    exr.File(header, {name: np.ascontiguousarray(a) for name, a in channels.items()}).write(buf)
    return buf.getvalue()


def write_exr(path: str | os.PathLike, rgb: np.ndarray, half: bool = False) -> None:
    """Write linear RGB [H, W, 3] as an EXR (float32, or half with `half=True`), atomically.

    Non-finite values are stored as they are (renderers emit them; `check` reports them).
    Half floats round to nearest even and overflow to Inf above 65504.
    """
    path = Path(path)
    _check_rgb(rgb, "EXR image", path)
    if not np.issubdtype(rgb.dtype, np.number):
        raise ValueError(f"{path}: EXR image must be numeric, got dtype {rgb.dtype}")
    data = np.asarray(rgb, dtype=np.float32)
    if half:
        with np.errstate(over="ignore"):
            data = data.astype(np.float16)
    atomic_write(path, _encode_exr({c: data[..., i] for i, c in enumerate("RGB")}))


def write_exr_channels(path: str | os.PathLike, channels: dict[str, np.ndarray]) -> None:
    """Write named float32 [H, W] channels as one EXR, atomically (readers that know only
    RGB read the R, G and B channels)."""
    path = Path(path)
    if not channels:
        raise ValueError(f"{path}: no channels to write")
    arrays = [np.asarray(v, np.float32) for v in channels.values()]
    if len({a.shape for a in arrays}) != 1 or arrays[0].ndim != 2:
        raise ValueError(f"{path}: channels must be [H, W] arrays of one shape, got "
                         f"{[a.shape for a in arrays]}")
    if arrays[0].size == 0:
        raise ValueError(f"{path}: channels must have H, W > 0, got {arrays[0].shape}")
    atomic_write(path, _encode_exr(dict(zip(channels, arrays))))


def _check_exr_layout(data: bytes, path: Path) -> None:
    """Raise ValueError if a single-part scanline EXR is cut short: its header, its chunk
    offset table or a chunk runs past the end of `data`. Other kinds (tiled, deep,
    multi-part) are left to OpenEXR's own checks."""
    size = len(data)

    def cut(what: str) -> ValueError:
        return ValueError(f"{path}: unreadable EXR (truncated or corrupt?): {what} runs past the "
                          f"end of the file ({size} bytes)")

    if size < 8 or struct.unpack_from("<i", data, 0)[0] != _MAGIC:
        raise ValueError(f"{path}: not an EXR file (no OpenEXR magic number)")
    flags = struct.unpack_from("<I", data, 4)[0]
    pos, compression, window = 8, None, None
    while True:
        if pos >= size:
            raise cut("the header")
        if pos > CAPS["EXR header"]:
            raise ValueError(f"{path}: unreadable EXR: header over {CAPS['EXR header']} bytes; refused")
        if data[pos] == 0:          # the header's terminating null
            pos += 1
            break
        name_end = data.find(b"\0", pos)
        type_end = data.find(b"\0", name_end + 1) if name_end >= 0 else -1
        if type_end < 0 or type_end + 5 > size:
            raise cut("the header")
        name = data[pos:name_end]
        length = struct.unpack_from("<i", data, type_end + 1)[0]
        value = type_end + 5
        if length < 0 or value + length > size:
            raise cut(f"header attribute {name.decode(errors='replace')!r}")
        if name == b"compression" and length == 1:
            compression = data[value]
        elif name == b"dataWindow" and length == 16:
            window = struct.unpack_from("<4i", data, value)
        pos = value + length
    if flags & (_TILED | _NON_IMAGE | _MULTIPART) or window is None or compression not in _LINES_PER_CHUNK:
        return
    rows = window[3] - window[1] + 1
    if rows < 1 or window[2] < window[0]:
        raise ValueError(f"{path}: unreadable EXR: empty data window {window}")
    chunks = math.ceil(rows / _LINES_PER_CHUNK[compression])
    table_end = pos + 8 * chunks
    if table_end > size:
        raise cut("the chunk offset table")
    for i, offset in enumerate(struct.unpack_from(f"<{chunks}Q", data, pos)):
        if offset < table_end or offset + 8 > size:
            raise cut(f"chunk {i} of {chunks}")
        y, packed = struct.unpack_from("<ii", data, offset)
        if packed <= 0:
            raise ValueError(f"{path}: unreadable EXR: chunk {i} of {chunks} is empty (zero-filled or corrupt data)")
        if offset + 8 + packed > size:
            raise cut(f"chunk {i} of {chunks}")
        if y != window[1] + i * _LINES_PER_CHUNK[compression]:     # zero-filled or shuffled data
            raise ValueError(f"{path}: unreadable EXR: chunk {i} of {chunks} is not the rows it should hold "
                             f"(line {y}, expected {window[1] + i * _LINES_PER_CHUNK[compression]}): "
                             "zero-filled or corrupt data")


def _read_exr_file(path: str | os.PathLike) -> tuple[Path, dict[str, np.ndarray]]:
    """Every channel of an EXR's first part as float32 [H, W], in the order Mitsuba's
    Bitmap gives them: R, G, B, A first, then the others in file order (alphabetical)."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise FileNotFoundError(f"{path}: no such EXR file")
    data = read_input(path, "EXR")
    _check_exr_layout(data, path)
    exr = _openexr()
    try:
        with exr.File(io.BytesIO(data), separate_channels=True) as f:
            raw = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as exc:      # the bindings raise RuntimeError, ValueError, ... by case
        raise ValueError(f"{path}: unreadable EXR (truncated or corrupt?): {exc}") from exc
    shapes = {np.shape(a) for a in raw.values()}
    if not raw or len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"{path}: unreadable EXR channels: expected full-resolution [H, W] "
                         f"channels, got { {n: np.shape(a) for n, a in raw.items()} }")
    order = [c for c in _FIRST if c in raw] + [c for c in raw if c not in _FIRST]
    return path, {name: np.asarray(raw[name]).astype(np.float32) for name in order}


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """EXR -> float32 [H, W, 3] linear RGB (alpha dropped, grey Y expanded to RGB; of a
    multi-channel file its R, G and B channels)."""
    path, channels = _read_exr_file(path)
    if {"R", "G", "B"} <= set(channels):
        return np.stack([channels[c] for c in "RGB"], axis=-1)
    if set(channels) in ({"Y"}, {"Y", "A"}):
        return np.repeat(channels["Y"][:, :, None], 3, axis=2)
    raise ValueError(f"{path}: no R, G, B channels among {sorted(channels)}")


def read_exr_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of an EXR by name, float32 [H, W] each (final.exr: R, G, B, converged, spp)."""
    return _read_exr_file(path)[1]


# ----------------------------------------------------------------------------- PNG

def write_png(path: str | os.PathLike, srgb8: np.ndarray) -> None:
    """Write an 8-bit sRGB image [H, W, 3] uint8 as PNG, atomically."""
    path = Path(path)
    _check_rgb(srgb8, "PNG image", path)
    if srgb8.dtype != np.uint8:
        raise ValueError(f"{path}: PNG image must be uint8, got dtype {srgb8.dtype}")
    image = _pil_image()
    buf = io.BytesIO()
    image.fromarray(np.ascontiguousarray(srgb8), "RGB").save(buf, format="PNG")
    atomic_write(path, buf.getvalue())


def read_png(path: str | os.PathLike) -> np.ndarray:
    """PNG -> float32 [H, W, 3] in [0, 1], still sRGB-encoded (display values): an 8-bit
    value v is v / 255 in float32, a 16-bit grey one v / 65535.

    Grey PNGs are expanded to RGB, alpha is dropped, palettes are looked up. 16-bit colour
    PNGs are refused (Pillow would read them as 8-bit). The bytes are read through
    `noisefeat.safeio` (a regular file within the PNG cap) and decoded from memory.
    """
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise FileNotFoundError(f"{path}: no such PNG file")
    data = read_input(path, "PNG")
    image = _pil_image()
    try:
        with image.open(io.BytesIO(data), formats=["PNG"]) as im:
            colour16 = im.mode in ("RGB", "RGBA") and any(";16" in str(t[3]) for t in im.tile)
            if im.mode in ("I;16", "I;16B", "I"):
                scale, arr = 65535.0, np.asarray(im, dtype=np.float64)
            else:
                scale, arr = 255.0, np.asarray(im.convert("RGB") if im.mode != "RGB" else im)
    except Exception as exc:     # Pillow raises OSError, SyntaxError, ValueError, ... by damage
        raise ValueError(f"{path}: unreadable PNG (truncated or corrupt?): {exc}") from exc
    if colour16:
        raise ValueError(f"{path}: 16-bit colour PNGs are not supported; convert it to 8-bit")
    out = (arr.astype(np.float32) / np.float32(scale)) if scale == 255.0 else (arr / scale).astype(np.float32)
    if out.ndim == 2:
        out = np.repeat(out[:, :, None], 3, axis=2)
    return np.clip(out, 0.0, 1.0)
