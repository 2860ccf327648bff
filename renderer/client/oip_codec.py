"""The Open Inference Protocol v2 binary tensor codec of the client and the server (`service.oip`), so
the two ends cannot drift apart (numpy only; in `renderer`, which `service` may import). A body is a
JSON header of `Inference-Header-Content-Length` bytes, then the raw little-endian row-major tensors
in the header's order, each of `parameters.binary_data_size` bytes (REFERENCES.md). Problems are
`WireError`: the server answers it as a 400, the client raises it naming the URL.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

HEADER_LENGTH = "Inference-Header-Content-Length"
BINARY_EXTENSION = "binary_tensor_data"

#: OIP datatypes and their little-endian numpy dtypes (BYTES, strings, has no use here)
DATATYPES: dict[str, np.dtype] = {
    "BOOL": np.dtype("?"), "UINT8": np.dtype("u1"), "UINT16": np.dtype("<u2"),
    "UINT32": np.dtype("<u4"), "UINT64": np.dtype("<u8"), "INT8": np.dtype("i1"),
    "INT16": np.dtype("<i2"), "INT32": np.dtype("<i4"), "INT64": np.dtype("<i8"),
    "FP16": np.dtype("<f2"), "FP32": np.dtype("<f4"), "FP64": np.dtype("<f8"),
}


class WireError(ValueError):
    """A binary body whose parts do not add up (lengths, sizes, datatypes)."""


def tensor_bytes(arr: np.ndarray, datatype: str | None = None) -> bytes:
    """The wire bytes of a tensor: little-endian, row-major, as `datatype` (default: its own)."""
    arr = np.asarray(arr)
    dtype = DATATYPES[datatype] if datatype is not None else arr.dtype.newbyteorder("<")
    return np.ascontiguousarray(arr, dtype=dtype).tobytes()


def join_body(header: bytes, tensors: Sequence[bytes]) -> tuple[bytes, int | None]:
    """(body, header length) of a message: the JSON header then the binary tensors; the
    header length is None when no tensor is binary (a plain JSON body)."""
    return (header + b"".join(tensors), len(header)) if tensors else (header, None)


def split_body(body: bytes | memoryview, header_length: int | None) -> tuple[bytes | memoryview, bytes | memoryview]:
    """(JSON header, binary tail) of a body (slices of a memoryview: no copy); without a
    header length the whole body is the header."""
    if header_length is None:
        return body, body[len(body):]
    if not 0 < header_length <= len(body):
        raise WireError(f"{HEADER_LENGTH} is {header_length} but the body holds {len(body)} bytes")
    return body[:header_length], body[header_length:]


def read_tensor(tail: bytes | memoryview, datatype: str, shape: Sequence[int], size: int, offset: int,
                what: str) -> np.ndarray:
    """The tensor of `size` bytes at `offset` of the binary tail, `what` naming it in errors:
    a view (no copy) when the memory is writable and aligned, else a copy (torch needs both)."""
    if datatype not in DATATYPES:
        raise WireError(f"{what}: unsupported datatype {datatype!r}")
    dtype = DATATYPES[datatype]
    count = math.prod(int(s) for s in shape)
    if size != count * dtype.itemsize:
        raise WireError(f"{what}: binary_data_size {size} does not match shape {list(shape)} of {datatype} "
                        f"({count * dtype.itemsize} bytes)")
    if offset + size > len(tail):
        raise WireError(f"{what}: binary data truncated (needs {size} bytes at offset {offset}, "
                        f"{len(tail) - offset} left)")
    flat = np.frombuffer(tail, dtype=dtype, count=count, offset=offset)
    if not flat.flags.aligned or not flat.flags.writeable:
        flat = flat.copy()
    return flat.reshape(tuple(int(s) for s in shape))
