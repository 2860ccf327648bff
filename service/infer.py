"""One inference request, from its body to its answer: the infer route's work.

The route reads its body itself (`service.body.read_body`): it may carry binary tensors
after the JSON header, and a 16-block JSON request holds ~1.5 M numbers that pydantic need
not walk one by one. The body's memory is claimed from the memory budget before it is
decoded (`service.memory_cost.decode_cost`, a byte count); a large JSON header is parsed
in a worker process (service.parsepool); decoding and inference run in worker threads
(anyio.to_thread with a capacity limiter), so the event loop keeps serving probes and
uploads while the CPU works.
"""
from __future__ import annotations

import logging
from typing import Any

import anyio.to_thread
import numpy as np
from fastapi import Request, Response

from learning.stoprule import OFFSET_LIMIT
from noisefeat.display import EXPOSURE_RANGE

from .body import TENSOR_ALIGNMENT, read_body
from .body_limit import UPLOAD_CLAIM
from .console import one_line
from .heap import release_memory
from .limits import ENV_MEMORY_BUDGET, Limits
from .memory_budget import MemoryBudget, busy
from .memory_cost import decode_cost
from .metrics import ServiceMetrics
from .oip import (HEADER_LENGTH, ApiError, InferenceRequest, InferenceResponse, RequestOutput, ResponseOutput,
                  decode_tensors, encode_response, may_hold_bools, number_param, param, parse_request, split_body)
from .parsepool import INLINE_BYTES, parse_inline
from .registry import OUTPUTS, ServedModel

log = logging.getLogger(__name__)

BINARY_MEDIA = "application/octet-stream"


async def answer_infer(request: Request, served: ServedModel, header_length: str | None) -> Response:
    """Answer one infer request with `served` (both infer routes: by model, by version)."""
    if request.headers.get("content-encoding", "identity").strip().lower() not in ("identity", ""):
        raise ApiError(415, "compressed request bodies are not accepted (Content-Encoding must be identity)")
    state = request.app.state
    length = None if header_length is None else int(header_length)
    # counted against the limit, timed and its bytes claimed from the budget by BodyLimitMiddleware
    body = [await read_body(request, TENSOR_ALIGNMENT if length is not None else 1, length or 0)]
    budget: MemoryBudget = state.memory_budget
    # the body (already in memory) and what decoding it will take: a byte count, no parsing
    cost = len(body[0]) + await anyio.to_thread.run_sync(decode_cost, body[0], length)
    if cost > budget.total:
        raise ApiError(413, f"decoding this request would take about {cost} bytes of working memory, over "
                            f"this server's whole budget of {budget.total} (serve --memory-budget, "
                            f"{ENV_MEMORY_BUDGET}); send binary tensors, fewer values or less nesting",
                       headers={"Connection": "close"})
    if not await budget.acquire(cost):
        raise busy(f"{cost} bytes to decode this request")
    upload_claim = request.scope.get(UPLOAD_CLAIM)
    if upload_claim and upload_claim[0]:           # the body now counts in `cost`
        state.upload_budget.release(upload_claim[0])
        upload_claim[0] = 0
    try:
        parsed = None
        head_size = len(body[0]) if length is None else min(length, len(body[0]))
        head = body[0] if length is None else memoryview(body[0])[:head_size]
        if not parse_inline(head, INLINE_BYTES):   # off the event loop and out of the GIL, with a time budget
            parsed = await state.parse_pool.parse(head)
        del head
        content, json_length = await anyio.to_thread.run_sync(
            infer_sync, served, body, length, state.limits, state.metrics, parsed, limiter=state.limiter)
    finally:
        body.clear()
        budget.release(cost)
        release_memory()
    if json_length is None:
        return Response(content, media_type="application/json")
    return Response(content, media_type=BINARY_MEDIA, headers={HEADER_LENGTH: str(json_length)})


