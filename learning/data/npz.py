"""Reading .npz files that may be damaged or forged: checkpoints and stack caches.

Why: with numpy's reader alone, a truncated or byte-flipped checkpoint.npz on `--resume`
ends in BadZipFile, a CRC error or a KeyError traceback. numpy's reader trusts each member's
header: a header that claims a larger shape than the member holds makes it allocate the
claimed size first. Here every member's header is read and its claimed size compared
with the bytes the member really holds before any array is built, object arrays are
refused (no pickle, ever), and every failure is a ValueError naming the file.
"""
from __future__ import annotations

import hashlib
import io
import math
import os
import zipfile
from collections.abc import Mapping
from typing import Any
from pathlib import Path

import numpy as np

DIGEST_KEY = "sha256"


def read_npz(path: str | os.PathLike, max_bytes: int | None = None, kind: str = "npz") -> dict[str, np.ndarray]:
    """Every array of the .npz at `path` by name; ValueError if anything about it is off.
    The file is opened through `noisefeat.safeio` (a regular file within the cap of its
    `kind`: a link to /dev/zero or a FIFO is refused at once, in one line naming it);
    `max_bytes` (default: the kind's cap) bounds the file and what its members' headers say
    they unpack to, checked before any is inflated; zipfile inflates a member no further
    than its header's size."""
    from noisefeat.safeio import CAPS, open_input

    path = Path(path)
    with open_input(path, kind) as raw:
        return _read_npz(path, raw, CAPS.get(kind, CAPS["file"]) if max_bytes is None else max_bytes)


def _read_npz(path: Path, raw: Any, max_bytes: int | None) -> dict[str, np.ndarray]:
    try:
        size = os.fstat(raw.fileno()).st_size
        if max_bytes is not None and size > max_bytes:
            raise ValueError(f"{size} bytes, more than the {max_bytes} expected")
        with zipfile.ZipFile(raw) as zf:
            out: dict[str, np.ndarray] = {}
            unpacked = sum(i.file_size for i in zf.infolist())
            if max_bytes is not None and unpacked > max_bytes:
                raise ValueError(f"unpacks to {unpacked} bytes, more than the {max_bytes} expected")
            for info in zf.infolist():
                if not info.filename.endswith(".npy") or info.filename[:-4] in out:
                    raise ValueError(f"unexpected member {info.filename!r}")
                out[info.filename[:-4]] = _read_member(zf, info)
            return out
    except Exception as exc:   # zipfile and numpy's header parser raise a dozen kinds on damage
        raise ValueError(f"{path}: damaged or not an .npz file ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]})") from None


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> np.ndarray:
    with zf.open(info) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"{info.filename}: unsupported .npy version {version}")
        if dtype.hasobject:
            raise ValueError(f"{info.filename}: object arrays are refused")
        claimed = math.prod(shape) * dtype.itemsize
        if f.tell() + claimed != info.file_size:
            raise ValueError(f"{info.filename}: header claims {claimed} bytes of data, the member holds "
                             f"{info.file_size - f.tell()}")
        data = f.read(claimed)              # CRC-32 is checked by zipfile at the end of the read
        if len(data) != claimed or f.read(1):
            raise ValueError(f"{info.filename}: truncated")
    arr = np.frombuffer(data, dtype=dtype)
    arr = arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)
    return arr.copy()


def digest(arrays: Mapping[str, np.ndarray]) -> str:
    """SHA-256 over every array's name, dtype, shape and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        if name == DIGEST_KEY:
            continue
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def savez_bytes(arrays: Mapping[str, np.ndarray], with_digest: bool = False) -> bytes:
    """np.savez into memory (for an atomic write), with a digest member if asked."""
    buf = io.BytesIO()
    payload = dict(arrays)
    if with_digest:
        payload[DIGEST_KEY] = np.array(digest(arrays))
    np.savez(buf, **payload)
    return buf.getvalue()


def check_digest(path: str | os.PathLike, arrays: Mapping[str, np.ndarray]) -> None:
    """ValueError unless `arrays` carry a digest that matches their content."""
    stored = arrays.get(DIGEST_KEY)
    if stored is None or stored.shape != () or stored.dtype.kind != "U":
        raise ValueError(f"{path}: no content digest")
    if str(stored) != digest(arrays):
        raise ValueError(f"{path}: content does not match its digest (changed or damaged)")
