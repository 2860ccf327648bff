"""`noisestop serve`: load the models, check the security settings, run uvicorn.

Everything that can be wrong with the command (no token on a public address, a missing
model bundle, a bad limit) fails here, before the port is bound, with a one-line message.
SIGTERM (and Ctrl-C) makes uvicorn stop accepting connections and finish the requests in
flight before it exits, up to `graceful_timeout` seconds.
"""
from __future__ import annotations

import logging
import os

import uvicorn

from .app import create_app
from .auth import check_bind, resolve_token
from .limits import Limits
from .registry import ModelRegistry, parse_model_specs

log = logging.getLogger(__name__)

__all__ = ["run", "build", "parse_model_specs"]


def build(models: dict[str, str | None] | None = None, host: str = "127.0.0.1", *,
          token: str | None = None, token_file: str | os.PathLike | None = None,
          max_body_bytes: int | None = None, max_batch: int | None = None,
          inference_threads: int = 2, offset: float | None = None):
    """The app `run` serves, with models loaded and settings checked (tests use it too).
    `offset` overrides every model's calibrated decision offset (`serve --offset`)."""
    secret = resolve_token(token, token_file)
    check_bind(host, secret)
    if secret is None:
        log.warning("no token (%s / %s): running UNAUTHENTICATED, on loopback %s only",
                    "NOISESTOP_TOKEN", "NOISESTOP_TOKEN_FILE", host)
    limits = Limits.from_env(max_body_bytes=max_body_bytes, max_batch=max_batch)
    if inference_threads < 1:
        raise ValueError(f"inference_threads must be >= 1, got {inference_threads}")
    registry = ModelRegistry(dict(models or {}), offset=offset)
    registry.load()
    return create_app(registry, token=secret, limits=limits, inference_threads=inference_threads)


def run(models: dict[str, str | None] | None = None, host: str = "127.0.0.1", port: int = 8000, *,
        token: str | None = None, token_file: str | os.PathLike | None = None,
        max_body_bytes: int | None = None, max_batch: int | None = None,
        inference_threads: int = 2, max_connections: int = 64, graceful_timeout: float = 30.0,
        log_level: str | None = None, offset: float | None = None) -> None:
    """Serve `models` ({name: bundle path or None for the bundled model}; empty: the bundled
    model) until SIGTERM/SIGINT. The token defaults to NOISESTOP_TOKEN / NOISESTOP_TOKEN_FILE;
    limits default to NOISESTOP_MAX_BODY_BYTES / NOISESTOP_MAX_BATCH. Logs go to the root logger
    (uvicorn's own logging setup is off); `log_level` overrides uvicorn's level only."""
    if not 0 <= port <= 65535:
        raise ValueError(f"port must be 0..65535, got {port}")
    app = build(models, host, token=token, token_file=token_file, max_body_bytes=max_body_bytes,
                max_batch=max_batch, inference_threads=inference_threads, offset=offset)
    limits = app.state.limits
    log.info("listening on http://%s:%d (%s; body limit %d bytes, batch limit %d)",
             f"[{host}]" if ":" in host else host, port,
             "token required" if app.state.token else "no token, loopback only",
             limits.max_body_bytes, limits.max_batch)
    config = uvicorn.Config(app, host=host, port=port, log_config=None, log_level=log_level,
                            timeout_graceful_shutdown=graceful_timeout,
                            limit_concurrency=max_connections, server_header=False,
                            proxy_headers=False)
    uvicorn.Server(config).run()
