"""Connection-level abuse: idle connections, slow headers, a stalled body, the in-flight
limit, a request line h11 cannot parse. Each returns what happened as plain numbers.
"""
from __future__ import annotations

import http.client
import json
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .wire import loopback_address, status_of, timed_get, wait_closed

MAX_CONNECTIONS = 512


def idle_flood(url: str, n: int = 64, probes: int = 10, wait: float = 30.0,
               infer: Callable[[], int | str] | None = None) -> dict[str, Any]:
    """n idle connections (half silent, half with a partial request line) held open while
    `probes` health checks (live and ready, alternating) and `infer` run; then the seconds
    until the server has closed every one (at most `wait`)."""
    host, port = loopback_address(url)
    if not 1 <= n <= MAX_CONNECTIONS:
        raise ValueError(f"n must be 1..{MAX_CONNECTIONS}, got {n}")
    socks = []
    try:
        for i in range(n):
            s = socket.create_connection((host, port), timeout=10)
            if i % 2:
                s.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n")   # never finished
            socks.append(s)
        t_open = time.monotonic()
        health = [timed_get(host, port, "/v2/health/live" if i % 2 == 0 else "/v2/health/ready")
                  for i in range(probes)]
        infer_status = infer() if infer is not None else None
        closed, statuses = 0, {}
        deadline = t_open + wait
        for s in socks:
            ok, got = wait_closed(s, deadline)
            closed += ok
            code = got.split(b" ", 2)[1].decode() if got.startswith(b"HTTP/1.1 ") else "none"
            statuses[code] = statuses.get(code, 0) + 1
        return {"connections": n, "health_status": sorted({str(h[0]) for h in health}),
                "health_ok": sum(h[0] == 200 for h in health), "probes": probes,
                "health_max_s": max(h[1] for h in health), "health_median_s": float(np.median([h[1] for h in health])),
                "infer_status": infer_status, "closed_by_server": closed,
                "all_closed_after_s": time.monotonic() - t_open if closed == n else None,
                "answers_before_close": statuses}
    finally:
        for s in socks:
            s.close()


def slow_headers(url: str, interval: float = 0.2, limit_s: float = 60.0) -> dict[str, Any]:
    """Send a request's headers one byte every `interval` seconds; when did the server hang up?"""
    host, port = loopback_address(url)
    line = b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n" + b"X-Slow: " + b"a" * 4000 + b"\r\n\r\n"
    s = socket.create_connection((host, port), timeout=10)
    t0 = time.monotonic()
    sent, got = 0, b""
    try:
        while sent < len(line) and time.monotonic() - t0 < limit_s:
            try:
                s.sendall(line[sent:sent + 1])
            except OSError:
                break
            sent += 1
            s.settimeout(interval)
            try:
                chunk = s.recv(4096)
                if not chunk:
                    break
                got += chunk
            except TimeoutError:
                continue
            except OSError:
                break
        closed, rest = wait_closed(s, time.monotonic() + 5)
        got += rest
    finally:
        s.close()
    return {"bytes_sent": sent, "header_bytes": len(line), "cut_off": sent < len(line),
            "after_s": time.monotonic() - t0, "status": got.split(b" ", 2)[1].decode()
            if got.startswith(b"HTTP/1.1 ") else None}


def stalled_body(url: str, token: str | None, declared: int = 1000, sent: int = 10,
                 limit_s: float = 60.0) -> dict[str, Any]:
    """Headers announcing `declared` body bytes, `sent` of them, then silence."""
    host, port = loopback_address(url)
    s = socket.create_connection((host, port), timeout=limit_s)
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    t0 = time.monotonic()
    try:
        s.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\n{auth}"
                   f"Content-Type: application/json\r\nContent-Length: {declared}\r\n\r\n").encode() + b"{" * sent)
        _, got = wait_closed(s, t0 + limit_s)
    finally:
        s.close()
    status = got.split(b" ", 2)[1].decode() if got.startswith(b"HTTP/1.1 ") else None
    return {"status": status, "after_s": time.monotonic() - t0}


def over_the_limit(url: str, token: str | None, limit: int) -> dict[str, Any]:
    """Hold `limit` requests in flight (stalled bodies), then send one more and probe health."""
    host, port = loopback_address(url)
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    held = []
    try:
        for _ in range(limit):
            s = socket.create_connection((host, port), timeout=30)
            s.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\n{auth}Content-Length: 100\r\n"
                       "Content-Type: application/json\r\n\r\n{").encode())
            held.append(s)
        deadline = time.monotonic() + 20         # the server reads the held ones as it gets to them
        attempts = 0
        while True:
            attempts += 1
            extra = http.client.HTTPConnection(host, port, timeout=30)
            extra.request("POST", "/v2/models/default/infer", body=b"{}",
                          headers={"Content-Type": "application/json",
                                   **({"Authorization": f"Bearer {token}"} if token else {})})
            resp = extra.getresponse()
            body = resp.read()
            retry_after = resp.getheader("Retry-After")
            extra.close()
            if resp.status == 503 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        health = timed_get(host, port, "/v2/health/ready")
        return {"held": limit, "extra_status": resp.status, "retry_after": retry_after, "attempts": attempts,
                "error": json.loads(body).get("error") if body.startswith(b"{") else None,
                "health_status": health[0]}
    finally:
        for s in held:
            s.close()


def protocol_error(url: str) -> dict[str, Any]:
    """A request h11 cannot parse: the status, content type and {"error"} body of the answer."""
    host, port = loopback_address(url)
    s = socket.create_connection((host, port), timeout=10)
    try:
        s.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nBad Header Line\r\n\r\n")
        _, got = wait_closed(s, time.monotonic() + 10)
    finally:
        s.close()
    head, _, body = got.partition(b"\r\n\r\n")
    ctype = next((line.split(b":", 1)[1].strip().decode() for line in head.split(b"\r\n")
                  if line.lower().startswith(b"content-type:")), None)
    try:
        error = json.loads(body).get("error")
    except ValueError:
        error = None
    return {"status": status_of(got), "content_type": ctype, "error": error}
