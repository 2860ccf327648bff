"""Slow uploaders: bodies trickled a byte at a time, or sent in a burst and then stalled,
while normal requests are timed beside them (the upload policy and budget's tests).
"""
from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .wire import loopback_address, post, status_of, wait_closed


def slow_upload(url: str, token: str | None, stop: threading.Event, declared: int | None = 64 << 20,
                interval: float = 1.0, limit_s: float = 600.0,
                out: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """One client trickling a body, one byte every `interval` seconds (chunked when
    `declared` is None, else under that Content-Length), reconnecting whenever the server
    hangs up, until `stop` is set. Each connection: its answer and how long it was held
    (appended to `out` as each ends, if given)."""
    host, port = loopback_address(url)
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    framing = "Transfer-Encoding: chunked\r\n" if declared is None else f"Content-Length: {declared}\r\n"
    piece = b"1\r\n[\r\n" if declared is None else b"["
    out = [] if out is None else out
    t_end = time.monotonic() + limit_s
    while not stop.is_set() and time.monotonic() < t_end:
        t0 = time.monotonic()
        try:
            s = socket.create_connection((host, port), timeout=10)
        except OSError as exc:
            out.append({"status": type(exc).__name__, "held_s": 0.0})
            stop.wait(interval)
            continue
        got = b""
        try:
            s.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\n{auth}"
                       f"Content-Type: application/json\r\n{framing}\r\n").encode())
            while not stop.is_set():
                s.sendall(piece)
                s.settimeout(interval)
                try:
                    chunk = s.recv(4096)
                except TimeoutError:
                    continue
                got += chunk
                if not chunk:
                    break
                if got.startswith(b"HTTP/"):           # answered: read the rest of the answer
                    got += wait_closed(s, time.monotonic() + 5)[1]
                    break
        except OSError:
            pass
        finally:
            s.close()
        out.append({"status": status_of(got), "held_s": time.monotonic() - t0,
                    "error": json.loads(got.split(b"\r\n\r\n", 1)[1]).get("error")
                    if b"\r\n\r\n{" in got else None})
    return out


def normal_latency_under_slow_uploads(url: str, token: str | None, slow: int, *, requests: int = 40,
                                      warm_up: float = 2.0, interval: float = 1.0, declared: int | None = 64 << 20,
                                      make: Callable[[], tuple[bytes, dict[str, str]]] | None = None) -> dict[str, Any]:
    """`slow` slow uploaders (`slow_upload`, half of them chunked) connected, then
    `requests` normal infer requests one after another: their p50/p99 latency and
    statuses, and what became of the slow uploads."""
    from tests.support.demo import make_request
    if not 0 <= slow <= 64:
        raise ValueError(f"slow must be 0..64, got {slow}")
    body, headers = make() if make is not None else make_request(blocks=4, size=64, binary=True)
    stop = threading.Event()
    results: list[list[dict[str, Any]]] = [[] for _ in range(slow)]

    def uploader(i: int) -> None:
        results[i] = slow_upload(url, token, stop, None if i % 2 else declared, interval)

    threads = [threading.Thread(target=uploader, args=(i,), daemon=True) for i in range(slow)]
    for t in threads:
        t.start()
    try:
        stop.wait(warm_up if slow else 0)
        latencies, statuses = [], []
        for _ in range(requests):
            t0 = time.perf_counter()
            status, _ = post(url, body, headers, token, timeout=120)
            latencies.append(time.perf_counter() - t0)
            statuses.append(status)
    finally:
        stop.set()
        for t in threads:
            t.join(interval + 15)
    ms = np.array(latencies) * 1e3
    slow_rows = [r for rows in results for r in rows]
    return {"slow_clients": slow, "requests": requests, "ok": sum(s == 200 for s in statuses),
            "statuses": sorted({str(s) for s in statuses}), "p50_ms": float(np.percentile(ms, 50)),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max()),
            "slow_connections": len(slow_rows),
            "slow_statuses": sorted({str(r["status"]) for r in slow_rows}),
            "slow_held_max_s": max((r["held_s"] for r in slow_rows), default=0.0)}


