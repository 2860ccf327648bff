"""`noisestop serve`: load the models, check the security settings, run uvicorn.

Everything that can be wrong with the command (no token without `--no-auth`, no token on
a public address, a missing model bundle, a bad limit) fails here, before the port is
bound, with a one-line message.
SIGTERM, SIGHUP and Ctrl-C make uvicorn stop accepting connections and finish the requests
in flight before it exits, up to `graceful_timeout` seconds, each with a log line (SIGHUP
drains like SIGTERM: it does not reload the model; a second Ctrl-C stops at once).

Connection settings (service.connections): request headers must arrive within
`header_timeout` seconds of a connection opening (or of its previous response), a body may
stall for `body_timeout` seconds, must be complete within `body_deadline` seconds and
arrive at `min_body_rate` bytes a second after `body_grace` seconds
(service.upload_policy.UploadPolicy), an idle kept-alive connection is closed after
`keep_alive` seconds; at most `limit_concurrency` requests are in flight (health probes
and /metrics exempt), together within `memory_budget` bytes of working memory
(service.memory_budget.MemoryBudget), and at most `max_connections` connections are open.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterator
from types import FrameType

from noisefeat.bounds import env_seconds
from noisefeat.extras import require_extra

require_extra("serve")   # one line naming the extra, not an ImportError from uvicorn
import uvicorn  # noqa: E402

from .app import create_app
from .auth import check_bind, resolve_token
from .connections import guarded_protocol
from .limits import Limits
from .parsepool import DEFAULT_PARSE_SECONDS, ENV_PARSE_SECONDS
from .registry import ModelRegistry, parse_model_specs
from .startup import guard_start_up
from .upload_policy import UploadPolicy

log = logging.getLogger(__name__)

__all__ = ["run", "build", "parse_model_specs"]


DEFAULT_LIMIT_CONCURRENCY = 64
DEFAULT_MAX_CONNECTIONS = 1024
DEFAULT_HEADER_TIMEOUT = 10.0
DEFAULT_BODY_TIMEOUT = 30.0
DEFAULT_KEEP_ALIVE = 5
#: torch threads per inference thread. Requests already run 2 at a time; intra-op threads on
#: top of that measured no faster at 1 client and slower at 8 (p99 233/230/195 ms against
#: 289/274/289 ms in three alternating runs), and wait on one another whenever
#: the machine is busy
DEFAULT_TORCH_THREADS = 1


def _check_seconds(name: str, value: float | None, high: float = 3600.0) -> None:
    if value is not None and not (isinstance(value, (int, float)) and 0 < value <= high):
        raise ValueError(f"{name} must be a number of seconds in (0, {high:g}], got {value!r}")


def build(models: dict[str, str | None] | None = None, host: str = "127.0.0.1", *,
          token: str | None = None, token_file: str | os.PathLike | None = None,
          max_body_bytes: int | None = None, max_batch: int | None = None,
          inference_threads: int = 2, offset: float | None = None,
          max_block_side: int | None = None, max_pixels: int | None = None,
          limit_concurrency: int | None = DEFAULT_LIMIT_CONCURRENCY,
          body_timeout: float | None = DEFAULT_BODY_TIMEOUT, memory_budget: int | None = None,
          no_auth: bool = False, body_deadline: float | None = None, min_body_rate: int | None = None,
          body_grace: float | None = None, tau: float | None = None):
    """The app `run` serves, with models loaded and settings checked (tests use it too).
    `offset` overrides every model's calibrated decision offset (`serve --offset`); `tau`
    picks each model's offset at that noise target (`serve --tau`).
    Without a token the server runs only with `no_auth` (`serve --no-auth`), on loopback."""
    secret = resolve_token(token, token_file)
    check_bind(host, secret, no_auth)
    if secret is None:
        log.warning("--no-auth: running UNAUTHENTICATED, on loopback %s only", host)
    limits = Limits.from_env(max_body_bytes=max_body_bytes, max_batch=max_batch,
                             max_block_side=max_block_side, max_pixels=max_pixels, memory_budget=memory_budget)
    if isinstance(inference_threads, bool) or not isinstance(inference_threads, int) or not 1 <= inference_threads <= 256:
        raise ValueError(f"inference_threads must be 1..256, got {inference_threads!r}")
    if limit_concurrency is not None and (isinstance(limit_concurrency, bool) or not isinstance(limit_concurrency, int)
                                          or limit_concurrency < 1):
        raise ValueError(f"limit_concurrency must be a whole number >= 1, got {limit_concurrency!r}")
    _check_seconds("body_timeout", body_timeout)
    upload = UploadPolicy.from_env(stall=body_timeout, deadline=body_deadline, min_rate=min_body_rate,
                                   grace=body_grace)
    parse_seconds = env_seconds(os.environ, ENV_PARSE_SECONDS, DEFAULT_PARSE_SECONDS, 3600)
    registry = ModelRegistry(dict(models or {}), offset=offset, tau=tau)
    registry.load()
    return create_app(registry, token=secret, limits=limits, inference_threads=inference_threads,
                      limit_concurrency=limit_concurrency, body_timeout=body_timeout, upload=upload,
                      parse_seconds=parse_seconds)


def run(models: dict[str, str | None] | None = None, host: str = "127.0.0.1", port: int = 8000, *,
        token: str | None = None, token_file: str | os.PathLike | None = None,
        max_body_bytes: int | None = None, max_batch: int | None = None,
        inference_threads: int = 2, graceful_timeout: float = 30.0,
        log_level: str | None = None, offset: float | None = None,
        max_block_side: int | None = None, max_pixels: int | None = None,
        limit_concurrency: int | None = DEFAULT_LIMIT_CONCURRENCY,
        max_connections: int = DEFAULT_MAX_CONNECTIONS, header_timeout: float = DEFAULT_HEADER_TIMEOUT,
        body_timeout: float | None = DEFAULT_BODY_TIMEOUT, keep_alive: int = DEFAULT_KEEP_ALIVE,
        memory_budget: int | None = None, torch_threads: int = DEFAULT_TORCH_THREADS,
        no_auth: bool = False, body_deadline: float | None = None, min_body_rate: int | None = None,
        body_grace: float | None = None, tau: float | None = None) -> None:
    """Serve `models` ({name: bundle path or None for the bundled model}; empty: the bundled
    model) until SIGTERM/SIGINT. The token defaults to NOISESTOP_TOKEN / NOISESTOP_TOKEN_FILE;
    limits default to NOISESTOP_MAX_BODY_BYTES / NOISESTOP_MAX_BATCH / NOISESTOP_MAX_BLOCK_SIDE /
    NOISESTOP_MAX_PIXELS. Logs go to the root logger (uvicorn's own logging setup is off);
    `log_level` overrides uvicorn's level only. Connection settings: module doc.
    `torch_threads`: torch's intra-op threads for each of the `inference_threads`. `tau`:
    the noise target verdicts are made at unless a request sends its own (None: each
    model's calibrated offset)."""
    guard_start_up()          # SIGHUP until uvicorn's handlers take over (service.startup)
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ValueError(f"port must be 0..65535, got {port!r}")
    _check_seconds("graceful_timeout", graceful_timeout)
    _check_seconds("header_timeout", header_timeout)
    _check_seconds("keep_alive", keep_alive)
    if isinstance(max_connections, bool) or not isinstance(max_connections, int) or max_connections < 1:
        raise ValueError(f"max_connections must be a whole number >= 1, got {max_connections!r}")
    if isinstance(torch_threads, bool) or not isinstance(torch_threads, int) or not 1 <= torch_threads <= 256:
        raise ValueError(f"torch_threads must be 1..256, got {torch_threads!r}")
    import torch
    torch.set_num_threads(torch_threads)     # before any inference thread starts: they inherit it
    protocol = guarded_protocol(header_timeout)
    app = build(models, host, token=token, token_file=token_file, max_body_bytes=max_body_bytes,
                max_batch=max_batch, inference_threads=inference_threads, offset=offset, tau=tau,
                max_block_side=max_block_side, max_pixels=max_pixels, limit_concurrency=limit_concurrency,
                body_timeout=body_timeout, memory_budget=memory_budget, no_auth=no_auth,
                body_deadline=body_deadline, min_body_rate=min_body_rate, body_grace=body_grace)
    limits = app.state.limits
    log.info("listening on http://%s:%d (%s; body limit %d bytes, batch limit %d, block side %d px, "
             "%d pixels a request, %d bytes of memory for requests in flight; %s requests in flight, "
             "%d connections, headers within %g s)",
             f"[{host}]" if ":" in host else host, port,
             "token required" if app.state.token else "--no-auth: no token, loopback only",
             limits.max_body_bytes, limits.max_batch, limits.max_block_side, limits.max_pixels,
             limits.memory_budget,
             limit_concurrency if limit_concurrency is not None else "unlimited", max_connections,
             header_timeout)
    config = uvicorn.Config(app, host=host, port=port, log_config=None, log_level=log_level,
                            timeout_graceful_shutdown=graceful_timeout, http=protocol,
                            timeout_keep_alive=keep_alive, limit_concurrency=max_connections,
                            server_header=False, proxy_headers=False)
    _DrainingServer(config).run()


class _DrainingServer(uvicorn.Server):
    """uvicorn's server, which also drains on SIGHUP (by default a hang-up kills the process
    at once, without a word), and says in the log which signal started the drain."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        with super().capture_signals():
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            previous = signal.signal(signal.SIGHUP, self._hang_up)
            try:
                yield
            finally:
                signal.signal(signal.SIGHUP, previous)

    def _hang_up(self, sig: int, frame: FrameType | None) -> None:
        log.warning("SIGHUP: draining requests in flight, then exiting as for SIGTERM (no reload)")
        super().handle_exit(signal.SIGTERM, frame)   # after the drain, the process ends as by SIGTERM

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        name = signal.Signals(sig).name
        if self.should_exit and sig == signal.SIGINT:
            log.warning("%s again: stopping at once", name)
        elif not self.should_exit:
            log.warning("%s: no new connections; finishing the requests in flight, then exiting", name)
        super().handle_exit(sig, frame)
