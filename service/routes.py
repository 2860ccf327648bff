"""The verdict API's routes, as FastAPI routers (DESIGN.md "HTTP API").

`health_routes`: GET /v2/health/live and /v2/health/ready, with no token (probes).
`api_routes`, behind the bearer token: GET /v2, GET|POST /v2/repository/index,
GET /v2/models/{m}[/versions/{v}], GET .../ready, POST .../infer (service.infer does the
work). Why routers: the app (service.app) puts them together with the middleware, and the
OpenAPI document lists them as they are declared here.
"""
from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, Request, Response
from fastapi.responses import JSONResponse

from .apidoc import INFER_BODY, INFER_OK, error_responses
from .auth import require_token
from .infer import answer_infer
from .oip import (BINARY_EXTENSION, HEADER_LENGTH, LiveResponse, ModelMetadata, ModelReadyResponse, ReadyResponse,
                  RepositoryModel, ServerMetadata)
from .registry import DEFAULT, ModelRegistry

SERVER_NAME = "noisestop"

# A decimal string (HTTP headers are text); absent: the whole body is JSON.
HeaderLength = Annotated[str | None, Header(alias=HEADER_LENGTH, convert_underscores=False,
                                            pattern=r"^[0-9]{1,15}$",
                                            description="length in bytes of the JSON header when "
                                                        "binary tensors follow it")]


def server_version() -> str:
    """The installed noisestop's version ("0+unknown" from a checkout that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("noisestop")
    except PackageNotFoundError:
        return "0+unknown"


def health_routes(registry: ModelRegistry) -> APIRouter:
    """The probes: live always, ready once `registry` has loaded."""
    router = APIRouter(prefix="/v2/health", tags=["health"])

    @router.get("/live")
    async def live() -> LiveResponse:
        return LiveResponse(live=True)

    @router.get("/ready", responses={400: {"model": ReadyResponse, "description": "not ready"}})
    async def ready() -> JSONResponse:
        return JSONResponse({"ready": registry.ready}, 200 if registry.ready else 400)

    return router


def api_routes(registry: ModelRegistry) -> APIRouter:
    """Server and model metadata, readiness and inference for the models of `registry`."""
    router = APIRouter(prefix="/v2", dependencies=[Depends(require_token)], responses=error_responses(401))
    model_errors = error_responses(401, 404)

    @router.get("", tags=["server"])
    async def server_metadata() -> ServerMetadata:
        return ServerMetadata(name=SERVER_NAME, version=server_version(), extensions=[BINARY_EXTENSION])

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
        responses={**INFER_OK, **error_responses(400, 401, 404, 408, 413, 415, 503)}, response_model=None,
        openapi_extra=INFER_BODY, tags=["models"])

    @router.post("/models/{model_name}/infer", **infer_doc)
    async def infer(model_name: str, request: Request,
                    header_length: HeaderLength = None) -> Response:
        return await answer_infer(request, registry.get(model_name), header_length)

    @router.post("/models/{model_name}/versions/{model_version}/infer", **infer_doc)
    async def infer_version(model_name: str, model_version: str, request: Request,
                            header_length: HeaderLength = None) -> Response:
        return await answer_infer(request, registry.get(model_name, model_version), header_length)

    return router