def _stall_after_burst(host: str, port: int, token: str | None, payload: bytes, declared: int,
                       release: threading.Event, out: dict[str, Any]) -> None:
    """Headers, `payload` as fast as the server takes it, then silence until `release`."""
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    t0 = time.monotonic()
    try:
        s = socket.create_connection((host, port), timeout=60)
    except OSError as exc:
        out.update(status=type(exc).__name__, held_s=0.0)
        return
    got = b""
    try:
        s.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\n{auth}Content-Type: application/json\r\n"
                   f"Content-Length: {declared}\r\n\r\n").encode())
        view = memoryview(payload)
        for i in range(0, len(view), 1 << 20):
            if release.is_set():
                break
            s.sendall(view[i:i + (1 << 20)])
        s.settimeout(0.5)
        while not release.is_set():
            try:
                chunk = s.recv(4096)
            except TimeoutError:
                continue
            if not chunk:
                break
            got += chunk
    except OSError as exc:             # the server hung up on it (ended while it stalled)
        got = got or type(exc).__name__.encode()
    finally:
        s.close()
    out.update(status=status_of(got) or got.decode(errors="replace")[:40] or None, held_s=time.monotonic() - t0)


def burst_then_stall(url: str, token: str | None, stallers: int = 16, megabytes: int = 63,
                     hold_s: float = 20.0, after_s: float = 10.0,
                     make: Callable[[], tuple[bytes, dict[str, str]]] | None = None) -> dict[str, Any]:
    """`stallers` clients each declare a body of `megabytes` + 1 MiB, send `megabytes` fast,
    then stall; normal requests run one after another the whole time. After `hold_s` the
    stallers hang up; normal requests go on for `after_s`. Statuses of the normal requests
    while the stallers held on, and how long after they hung up the first 200 came."""
    from ..loadtest import make_request
    host, port = loopback_address(url)
    if not 0 <= stallers <= 64 or not 0 < megabytes <= 256 or not 0 < hold_s <= 120 or not 0 < after_s <= 60:
        raise ValueError("stallers 0..64, megabytes 1..256, hold_s 1..120, after_s 1..60")
    body, headers = make() if make is not None else make_request(blocks=16, size=128, binary=True)
    payload = b"[" * (megabytes << 20)
    release = threading.Event()
    outs: list[dict[str, Any]] = [{} for _ in range(stallers)]
    threads = [threading.Thread(target=_stall_after_burst, daemon=True,
                                args=(host, port, token, payload, (megabytes + 1) << 20, release, outs[i]))
               for i in range(stallers)]
    for t in threads:
        t.start()
    during: list[tuple[float, int | str, float]] = []
    after: list[tuple[float, int | str, float]] = []
    t_start = time.monotonic()
    released_at = None
    while True:
        now = time.monotonic()
        if released_at is None and now - t_start >= hold_s:
            release.set()
            released_at = now
        if released_at is not None and now - released_at >= after_s:
            break
        t0 = time.perf_counter()
        status, _ = post(url, body, headers, token, timeout=120)
        (during if released_at is None else after).append((now - t_start, status, time.perf_counter() - t0))
    release.set()
    for t in threads:
        t.join(30)
    ok_after = [t for t, s, _ in after if s == 200]
    during_ms = np.array([x[2] for x in during if x[1] == 200] or [np.nan]) * 1e3
    return {"stallers": stallers, "megabytes": megabytes, "hold_s": hold_s,
            "during": len(during), "during_ok": sum(s == 200 for _, s, _ in during),
            "during_statuses": sorted({str(s) for _, s, _ in during}),
            "during_p50_ms": float(np.nanpercentile(during_ms, 50)), "during_p99_ms": float(np.nanpercentile(during_ms, 99)),
            "after": len(after), "after_ok": sum(s == 200 for _, s, _ in after),
            "first_200_after_s": (ok_after[0] - (released_at - t_start)) if ok_after else None,
            "staller_statuses": sorted({str(o.get("status")) for o in outs})}
