"""How every error becomes an answer: a JSON body {"error": "..."} with the right status.

Why one place: a client must never see FastAPI's own error shapes ({"detail": ...}) or a
traceback; a 500 means a bug here, and running out of memory is answered 503 and served on.
"""
from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from .heap import release_memory
from .oip import ApiError

log = logging.getLogger(__name__)


def add_error_handlers(app: FastAPI) -> None:
    """Register the handlers of `ApiError`, HTTP errors, validation errors, MemoryError and
    any other exception (500, logged) on `app`."""
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
