"""Hostile request bodies, made and not sent: the largest and oddest shapes the limits allow
(and some they refuse), the costliest JSON to parse per byte, nested and valid JSON bodies
around the parse pool's threshold.

Each maker returns (body, headers) for `post`.
"""
from __future__ import annotations

import json
from collections.abc import Callable

import numpy as np

from service.oip import HEADER_LENGTH


def binary_request(shape: tuple[int, ...], names: tuple[str, ...] = ("blocks", "quick"),
                   seed: int = 0) -> tuple[bytes, dict[str, str]]:
    """Body and headers of a binary-tensor request of FP32 `shape` per input (random values)."""
    n = int(np.prod(shape))
    head = json.dumps({"inputs": [{"name": nm, "shape": list(shape), "datatype": "FP32",
                                   "parameters": {"binary_data_size": 4 * n}} for nm in names]}).encode()
    data = np.random.default_rng(seed).random(n, dtype=np.float32).tobytes()
    return head + data * len(names), {HEADER_LENGTH: str(len(head)), "Content-Type": "application/octet-stream"}


def nested_json_request(shape: tuple[int, int, int, int], value: bytes = b"0") -> tuple[bytes, dict[str, str]]:
    """The costliest JSON to parse per byte: nested lists of one-character numbers."""
    n, h, w, c = shape
    pixel = b"[" + b",".join([value] * c) + b"]"
    row = b"[" + b",".join([pixel] * w) + b"]"
    image = b"[" + b",".join([row] * h) + b"]"
    data = b"[" + b",".join([image] * n) + b"]"
    inputs = b",".join(b'{"name":"%s","shape":%s,"datatype":"FP32","data":%s}'
                       % (nm, json.dumps(list(shape)).encode(), data) for nm in (b"blocks", b"quick"))
    return b'{"inputs":[' + inputs + b"]}", {"Content-Type": "application/json"}