def infer_sync(served: ServedModel, body: list[bytearray | memoryview], header_length: int | None,
               limits: Limits, metrics: ServiceMetrics, parsed: InferenceRequest | None = None
               ) -> tuple[bytes, int | None]:
    """Decode, classify, encode: everything CPU-bound about one request, in a worker thread.

    Running out of memory (a MemoryError under an address-space limit, or the JSON parser's
    native code giving up, which surfaces as a BaseException that is not an Exception) is
    answered 503 and logged; the request's memory is freed and the server serves on."""
    try:
        req, tensors, exposure, offset, tau, wanted = _decode_sync(body, header_length, limits, parsed)
        arrays, parameters = served.infer(tensors, exposure, offset, tau)
        return _encode(served, req, wanted, arrays, parameters, metrics)
    except MemoryError:
        body.clear()
        log.error("out of memory while answering a request (%s); answered 503, serving on",
                  "decode or inference")
        raise ApiError(503, "server out of memory for this request; retry, or send a smaller one",
                       headers={"Retry-After": "1", "Connection": "close"}) from None
    except BaseException as exc:      # noqa: B036 - only pyo3's PanicException is handled here
        if type(exc).__name__ != "PanicException":
            raise
        body.clear()
        log.error("the JSON parser failed in native code (%s); answered 503, serving on", one_line(exc))
        raise ApiError(503, "server could not parse this request (out of memory?); retry, or send a smaller one",
                       headers={"Retry-After": "1", "Connection": "close"}) from None


def _decode_sync(body: list[bytearray | memoryview], header_length: int | None, limits: Limits,
                 parsed: InferenceRequest | None = None) -> tuple[InferenceRequest, dict[str, np.ndarray], float, float | None, float | None,
                            dict[str, bool]]:
    """The request, its tensors, exposure, offset, noise target tau and wanted outputs.

    `body` is a one-item list, emptied once the tensors are decoded: a JSON body's text is
    then freed before the model runs; binary tensors are views of the body (no copy), which
    lives as long as they do. `parsed`: the header as a parse worker returned it (its JSON
    data already arrays, checked there: service.parsepool)."""
    if parsed is not None:                     # parsed by a worker: only the binary tail is left
        head, tail = b"", split_body(memoryview(body[0]), header_length)[1] if header_length is not None else b""
    elif header_length is None:                # all JSON: parsed in place
        head, tail = body[0], b""
    else:
        head, tail = split_body(memoryview(body[0]), header_length)
        head = bytes(head)
    req = parse_request(head) if parsed is None else parsed
    exposure = number_param(req.parameters, "exposure", 0.0, *EXPOSURE_RANGE)
    offset = number_param(req.parameters, "offset", None, -OFFSET_LIMIT, OFFSET_LIMIT)
    tau = number_param(req.parameters, "tau", None, 0.0, 1.0)    # the model's range is checked by infer
    limits.check_shapes(req.inputs)       # what the request declares, before any tensor is built
    wanted = _requested_outputs(req)
    tensors = decode_tensors(req, tail, limits.max_batch, scan_bools=parsed is None and may_hold_bools(head))
    del head, tail
    if isinstance(body[0], bytearray) and header_length is None:
        body[0].clear()                        # the JSON text (no view of it is left)
    body.clear()
    for t in req.inputs:       # the parsed JSON values (~10x the body): no longer needed
        t.data = None
    return req, tensors, exposure, offset, tau, wanted


def _encode(served: ServedModel, req: InferenceRequest, wanted: dict[str, bool], arrays: dict[str, np.ndarray],
            parameters: dict[str, Any], metrics: ServiceMetrics) -> tuple[bytes, int | None]:
    metrics.record(served.name, arrays["verdict"], parameters)
    resp = InferenceResponse(
        model_name=served.name, model_version=served.version, id=req.id, parameters=parameters or None,
        outputs=[ResponseOutput(name=n, shape=[int(s) for s in arrays[n].shape], datatype=OUTPUTS[n])
                 for n in wanted])
    return encode_response(resp, arrays, {n for n, binary in wanted.items() if binary})


def _requested_outputs(req: InferenceRequest) -> dict[str, bool]:
    """Output name -> sent as binary; all outputs when none are named (OIP)."""
    default_binary = param(req.parameters, "binary_data_output", bool, False)
    outputs = req.outputs or [RequestOutput(name=n) for n in OUTPUTS]
    wanted: dict[str, bool] = {}
    for out in outputs:
        if out.name not in OUTPUTS:
            raise ApiError(400, f"unknown output {out.name!r}; the outputs are {list(OUTPUTS)}")
        if out.name in wanted:
            raise ApiError(400, f"output {out.name!r} requested twice")
        wanted[out.name] = param(out.parameters, "binary_data", bool, default_binary)
    return wanted
