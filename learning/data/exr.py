"""Image files of the dataset: EXR (linear RGB) and PNG (8-bit sRGB), read and written safely.

Everything goes through Mitsuba's `Bitmap` (already a dependency, handles OpenEXR and PNG).
Writes are atomic: the file is encoded in memory, written to a temporary name in the
target directory, fsync'ed and renamed over the final name, so a reader never sees a
half-written image (DESIGN "Dataset format v1"). Reads turn Mitsuba's RuntimeError for a
truncated or corrupt file into a ValueError that names the file.

Limit worth knowing: OpenEXR has no checksum, so bytes flipped *inside* a complete file
can decode to wrong pixels without any error; truncation is always detected.
"""
from __future__ import annotations

import contextlib
import logging
import os
import secrets
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

def _mi():
    """Mitsuba with the process's variant set (Bitmap needs one): the one choice of
    `learning.data.variant`, so reading an EXR first never pins a slower variant."""
    from .variant import select_variant

    select_variant()
    import mitsuba as mi

    return mi


@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """An OSError raised while writing `path` names it: a full disk's write() and fsync()
    raise "No space left on device" without any file name."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise type(exc)(exc.errno, exc.strerror or str(exc), str(path)) from None


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` so that the file is either absent/old or complete and new."""
    path = Path(path)
    with naming(path):
        _atomic_write_bytes(path, data)


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    # O_EXCL: never clobber another writer's temp file; mode 0o666 lets the umask decide
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def _fsync_dir(directory: Path) -> None:
    """Make the rename durable too (best effort: not every filesystem allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _check_rgb(arr: np.ndarray, what: str, path: Path) -> None:
    if not isinstance(arr, np.ndarray):
        raise ValueError(f"{path}: {what} must be a numpy array, got {type(arr).__name__}")
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{path}: {what} must have shape [H, W, 3] with H, W > 0, got {arr.shape}")


def _encode(bitmap, fmt) -> bytes:
    mi = _mi()
    stream = mi.MemoryStream()
    bitmap.write(stream, fmt)
    return bytes(stream.raw_buffer())[: stream.size()]


def write_exr(path: str | os.PathLike, rgb: np.ndarray, half: bool = False) -> None:
    """Write linear RGB [H, W, 3] as an EXR (float32, or half with `half=True`), atomically.

    Non-finite values are stored as they are (renderers emit them; `check` reports them).
    Half floats overflow to Inf above 65504.
    """
    path = Path(path)
    _check_rgb(rgb, "EXR image", path)
    if not np.issubdtype(rgb.dtype, np.number):
        raise ValueError(f"{path}: EXR image must be numeric, got dtype {rgb.dtype}")
    mi = _mi()
    data = np.ascontiguousarray(rgb, dtype=np.float32)
    bm = mi.Bitmap(data, pixel_format=mi.Bitmap.PixelFormat.RGB)
    if half:
        bm = bm.convert(component_format=mi.Struct.Type.Float16)
    atomic_write_bytes(path, _encode(bm, mi.Bitmap.FileFormat.OpenEXR))


def _load(path: Path, fmt, kind: str):
    mi = _mi()
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such {kind} file")
    try:
        return mi.Bitmap(str(path), fmt)
    except RuntimeError as exc:
        raise ValueError(f"{path}: unreadable {kind} (truncated or corrupt?): {exc}") from exc


def _read_rgb(path: str | os.PathLike, kind: str, srgb: bool) -> np.ndarray:
    """A Bitmap file as float32 [H, W, 3] (alpha dropped, grey expanded to RGB)."""
    path = Path(path)
    mi = _mi()
    fmt = mi.Bitmap.FileFormat.OpenEXR if kind == "EXR" else mi.Bitmap.FileFormat.PNG
    bm = _load(path, fmt, kind)
    if bm.pixel_format() == mi.Bitmap.PixelFormat.MultiChannel:   # e.g. final.exr: RGB + spp + mask
        channels = _channels(bm, path)
        if not {"R", "G", "B"} <= set(channels):
            raise ValueError(f"{path}: no R, G, B channels among {sorted(channels)}")
        return np.stack([channels[c] for c in "RGB"], axis=-1)
    try:
        bm = bm.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=srgb)
    except RuntimeError as exc:
        raise ValueError(f"{path}: cannot convert {kind} to RGB: {exc}") from exc
    out = np.array(bm, dtype=np.float32, copy=True)
    if out.ndim == 2:
        out = np.repeat(out[:, :, None], 3, axis=2)
    return out


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """EXR -> float32 [H, W, 3] linear RGB (alpha dropped, grey expanded to RGB; of a
    multi-channel file its R, G and B channels)."""
    return _read_rgb(path, "EXR", srgb=False)


def _channels(bm: Any, path: Path) -> dict[str, np.ndarray]:
    try:
        names = [field.name for field in bm.struct_()]
        data = np.array(bm, copy=True).astype(np.float32)
    except RuntimeError as exc:
        raise ValueError(f"{path}: unreadable channels: {exc}") from exc
    data = data.reshape(data.shape[0], data.shape[1], len(names))
    return {name: data[..., i] for i, name in enumerate(names)}


def read_exr_channels(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every channel of an EXR by name, float32 [H, W] each (final.exr: R, G, B, spp, converged)."""
    path = Path(path)
    return _channels(_load(path, _mi().Bitmap.FileFormat.OpenEXR, "EXR"), path)


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
    mi = _mi()
    bm = mi.Bitmap(np.ascontiguousarray(np.stack(arrays, axis=-1)),
                   pixel_format=mi.Bitmap.PixelFormat.MultiChannel, channel_names=list(channels))
    atomic_write_bytes(path, _encode(bm, mi.Bitmap.FileFormat.OpenEXR))


def write_png(path: str | os.PathLike, srgb8: np.ndarray) -> None:
    """Write an 8-bit sRGB image [H, W, 3] uint8 as PNG, atomically."""
    path = Path(path)
    _check_rgb(srgb8, "PNG image", path)
    if srgb8.dtype != np.uint8:
        raise ValueError(f"{path}: PNG image must be uint8, got dtype {srgb8.dtype}")
    mi = _mi()
    bm = mi.Bitmap(np.ascontiguousarray(srgb8), pixel_format=mi.Bitmap.PixelFormat.RGB)
    bm.set_srgb_gamma(True)
    atomic_write_bytes(path, _encode(bm, mi.Bitmap.FileFormat.PNG))


def read_png(path: str | os.PathLike) -> np.ndarray:
    """PNG -> float32 [H, W, 3] in [0, 1], still sRGB-encoded (display values).

    Grey PNGs are expanded to RGB, alpha is dropped, 16-bit PNGs are scaled to [0, 1].
    """
    return np.clip(_read_rgb(path, "PNG", srgb=True), 0.0, 1.0)