def worst_shapes(max_body: int) -> dict[str, Callable[[], tuple[bytes, dict[str, str]]]]:
    """Named requests at and beyond the default limits (64 MiB body, 2048 px side, 4 Mi px)."""
    side_px = lambda n: int((max_body - 4096) // (2 * 12 * n))     # noqa: E731 pixels a body holds
    wide = side_px(1) // 2048
    return {
        "block side past the limit [1, 8, 40000, 3]": lambda: binary_request((1, 8, 40000, 3)),
        f"widest block [1, {wide}, 2048, 3]": lambda: binary_request((1, wide, 2048, 3)),
        "thin blocks [160, 8, 2048, 3]": lambda: binary_request((160, 8, 2048, 3)),
        "many small blocks [1024, 40, 40, 3]": lambda: binary_request((1024, 40, 40, 3)),
        "odd sizes [2, 999, 1001, 3]": lambda: binary_request((2, 999, 1001, 3)),
        "pixel budget exceeded [2, 2048, 1100, 3] (one input)": lambda: binary_request((2, 2048, 1100, 3), ("blocks",)),
        "nested JSON of one-digit numbers, ~body limit": lambda: nested_json_request(
            (2, 1024, max(8, int(max_body * 0.98 / (2 * 2 * 1024 * 8))), 3)),
        "body over the limit (declared)": lambda: (b"", {"Content-Length": str(max_body + 1),
                                                         "Content-Type": "application/octet-stream"}),
    }


def nested_json_request_62(megabytes: int = 62) -> tuple[bytes, dict[str, str]]:
    """Body and headers of `nested_over_budget`'s request."""
    unit = b"[" * 20 + b"1" + b"]" * 20
    n = (megabytes << 20) // (len(unit) + 1)
    data = b"[" + b",".join([unit] * n) + b"]"
    return (b'{"inputs":[{"name":"features","shape":[%d,1,1,1,1,1,1,1],"datatype":"FP32","data":' % n + data + b"}]}",
            {"Content-Type": "application/json"})


def costliest_valid_json(budget_fraction: float = 0.9, budget: int | None = None) -> tuple[bytes, dict[str, str]]:
    """The JSON body that costs the most CPU to parse per byte among those a default server
    admits: a rank-8 `features` tensor whose every value sits in 7 nested lists (the most
    nesting its shape allows), sized to `budget_fraction` of the memory budget's estimate."""
    from service.limits import DEFAULT_MEMORY_BUDGET
    from service.memory_cost import json_cost
    unit = b"[" * 7 + b"1" + b"]" * 7
    per = json_cost(unit + b",") + len(unit) + 1
    n = int(budget_fraction * (budget or DEFAULT_MEMORY_BUDGET) / per)
    data = b"[" + b",".join([unit] * n) + b"]"
    return (b'{"inputs":[{"name":"features","shape":[%d,1,1,1,1,1,1,1],"datatype":"FP32","data":' % n
            + data + b"}]}", {"Content-Type": "application/json"})


def nested_json_255k(depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """A nested body: 255 kB of `[[[[[[[0]]]]]]]` (11 deep with the envelope, the most a
    request may nest), a rank-8 `features` tensor: parsed in full, then refused (400)."""
    unit = b"[" * depth + b"0" + b"]" * depth
    n = (255_000 - 100) // (len(unit) + 1)
    return (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (n, b",1" * depth)
            + b",".join([unit] * n) + b"]}]}", {"Content-Type": "application/json"})


def nested_json(size: int, depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """The nested body at about `size` bytes (16.3 kB is just under the parse pool's byte
    threshold: too many lists to parse on the server's own thread)."""
    unit = b"[" * depth + b"0" + b"]" * depth
    n = (size - 100) // (len(unit) + 1)
    return (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (n, b",1" * depth)
            + b",".join([unit] * n) + b"]}]}", {"Content-Type": "application/json"})


def bound_json(size: int, units: int = 35, depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """The costliest body still parsed on the server's own thread: `units`
    values nested `depth` deep (253 lists and objects with the envelope, under
    `parsepool.INLINE_CONTAINERS`), padded with a flat list of zeros to about `size` bytes."""
    unit = b"[" * depth + b"0" + b"]" * depth
    head = (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (units, b",1" * depth)
            + b",".join([unit] * units) + b']},{"name":"pad","shape":[%d],"datatype":"FP32","data":[')
    n = max(1, (size - len(head) - 20) // 2)
    return head % n + b",".join([b"0"] * n) + b"]}]}", {"Content-Type": "application/json"}


def valid_halves_json(size: int) -> tuple[bytes, dict[str, str]]:
    """The largest valid halves request (`even` and `odd`, [k, 8, 8, 3] of 0.5, for the
    bundled model) of at most `size` bytes (16 kB: a valid body at the parse pool's threshold)."""
    def body(k: int) -> bytes:
        values = b"[" + b",".join([b"0.5"] * (k * 8 * 8 * 3)) + b"]"
        return (b'{"inputs":[{"name":"even","shape":[%d,8,8,3],"datatype":"FP32","data":' % k + values +
                b'},{"name":"odd","shape":[%d,8,8,3],"datatype":"FP32","data":' % k + values + b"}]}")
    k = 1
    while len(body(k + 1)) <= size:
        k += 1
    return body(k), {"Content-Type": "application/json"}


def valid_json_255k() -> tuple[bytes, dict[str, str]]:
    """A large valid body: a fully valid JSON request (184 kB), 8x8 blocks as the demo
    model takes them (120 blocks and their 120 quick images: 240 of [8, 8, 3])."""
    values = b"[" + b",".join([b"0.5"] * (120 * 8 * 8 * 3)) + b"]"
    return (b'{"inputs":[{"name":"blocks","shape":[120,8,8,3],"datatype":"FP32","data":' + values +
            b'},{"name":"quick","shape":[120,8,8,3],"datatype":"FP32","data":' + values + b"}]}",
            {"Content-Type": "application/json"})
