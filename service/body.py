"""Reading a request body into one buffer, its binary tensors aligned where they will be used.

Why not Starlette's `request.body()`: it joins a list of chunks, twice the body at its peak;
and a body placed at `TENSOR_ALIGNMENT` lets oip.decode_tensors use the tensors in place,
as numpy views of the body, with no copy (docs/benchmarks/service.md).
"""
from __future__ import annotations

import numpy as np
from starlette.requests import ClientDisconnect, Request

from .oip import ApiError

#: the binary tensors of a request are placed at this alignment in memory (`read_body`), so
#: that they are used where they arrived, as numpy views (oip.decode_tensors), with no copy
TENSOR_ALIGNMENT = 64


#: bodies up to this size get their whole buffer (by Content-Length) when they start; larger
#: ones grow theirs as bytes arrive (doubling), so that a client declaring a large body and
#: sending little holds little memory and address space
PREALLOCATE = 8 << 20


def _aligned(size: int, align: int, at: int) -> tuple[np.ndarray, int]:
    """An uninitialised buffer of `size` bytes (plus slack) and the offset `pad` at which a
    body must start so that its byte `at` lies on an `align`-byte boundary."""
    store = np.empty(size + align, np.uint8)           # no zero-filling: every byte is written
    return store, -(store.ctypes.data + at) % align


async def read_body(request: Request, align: int = 1, at: int = 0) -> memoryview | bytearray:
    """The body in one buffer (Starlette's `request.body()` joins a list of chunks: twice
    the body at its peak), sized by Content-Length when declared up to `PREALLOCATE`,
    grown as bytes arrive beyond it.

    With `align` > 1 the body is placed in a slightly larger, uninitialised buffer so that
    its byte `at` (where the binary tensors start, after the JSON header) lies on an
    `align`-byte boundary, and a memoryview of the body is returned: the tensors are then
    used in place whatever the header's length (oip.decode_tensors). Without a declared
    length the body grows as it arrives (tensors that end up misaligned are copied)."""
    declared = request.headers.get("content-length", "")
    size = int(declared) if declared.isdigit() else 0
    if align > 1 and size:
        store, pad = _aligned(min(size, PREALLOCATE), align, at)
        pos = pad
        try:
            async for chunk in request.stream():
                if pos - pad + len(chunk) > size:   # more than declared: BodyLimit/h11 stop this
                    raise ApiError(400, f"body longer than its Content-Length ({size} bytes)")
                if pos + len(chunk) > len(store) - align + pad:
                    grown, new_pad = _aligned(min(size, max(2 * (len(store) - align), pos - pad + len(chunk))),
                                              align, at)
                    grown[new_pad:new_pad + pos - pad] = store[pad:pos]
                    store, pos, pad = grown, new_pad + pos - pad, new_pad
                store[pos:pos + len(chunk)] = np.frombuffer(chunk, np.uint8)
                pos += len(chunk)
        except ClientDisconnect:
            raise ApiError(400, f"client disconnected after {pos - pad} body bytes") from None
        return memoryview(store)[pad:pos]
    buf = bytearray(min(size, PREALLOCATE))
    pos = 0
    try:
        async for chunk in request.stream():
            if pos + len(chunk) > len(buf):
                buf[pos:] = chunk                      # more than allocated (or none declared)
            else:
                buf[pos:pos + len(chunk)] = chunk
            pos += len(chunk)
    except ClientDisconnect:   # the client went away mid-body: its problem, not a server error
        raise ApiError(400, f"client disconnected after {pos} body bytes") from None
    del buf[pos:]                                      # less than declared
    return buf
