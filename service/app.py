"""The verdict API: Open Inference Protocol v2 over FastAPI (DESIGN.md "HTTP API").

Routes: GET /v2/health/live, /v2/health/ready (no token: probes), and, behind the bearer
token, GET /v2, GET|POST /v2/repository/index, GET /v2/models/{m}[/versions/{v}],
GET .../ready, POST .../infer, GET /metrics. Every client error is a 4xx with
{"error": "..."}; a 500 means a bug here.

The infer route reads its body itself (FastAPI's documented route for custom bodies, with
the schema given through `openapi_extra`): the body may carry binary tensors after the JSON
header, and a 16-block JSON request holds ~1.5 M numbers that pydantic need not walk one
by one. Decoding and inference run in worker threads (anyio.to_thread with a capacity
limiter), so the event loop keeps serving probes and uploads while the CPU works.
"""
from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any

from noisefeat.extras import require_extra

require_extra("serve")   # one line naming the extra, not an ImportError from fastapi
import anyio  # noqa: E402
import anyio.to_thread  # noqa: E402
import numpy as np  # noqa: E402
from fastapi import APIRouter, Depends, FastAPI, Header, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from pydantic.json_schema import models_json_schema
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from learning.stoprule import OFFSET_LIMIT
from noisefeat.display import EXPOSURE_RANGE

from .auth import require_token
from .console import one_line
from .connections import HealthFastPath, InFlightLimitMiddleware
from .limits import (ENV_MEMORY_BUDGET, UPLOAD_BODIES, UPLOAD_CLAIM, BodyLimitMiddleware, Limits, MemoryBudget,
                     UploadPolicy, busy, decode_cost, release_memory)
from .metrics import ServiceMetrics
from .oip import (BINARY_EXTENSION, HEADER_LENGTH, ApiError, ErrorResponse, InferenceRequest,
                  InferenceResponse, LiveResponse, ModelMetadata, ModelReadyResponse, ReadyResponse,
                  RepositoryModel, RequestOutput, ResponseOutput, ServerMetadata, decode_tensors,
                  encode_response, may_hold_bools, number_param, param, parse_request, split_body)
from .parsepool import DEFAULT_PARSE_SECONDS, INLINE_BYTES, ParsePool, ParseRules, parse_inline
from .registry import DEFAULT, OUTPUTS, ModelRegistry, ServedModel

log = logging.getLogger(__name__)

SERVER_NAME = "noisestop"
BINARY_MEDIA = "application/octet-stream"

_DESCRIPTIONS = {400: "bad request (shape, datatype, data, parameter out of range, JSON)",
                 401: "missing or wrong bearer token", 404: "unknown model or version",
                 408: "request body stopped arriving (serve --body-timeout)",
                 413: "body, batch, block side or pixel count over the server's limit",
                 415: "compressed request body",
                 503: "too many requests in flight (serve --limit-concurrency, --memory-budget); "
                      "retry after Retry-After"}


# A decimal string (HTTP headers are text); absent: the whole body is JSON.
HeaderLength = Annotated[str | None, Header(alias=HEADER_LENGTH, convert_underscores=False,
                                            pattern=r"^[0-9]{1,15}$",
                                            description="length in bytes of the JSON header when "
                                                        "binary tensors follow it")]


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {c: {"model": ErrorResponse, "description": _DESCRIPTIONS[c]} for c in codes}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("noisestop")
    except PackageNotFoundError:
        return "0+unknown"


