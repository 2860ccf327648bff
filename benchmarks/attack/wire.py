"""The attacks' side of the wire: plain HTTP/1.1 on loopback, one fresh connection per call.

Why not an HTTP client library: the scenarios need to send what no well-behaved client
sends (half a request line, a body that stops) and to see exactly when the server hangs
up; and `loopback_address` keeps every scenario on this machine.
"""
from __future__ import annotations

import http.client
import socket
import time
from urllib.parse import urlsplit

from service.auth import is_loopback


def loopback_address(url: str) -> tuple[str, int]:
    """(host, port) of `url`; ValueError unless it is http:// on a loopback address."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    if parts.scheme != "http" or not is_loopback(host):
        raise ValueError(f"{url}: attack scenarios run against a loopback http:// server only")
    return host, parts.port or 80


def timed_get(host: str, port: int, path: str, timeout: float = 10.0) -> tuple[int | str, float]:
    """(status or error name, seconds) of one GET on a fresh connection."""
    t0 = time.perf_counter()
    conn = http.client.HTTPConnection(host, port, timeout=timeout)
    try:
        conn.request("GET", path)
        resp = conn.getresponse()
        resp.read()
        return resp.status, time.perf_counter() - t0
    except OSError as exc:
        return type(exc).__name__, time.perf_counter() - t0
    finally:
        conn.close()


def post(url: str, body: bytes, headers: dict[str, str], token: str | None = None,
         path: str = "/v2/models/default/infer", timeout: float = 300.0) -> tuple[int | str, bytes]:
    """(status or error name, body) of one POST; a server that hangs up early is an error name."""
    host, port = loopback_address(url)
    conn = http.client.HTTPConnection(host, port, timeout=timeout)
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    try:
        conn.request("POST", path, body=body, headers={**auth, **headers})
        resp = conn.getresponse()
        return resp.status, resp.read()
    except OSError as exc:
        return type(exc).__name__, b""
    finally:
        conn.close()


def wait_closed(sock: socket.socket, deadline: float) -> tuple[bool, bytes]:
    """Wait until the server closes `sock` (or the deadline); (closed, bytes it sent)."""
    got = b""
    while time.monotonic() < deadline:
        sock.settimeout(max(0.05, deadline - time.monotonic()))
        try:
            chunk = sock.recv(4096)
        except TimeoutError:
            break
        except OSError:
            return True, got
        if not chunk:
            return True, got
        got += chunk
    return False, got


def status_of(raw: bytes) -> int | None:
    """The status code of a raw HTTP/1.1 answer (None: no answer, or not one)."""
    return int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/1.1 ") and raw[9:12].isdigit() else None
