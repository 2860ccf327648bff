"""What the OpenAPI document says beyond what FastAPI reads off the routes.

Why: every client error is a 4xx with {"error": "..."} (`error_responses` documents each
status a route may answer), and the infer route reads its body itself (service.infer), so
FastAPI cannot see its schema: `INFER_BODY` and `INFER_OK` give it through
`openapi_extra`, and `openapi` adds the request's pydantic schemas to the document.
"""
from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic.json_schema import models_json_schema

from .infer import BINARY_MEDIA
from .oip import HEADER_LENGTH, ErrorResponse, InferenceRequest, InferenceResponse

DESCRIPTIONS = {400: "bad request (shape, datatype, data, parameter out of range, JSON)",
                401: "missing or wrong bearer token", 404: "unknown model or version",
                408: "request body stopped arriving (serve --body-timeout)",
                413: "body, batch, block side or pixel count over the server's limit",
                415: "compressed request body",
                503: "too many requests in flight (serve --limit-concurrency, --memory-budget); "
                     "retry after Retry-After"}


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The `responses` entry of a route for these error statuses ({"error": ...} bodies)."""
    return {c: {"model": ErrorResponse, "description": DESCRIPTIONS[c]} for c in codes}


_BINARY_SCHEMA = {"type": "string", "format": "binary",
                  "description": f"JSON header ({HEADER_LENGTH} bytes), then raw little-endian tensors"}
INFER_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"$ref": "#/components/schemas/InferenceRequest"}},
    BINARY_MEDIA: {"schema": _BINARY_SCHEMA}}}}
INFER_OK: dict[int | str, dict[str, Any]] = {200: {
    "model": InferenceResponse, "description": "verdict (-1 noisy, +1 converged) and score per item",
    "content": {BINARY_MEDIA: {"schema": _BINARY_SCHEMA}},
    "headers": {HEADER_LENGTH: {"description": "present when binary outputs follow the JSON header",
                                "schema": {"type": "integer"}}}}}


def openapi(app: FastAPI) -> dict[str, Any]:
    """FastAPI's document plus the schemas of the infer body, which the route reads itself."""
    if app.openapi_schema is None:
        doc = get_openapi(title=app.title, version=app.version, description=app.description,
                          routes=app.routes)
        _, defs = models_json_schema([(InferenceRequest, "validation")],
                                     ref_template="#/components/schemas/{model}")
        doc.setdefault("components", {}).setdefault("schemas", {}).update(defs["$defs"])
        app.openapi_schema = doc
    return app.openapi_schema