def create_app(registry: ModelRegistry, *, token: str | None = None, limits: Limits | None = None,
               inference_threads: int = 2, metrics: ServiceMetrics | None = None,
               limit_concurrency: int | None = None, body_timeout: float | None = None,
               upload: UploadPolicy | None = None, parse_seconds: float = DEFAULT_PARSE_SECONDS) -> FastAPI:
    """The ASGI app; models load in its lifespan (now, if `registry` is not loaded yet).

    `limit_concurrency`: most requests in flight, health probes and /metrics not counted
    (None: no limit); `body_timeout`: seconds a request body may stall (None: no limit);
    `upload`: the whole upload policy (stall, deadline, minimum rate; `body_timeout` is then
    ignored); `parse_seconds`: the time a large JSON header may take to parse (service.parsepool).

    Requests are classified one by one, 2 at a time (`inference_threads`): a micro-batching
    window across concurrent requests was measured slower (BENCHMARKS.md "Verdict
    service") and is not kept."""
    limits = limits or Limits()
    metrics = metrics or ServiceMetrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.limiter = anyio.CapacityLimiter(inference_threads)
        await anyio.to_thread.run_sync(registry.load)
        await anyio.to_thread.run_sync(app.state.parse_pool.start)
        for name, served in registry.models.items():
            metrics.load_seconds.labels(name).set(served.load_seconds)
        log.info("serving %s; %r is %s", ", ".join(registry.models), DEFAULT, registry.default_name)
        try:
            yield
        finally:
            app.state.parse_pool.close()

    app = FastAPI(title="noisestop verdict service", version=_version(), lifespan=lifespan,
                  docs_url=None, redoc_url=None,
                  description="Open Inference Protocol v2: is this sub-image still noisy to a human?")
    app.state.token = token
    app.state.registry = registry
    app.state.limits = limits
    app.state.metrics = metrics
    app.state.memory_budget = MemoryBudget(limits.memory_budget)
    app.state.parse_pool = ParsePool(ParseRules(limits.max_batch, limits.max_block_side, limits.max_pixels,
                                                tuple(EXPOSURE_RANGE), OFFSET_LIMIT),
                                     workers=inference_threads, seconds=parse_seconds)
    app.state.upload_budget = MemoryBudget(UPLOAD_BODIES * limits.max_body_bytes)
    app.add_middleware(BodyLimitMiddleware, max_bytes=limits.max_body_bytes, body_timeout=body_timeout,
                       budget=app.state.upload_budget, upload=upload)
    # probes answered before routing, the token, body limits (still counted by /metrics, outside it)
    app.add_middleware(HealthFastPath, ready=lambda: registry.ready)
    metrics.instrument(app, dependencies=[Depends(require_token)], tags=["metrics"], responses={
        200: {"description": "Prometheus text format",
              "content": {"text/plain": {"schema": {"type": "string"}}}},
        **_errors(401)})
    _add_error_handlers(app)
    app.include_router(_health_routes(registry))
    app.include_router(_api_routes(registry))
    if limit_concurrency is not None:   # added last: the outermost, before any body is read
        app.add_middleware(InFlightLimitMiddleware, limit=limit_concurrency)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def _add_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse({"error": exc.message}, exc.status, headers=exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        return JSONResponse({"error": str(exc.detail)}, exc.status_code, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        where = ".".join(str(p) for p in first.get("loc", ()))
        return JSONResponse({"error": f"{where}: {first.get('msg')}"}, 400)

    @app.exception_handler(MemoryError)
    async def out_of_memory(_: Request, exc: MemoryError) -> JSONResponse:
        log.error("out of memory while receiving a request; answered 503, serving on")
        release_memory(0)
        return JSONResponse({"error": "server out of memory for this request; retry, or send a smaller one"},
                            503, headers={"Retry-After": "1", "Connection": "close"})

    @app.exception_handler(Exception)
    async def server_error(_: Request, exc: Exception) -> JSONResponse:
        log.exception("unexpected error", exc_info=exc)
        return JSONResponse({"error": "internal server error"}, 500)


def _health_routes(registry: ModelRegistry) -> APIRouter:
    router = APIRouter(prefix="/v2/health", tags=["health"])

    @router.get("/live")
    async def live() -> LiveResponse:
        return LiveResponse(live=True)

    @router.get("/ready", responses={400: {"model": ReadyResponse, "description": "not ready"}})
    async def ready() -> JSONResponse:
        return JSONResponse({"ready": registry.ready}, 200 if registry.ready else 400)

    return router


def _api_routes(registry: ModelRegistry) -> APIRouter:
    router = APIRouter(prefix="/v2", dependencies=[Depends(require_token)], responses=_errors(401))
    model_errors = _errors(401, 404)

    @router.get("", tags=["server"])
    async def server_metadata() -> ServerMetadata:
        return ServerMetadata(name=SERVER_NAME, version=_version(), extensions=[BINARY_EXTENSION])

    @router.get("/repository/index", tags=["server"])
    async def repository_index() -> list[RepositoryModel]:
        out = [RepositoryModel(name=DEFAULT, version=registry.get(DEFAULT).version, state="READY",
                               reason=f"alias of {registry.default_name}")]
        return out + [RepositoryModel(name=n, version=s.version, state="READY")
                      for n, s in registry.models.items()]

    @router.post("/repository/index", tags=["server"], description="Triton's form (its body is ignored)")
    async def repository_index_post() -> list[RepositoryModel]:
        return await repository_index()

    @router.get("/models/{model_name}", responses=model_errors, tags=["models"])
    async def model_metadata(model_name: str) -> ModelMetadata:
        return registry.get(model_name).metadata(model_name)

    @router.get("/models/{model_name}/versions/{model_version}", responses=model_errors, tags=["models"])
    async def model_version_metadata(model_name: str, model_version: str) -> ModelMetadata:
        return registry.get(model_name, model_version).metadata(model_name)

    @router.get("/models/{model_name}/ready", responses=model_errors, tags=["models"])
    async def model_ready(model_name: str) -> ModelReadyResponse:
        registry.get(model_name)
        return ModelReadyResponse(name=model_name, ready=True)

    @router.get("/models/{model_name}/versions/{model_version}/ready", responses=model_errors,
                tags=["models"])
    async def model_version_ready(model_name: str, model_version: str) -> ModelReadyResponse:
        registry.get(model_name, model_version)
        return ModelReadyResponse(name=model_name, ready=True)

    infer_doc: dict[str, Any] = dict(
        responses={**_INFER_OK, **_errors(400, 401, 404, 408, 413, 415, 503)}, response_model=None,
        openapi_extra=_INFER_BODY, tags=["models"])

    @router.post("/models/{model_name}/infer", **infer_doc)
    async def infer(model_name: str, request: Request,
                    header_length: HeaderLength = None) -> Response:
        return await _infer(request, registry.get(model_name), header_length)

    @router.post("/models/{model_name}/versions/{model_version}/infer", **infer_doc)
    async def infer_version(model_name: str, model_version: str, request: Request,
                            header_length: HeaderLength = None) -> Response:
        return await _infer(request, registry.get(model_name, model_version), header_length)

    return router


async def _infer(request: Request, served: ServedModel, header_length: str | None) -> Response:
    if request.headers.get("content-encoding", "identity").strip().lower() not in ("identity", ""):
        raise ApiError(415, "compressed request bodies are not accepted (Content-Encoding must be identity)")
    state = request.app.state
    length = None if header_length is None else int(header_length)
    # counted against the limit, timed and its bytes claimed from the budget by BodyLimitMiddleware
    body = [await _read_body(request, TENSOR_ALIGNMENT if length is not None else 1, length or 0)]
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
            _infer_sync, served, body, length, state.limits, state.metrics, parsed, limiter=state.limiter)
    finally:
        body.clear()
        budget.release(cost)
        release_memory()
    if json_length is None:
        return Response(content, media_type="application/json")
    return Response(content, media_type=BINARY_MEDIA, headers={HEADER_LENGTH: str(json_length)})


#: the binary tensors of a request are placed at this alignment in memory (`_read_body`), so
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


async def _read_body(request: Request, align: int = 1, at: int = 0) -> memoryview | bytearray:
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


def _infer_sync(served: ServedModel, body: list[bytearray | memoryview], header_length: int | None,
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


_BINARY_SCHEMA = {"type": "string", "format": "binary",
                  "description": f"JSON header ({HEADER_LENGTH} bytes), then raw little-endian tensors"}
_INFER_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/InferenceRequest"}},
    BINARY_MEDIA: {"schema": _BINARY_SCHEMA}}}}
_INFER_OK: dict[int | str, dict[str, Any]] = {200: {
    "model": InferenceResponse, "description": "verdict (-1 noisy, +1 converged) and score per item",
    "content": {BINARY_MEDIA: {"schema": _BINARY_SCHEMA}},
    "headers": {HEADER_LENGTH: {"description": "present when binary outputs follow the JSON header",
                                "schema": {"type": "integer"}}}}}


def _openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's document plus the schemas of the infer body, which the route reads itself."""
    if app.openapi_schema is None:
        doc = get_openapi(title=app.title, version=app.version, description=app.description,
                          routes=app.routes)
        _, defs = models_json_schema([(InferenceRequest, "validation")],
                                     ref_template="#/components/schemas/{model}")
        doc.setdefault("components", {}).setdefault("schemas", {}).update(defs["$defs"])
        app.openapi_schema = doc
    return app.openapi_schema
