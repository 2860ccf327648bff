"""The verdict API: Open Inference Protocol v2 over FastAPI (DESIGN.md "HTTP API").

Routes (service.routes): GET /v2/health/live, /v2/health/ready (no token: probes), and,
behind the bearer token, GET /v2, GET|POST /v2/repository/index, GET
/v2/models/{m}[/versions/{v}], GET .../ready, POST .../infer (service.infer), GET /metrics.
Every client error is a 4xx with {"error": "..."} (service.error_handlers); a 500 means a
bug here.

This module puts the app together, as FastAPI's documentation does: the models load in
the lifespan, the limits are middleware (service.body_limit, service.connections), the
routes are routers, and the OpenAPI document is completed by service.apidoc.
"""
from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from noisefeat.extras import require_extra

require_extra("serve")   # one line naming the extra, not an ImportError from fastapi
import anyio  # noqa: E402
import anyio.to_thread  # noqa: E402
from fastapi import Depends, FastAPI  # noqa: E402

from learning.stoprule import OFFSET_LIMIT  # noqa: E402
from noisefeat.display import EXPOSURE_RANGE  # noqa: E402

from .apidoc import error_responses, openapi  # noqa: E402
from .auth import require_token  # noqa: E402
from .body_limit import UPLOAD_BODIES, BodyLimitMiddleware  # noqa: E402
from .connections import HealthFastPath, InFlightLimitMiddleware  # noqa: E402
from .error_handlers import add_error_handlers  # noqa: E402
from .limits import Limits  # noqa: E402
from .memory_budget import MemoryBudget  # noqa: E402
from .metrics import ServiceMetrics  # noqa: E402
from .parsepool import DEFAULT_PARSE_SECONDS, ParsePool, ParseRules  # noqa: E402
from .registry import DEFAULT, ModelRegistry  # noqa: E402
from .routes import api_routes, health_routes, server_version  # noqa: E402
from .upload_policy import UploadPolicy  # noqa: E402

log = logging.getLogger(__name__)


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
    window across concurrent requests was measured slower (docs/benchmarks/service.md) and is not kept."""
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

    app = FastAPI(title="noisestop verdict service", version=server_version(), lifespan=lifespan,
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
        **error_responses(401)})
    add_error_handlers(app)
    app.include_router(health_routes(registry))
    app.include_router(api_routes(registry))
    if limit_concurrency is not None:   # added last: the outermost, before any body is read
        app.add_middleware(InFlightLimitMiddleware, limit=limit_concurrency)
    app.openapi = lambda: openapi(app)  # type: ignore[method-assign]
    return app
