"""What a request costs in working memory, estimated from its body before any parsing.

Why before parsing: a 3.8 MB request once took the server to 23.7 GB, and a JSON body of
nested lists costs ~50 times its size once parsed; the estimate (a byte count, ~10 ms for
30 MB) lets the server refuse or queue a request before it spends that memory
(service.memory_budget, service.infer). Binary tensors cost `MEMORY_PER_BODY_BYTE` a byte,
JSON is counted by its brackets, commas and colons, the costs measured for the worst shapes.
"""
from __future__ import annotations

#: working memory a request of binary tensors takes per byte of its body, at its peak, the
#: body included (measured ~10x, BENCHMARKS.md "Reliability"), plus a fixed part
MEMORY_PER_BODY_BYTE = 16
MEMORY_PER_REQUEST = 1 << 20
#: what parsing and decoding JSON costs, in bytes, per opening bracket or brace (a list or
#: dict object, its slot in its parent, numpy's walk of it), per comma or colon (a number
#: object and its slot, or a dict entry) and per byte of text (strings). Measured peak
#: working memory over the body, full decode (docs/benchmarks/reliability.md,
#: "Memory"): 20 nested lists around each number 52x (this estimate: 60x), [1] 31x (48x),
#: {} 28x (64x), {"a":1} 26x (32x), flat 3-digit integers 13x (16x), floats of 9 digits
#: 4.3x (5.3x), whitespace and long number strings ~0x (1x).
JSON_COST_PER_CONTAINER = 128
JSON_COST_PER_ITEM = 64
JSON_COST_PER_BYTE = 1


def request_cost(body_bytes: int) -> int:
    """Working memory a binary request of `body_bytes` is counted for, body included
    (`MEMORY_PER_BODY_BYTE`): the least budget that admits one request of the largest body."""
    return MEMORY_PER_BODY_BYTE * body_bytes + MEMORY_PER_REQUEST


def json_cost(text: bytes | bytearray) -> int:
    """Working memory parsing and decoding this JSON text may take, from a byte count
    alone (no parsing; ~10 ms for 30 MB). Brackets, commas and colons inside strings are
    counted too: the estimate errs on the high side, never the low."""
    from .jsonguard import CHUNK, SCAN_BYTES_PER_BYTE

    containers = text.count(b"[") + text.count(b"{")
    items = text.count(b",") + text.count(b":")
    # plus the depth scan's working arrays (`jsonguard`), which run before the parser
    return JSON_COST_PER_CONTAINER * containers + JSON_COST_PER_ITEM * items + JSON_COST_PER_BYTE * len(text) \
        + SCAN_BYTES_PER_BYTE * min(len(text), CHUNK)


def decode_cost(body: bytes | bytearray | memoryview, header_length: int | None) -> int:
    """Working memory a complete request body will take beyond the body itself, estimated
    before any parsing: its JSON by `json_cost`, its binary tensors at
    `MEMORY_PER_BODY_BYTE` - 1 a byte (the body is already counted as it arrived)."""
    if header_length is None:
        head, tail = bytes(body) if isinstance(body, memoryview) else body, 0
    else:
        head = bytes(memoryview(body)[:max(0, min(header_length, len(body)))])
        tail = len(body) - len(head)
    return MEMORY_PER_REQUEST + json_cost(head) + (MEMORY_PER_BODY_BYTE - 1) * tail
