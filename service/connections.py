"""Connection guards: a header-read timeout and a limit on requests in flight.

Why: without them, 64 idle half-open connections deny service to everyone for 40 s and
more (measured). uvicorn had no header-read timeout (its keep-alive timeout only runs between two
requests of one connection) and its `limit_concurrency` counts open connections, idle
ones included, and then answers 503 to every route, health probes too.

* `guarded_protocol(header_timeout)`: uvicorn's h11 protocol (fed in `H11_PIECE` slices)
  with a deadline for the request line and headers, armed when a connection opens and whenever it waits for a
  new request; a connection that has not sent complete headers by then is closed (408
  if it sent part of a request). Slow-header clients (slowloris) hold a connection for
  `header_timeout` seconds at most.
* `InFlightLimitMiddleware`: at most `limit` requests in flight (`serve
  --limit-concurrency`); over it, 503 with Retry-After and an {"error"} body. Health probes
  and /metrics are never counted nor refused, so a liveness probe does not kill a busy pod.
* `BodyLimitMiddleware` (service.body_limit) adds the body's own limits: a body that stalls
  for `body_timeout` seconds, is not complete within the whole-body deadline, or arrives
  slower than the minimum rate after the grace period is answered 408.
* A request h11 cannot parse is answered 400 with the {"error"} JSON body every other
  error has, naming what was wrong (`send_400_response`; uvicorn's is plain text) but
  never quoting the request: no header content goes back (`protocol_problem`).

uvicorn's own `limit_concurrency` stays on as the ceiling of open connections
(`serve --max-connections`), far above what idle clients can hold for long.
"""
from __future__ import annotations

import asyncio
import json
import logging
import re
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

#: bytes handed to h11 at a time. asyncio reads up to 256 KiB per call; h11 copies what it
#: is given three times over, and a 6.3 MB request body (16 blocks of 128x128, two
#: tensors) took 18 ms of the event loop in 256 KiB pieces against 3 ms in 64 KiB ones
#: (measured; the copies then stay in cache).
H11_PIECE = 64 * 1024

#: paths that are never counted against nor refused by the in-flight limit
EXEMPT_PREFIXES = ("/v2/health/", "/metrics")
_BODY_408 = b'{"error": "request headers took too long"}'
_TIMEOUT_408 = (b"HTTP/1.1 408 Request Timeout\r\ncontent-type: application/json\r\nconnection: close\r\n"
                b"content-length: " + str(len(_BODY_408)).encode() + b"\r\n\r\n" + _BODY_408)


def protocol_problem(exc: Exception) -> str:
    """What h11 found wrong, without what it quoted of the request: h11 puts the offending
    bytes in its message (``Illegal header value b'Bearer <token>\\x00'``), and a 400 that
    echoes a header line hands its token to whoever sent or relays it. The text up to the
    first quoted bytes is h11's own wording."""
    text = " ".join(str(exc).split())
    cut = _QUOTED.search(text)
    return (text[:cut.start()] if cut else text)[:200].rstrip(" :") or "malformed request"


#: where h11 starts quoting the request: a bytes or bytearray repr, or a quote opening a word
#: (an apostrophe inside one, as in "Can't", is h11's wording)
_QUOTED = re.compile(r"""(?:^|(?<=[\s(:=]))(?:bytearray\()?b?['"]""")


