"""Open-loop load: requests arrive at a set rate whether or not earlier ones are answered.

A closed loop (N clients, each waiting for its answer) slows its own arrivals when the
server slows, so it cannot tell a user what latency to expect at a given traffic. Here
arrival times are drawn up front (Poisson, seeded) and each request's latency runs from its
*scheduled* arrival to its answer, so time spent waiting for a free connection counts too
(no coordinated omission). Loopback only, counts and time capped, like `loadtest.run_load`.
"""
from __future__ import annotations

import http.client
import queue
import threading
import time
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from service.auth import is_loopback
from tests.support.demo import make_request
from .loadtest import post_infer, served_inputs

MAX_RATE = 1000.0
MAX_REQUESTS = 5000
MAX_CONNECTIONS = 64


def arrival_times(rate: float, requests: int, seed: int = 0) -> np.ndarray:
    """Seconds from the start at which each request arrives: a Poisson process of `rate`
    per second (exponential gaps), the first at its first gap."""
    if not (0 < rate <= MAX_RATE) or not (1 <= requests <= MAX_REQUESTS):
        raise ValueError(f"rate must be in (0, {MAX_RATE:g}] per second and requests in 1..{MAX_REQUESTS}, "
                         f"got {rate!r} and {requests!r}")
    gaps = np.random.default_rng(seed).exponential(1.0 / rate, requests)
    return np.cumsum(gaps)


def run_open_loop(url: str, *, rate: float, requests: int, model: str = "default", blocks: int = 16,
                  size: int = 64, token: str | None = None, connections: int = 16, seed: int = 0,
                  timeout: float = 60.0) -> dict[str, Any]:
    """Send `requests` binary infer requests at Poisson arrivals of `rate` per second.

    Parameters
    ----------
    url : a loopback ``http://`` server.
    rate : mean arrivals per second.
    requests : how many requests in all.
    model, blocks, size, token : what each request asks (as `loadtest.run_load`).
    connections : persistent connections that carry the requests; a request whose arrival
        finds them all busy waits, and the wait is in its latency.
    seed : the arrival times' seed.

    Returns
    -------
    dict with offered_rate, achieved_rate (answers per second over the run), requests,
    errors, p50_ms, p99_ms, mean_ms, max_lag_ms (latest start behind schedule) and
    blocks_per_s.
    """
    parts = urlsplit(url)
    host, port = parts.hostname or "", parts.port or 80
    if parts.scheme != "http" or not is_loopback(host):
        raise ValueError(f"{url}: the load test runs against a loopback http:// server only")
    if not 1 <= connections <= MAX_CONNECTIONS:
        raise ValueError(f"connections must be 1..{MAX_CONNECTIONS}, got {connections!r}")
    arrivals = arrival_times(rate, requests, seed)
    kind = served_inputs(host, port, model, token, timeout)
    body, headers = make_request(blocks, size, binary=True, inputs=kind)
    if token:
        headers["Authorization"] = f"Bearer {token}"
    path = f"/v2/models/{model}/infer"
    todo: queue.SimpleQueue[float | None] = queue.SimpleQueue()
    latencies: list[float] = []
    lags: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()
    def worker() -> None:
        conn = http.client.HTTPConnection(host, port, timeout=timeout)
        try:
            while (due := todo.get()) is not None:
                wait = start_at + due - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                start = time.perf_counter()
                problem = post_infer(conn, path, body, headers, blocks)
                done = time.perf_counter()
                with lock:
                    lags.append(start - (start_at + due))
                    (errors.append(problem) if problem else latencies.append(done - (start_at + due)))
        finally:
            conn.close()

    start_at = time.perf_counter() + 0.05          # every arrival time counts from here
    threads = [threading.Thread(target=worker, daemon=True) for _ in range(connections)]
    for due in arrivals:
        todo.put(float(due))
    for _ in threads:
        todo.put(None)
    for t in threads:
        t.start()
    for t in threads:
        t.join(float(arrivals[-1]) + timeout * requests / connections + 10)
    wall = time.perf_counter() - start_at
    lat_ms = np.array(latencies) * 1e3
    stats = {"p50_ms": float(np.percentile(lat_ms, 50)), "p99_ms": float(np.percentile(lat_ms, 99)),
             "mean_ms": float(lat_ms.mean())} if len(lat_ms) else {"p50_ms": None, "p99_ms": None, "mean_ms": None}
    return {"offered_rate": float(rate), "achieved_rate": len(latencies) / wall, "requests": len(latencies),
            "errors": len(errors), "first_error": errors[0] if errors else None,
            "blocks_per_request": blocks, "block_size": size, "blocks_per_s": len(latencies) * blocks / wall,
            "max_lag_ms": 1e3 * max(lags) if lags else None, **stats}