class _HeaderDeadlineProtocol(H11Protocol):
    """H11Protocol with a deadline on reading each request's line and headers."""

    header_timeout: float = 10.0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._protocol_problem: str | None = None
        next_event = self.conn.next_event

        def remembering_next_event():       # h11's reason for a 400, for send_400_response
            try:
                return next_event()
            except h11.RemoteProtocolError as exc:
                self._protocol_problem = protocol_problem(exc)
                raise
        self.conn.next_event = remembering_next_event      # type: ignore[method-assign]
        self._header_timer: asyncio.TimerHandle | None = None
        self._partial = False
        self._arm()

    def data_received(self, data: bytes) -> None:
        waiting = self.conn.their_state is h11.IDLE
        if waiting and self._header_timer is None:     # a new request on a kept-alive connection
            self._arm()
        if waiting and data:
            self._partial = True
        if len(data) <= H11_PIECE:
            super().data_received(data)
        else:
            view = memoryview(data)
            for start in range(0, len(data), H11_PIECE):
                super().data_received(view[start:start + H11_PIECE])
                if self.transport.is_closing():         # answered (e.g. 400): the rest is moot
                    break
        if self.conn.their_state is not h11.IDLE:       # request line and headers are in
            self._disarm()
            self._partial = False

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def send_400_response(self, msg: str) -> None:
        """A request h11 cannot parse (bad request line, header, chunk framing): 400 with the
        {"error": ...} body every other error has (uvicorn sends plain text), naming what
        h11 found wrong, then the connection is closed."""
        problem = getattr(self, "_protocol_problem", None)
        body = json.dumps({"error": f"invalid HTTP request: {problem}" if problem else
                           "invalid HTTP request"}).encode()
        try:
            for event in (h11.Response(status_code=400, reason=b"Bad Request", headers=[
                    (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close")]), h11.Data(data=body), h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
        except h11.LocalProtocolError:      # a response had already begun: just hang up
            pass
        self.transport.close()

    def _arm(self) -> None:
        self._disarm()
        self._header_timer = self.loop.call_later(self.header_timeout, self._expire)

    def _disarm(self) -> None:
        timer = getattr(self, "_header_timer", None)
        if timer is not None:
            timer.cancel()
            self._header_timer = None

    def _expire(self) -> None:
        self._header_timer = None
        if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
            return
        if self._partial:
            self.transport.write(_TIMEOUT_408)
        log.debug("closing a connection that sent no complete request headers in %.1f s", self.header_timeout)
        self.transport.close()


def guarded_protocol(header_timeout: float) -> type[H11Protocol]:
    """The protocol class for `uvicorn.Config(http=...)` with this header deadline (seconds)."""
    if not 0 < header_timeout <= 3600:
        raise ValueError(f"header_timeout must be in (0, 3600] seconds, got {header_timeout!r}")
    return type("HeaderDeadlineProtocol", (_HeaderDeadlineProtocol,), {"header_timeout": float(header_timeout)})


class HealthFastPath:
    """GET /v2/health/live and /v2/health/ready answered here, outside every other layer
    (limits, metrics, routing, the token): a probe is never queued behind a request.

    The routes in service.routes stay, for the OpenAPI document; this answers the same."""

    def __init__(self, app: Any, ready: Any) -> None:
        self.app = app
        self.ready = ready          # () -> bool

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or scope.get("method") not in ("GET", "HEAD") or \
                path not in ("/v2/health/live", "/v2/health/ready"):
            await self.app(scope, receive, send)
            return
        if path.endswith("/live"):
            status, body = 200, b'{"live":true}'
        else:
            ok = bool(self.ready())
            status, body = (200, b'{"ready":true}') if ok else (400, b'{"ready":false}')
        await send({"type": "http.response.start", "status": status, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": b"" if scope["method"] == "HEAD" else body})


class InFlightLimitMiddleware:
    """503 (Retry-After: 1) beyond `limit` requests in flight; probes and metrics exempt."""

    def __init__(self, app: Any, limit: int) -> None:
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"limit must be a whole number >= 1, got {limit!r}")
        self.app = app
        self.limit = limit
        self.in_flight = 0

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["path"].startswith(EXEMPT_PREFIXES):
            await self.app(scope, receive, send)
            return
        if self.in_flight >= self.limit:
            body = json.dumps({"error": f"server busy: {self.in_flight} requests in flight, the limit "
                                        f"is {self.limit} (serve --limit-concurrency); retry"}).encode()
            await send({"type": "http.response.start", "status": 503, "headers": [
                (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                (b"retry-after", b"1")]})
            await send({"type": "http.response.body", "body": body})
            return
        self.in_flight += 1     # one event loop: no lock needed
        try:
            await self.app(scope, receive, send)
        finally:
            self.in_flight -= 1
