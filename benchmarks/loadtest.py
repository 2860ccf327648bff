"""A bounded load test of the verdict service: JSON vs binary tensors, on loopback only.

`run_load` drives a running server with N client threads x M requests of `blocks` sub-images
(blocks + quick, FP32) and reports throughput and latency percentiles. `bench` starts a
server in a subprocess (so the clients do not share its interpreter lock), runs both
encodings and stops it. Counts and time are capped: this is a measurement, not a stress
test. `LocalServer`, `make_demo_bundle` and `make_request` are the tests' helpers
(tests/support), shared from the source checkout.
"""
from __future__ import annotations

import http.client
import json
import logging
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from service.auth import is_loopback
from service.oip import HEADER_LENGTH
from tests.support.demo import IMAGE_INPUTS, make_demo_bundle, make_request
from tests.support.local_server import LocalServer

log = logging.getLogger(__name__)

MAX_CLIENTS = 32
MAX_REQUESTS = 1000
MAX_SECONDS = 600.0


def served_inputs(host: str, port: int, model: str, token: str | None, timeout: float) -> str:
    """'halves' if the served model reads half buffers (its metadata lists 'even'), else 'blocks'."""
    conn = http.client.HTTPConnection(host, port, timeout=timeout)
    try:
        conn.request("GET", f"/v2/models/{model}", headers={"Authorization": f"Bearer {token}"} if token else {})
        resp = conn.getresponse()
        body = resp.read()
        if resp.status != 200:
            raise ValueError(f"model {model!r} metadata: HTTP {resp.status}: {body[:200]!r}")
        names = {t.get("name") for t in json.loads(body).get("inputs", [])}
    finally:
        conn.close()
    return "halves" if "even" in names else "blocks"


def run_load(url: str, *, model: str = "default", clients: int = 4, requests_per_client: int = 5,
             blocks: int = 16, size: int = 128, binary: bool = False, token: str | None = None,
             max_seconds: float = 120.0, timeout: float = 120.0) -> dict[str, Any]:
    """Throughput and latency of `clients` x `requests_per_client` infer requests.

    Returns requests, errors, wall_s, requests_per_s, blocks_per_s, p50_ms, p99_ms, mean_ms,
    request_bytes, and the inputs sent (the two image tensors the served model reads). Requests not started before `max_seconds` are skipped (counted in
    `skipped`).
    """
    parts = urlsplit(url)
    host, port = parts.hostname or "", parts.port or 80
    if parts.scheme != "http" or not is_loopback(host):
        raise ValueError(f"{url}: the load test runs against a loopback http:// server only")
    if not (1 <= clients <= MAX_CLIENTS and 1 <= requests_per_client <= MAX_REQUESTS
            and 0 < max_seconds <= MAX_SECONDS):
        raise ValueError(f"clients must be 1..{MAX_CLIENTS}, requests_per_client 1..{MAX_REQUESTS}, "
                         f"max_seconds (0, {MAX_SECONDS}]")
    kind = served_inputs(host, port, model, token, timeout)
    body, headers = make_request(blocks, size, binary, inputs=kind)
    if token:
        headers["Authorization"] = f"Bearer {token}"
    path = f"/v2/models/{model}/infer"
    latencies: list[float] = []
    errors: list[str] = []
    skipped = [0]
    lock = threading.Lock()
    start = threading.Barrier(clients + 1)
    deadline = [0.0]

    def client() -> None:
        conn = http.client.HTTPConnection(host, port, timeout=timeout)
        start.wait()
        try:
            for i in range(requests_per_client):
                if time.monotonic() > deadline[0]:
                    with lock:
                        skipped[0] += requests_per_client - i
                    return
                t0 = time.perf_counter()
                problem = post_infer(conn, path, body, headers, blocks)
                elapsed = time.perf_counter() - t0
                with lock:
                    (errors.append(problem) if problem else latencies.append(elapsed))
        finally:
            conn.close()

    threads = [threading.Thread(target=client, daemon=True) for _ in range(clients)]
    for t in threads:
        t.start()
    deadline[0] = time.monotonic() + max_seconds
    t_start = time.perf_counter()
    start.wait()
    for t in threads:
        t.join(max_seconds + timeout + 10)
    wall = time.perf_counter() - t_start
    if errors:
        log.warning("%d of %d requests failed, first: %s", len(errors), len(errors) + len(latencies),
                    errors[0])
    lat_ms = np.array(latencies) * 1e3
    stats = {"p50_ms": float(np.percentile(lat_ms, 50)), "p99_ms": float(np.percentile(lat_ms, 99)),
             "mean_ms": float(lat_ms.mean())} if len(lat_ms) else {"p50_ms": None, "p99_ms": None,
                                                                  "mean_ms": None}
    return {"encoding": "binary" if binary else "json", "clients": clients,
            "requests": len(latencies), "errors": len(errors), "skipped": skipped[0],
            "blocks_per_request": blocks, "block_size": size, "inputs": list(IMAGE_INPUTS[kind]),
            "request_bytes": len(body),
            "wall_s": wall, "requests_per_s": len(latencies) / wall,
            "blocks_per_s": len(latencies) * blocks / wall, **stats,
            "first_error": errors[0] if errors else None}


def post_infer(conn: http.client.HTTPConnection, path: str, body: bytes, headers: dict[str, str],
               blocks: int) -> str | None:
    """Send one infer request on `conn` and read the answer: None if it is a verdict for
    each of `blocks` blocks, else what went wrong (the connection is closed on a transport
    error, so the next request reconnects)."""
    try:
        conn.request("POST", path, body=body, headers=headers)
        resp = conn.getresponse()
        data = resp.read()
        if resp.status != 200:
            return f"HTTP {resp.status}: {data[:200]!r}"
        return _check_response(data, resp.getheader(HEADER_LENGTH), blocks)
    except (OSError, http.client.HTTPException) as exc:
        conn.close()
        return f"{type(exc).__name__}: {exc}"


def _check_response(data: bytes, header_length: str | None, blocks: int) -> str | None:
    try:
        head = json.loads(data[:int(header_length)] if header_length else data)
        shapes = {o["name"]: o["shape"] for o in head["outputs"]}
    except (ValueError, KeyError, TypeError) as exc:
        return f"unreadable response: {exc}"
    return None if shapes.get("verdict") == [blocks] else f"unexpected outputs {shapes}"


def bench(model: str | None = None, *, clients: int = 2, requests_per_client: int = 4,
          blocks: int = 16, size: int = 128, max_seconds: float = 60.0) -> dict[str, Any]:
    """Start a local server (the given bundle, else the bundled model, else a demo bundle),
    load it with JSON and with binary requests, and stop it."""
    from service.registry import bundle_name
    with tempfile.TemporaryDirectory() as tmp:
        source = model or "bundled"
        if model is None:
            try:
                bundle_name(None)
            except FileNotFoundError:
                model, source = str(make_demo_bundle(Path(tmp) / "demo")), "demo (synthetic blocks)"
        with LocalServer({"bench": model}) as server:
            results = {enc: run_load(server.url, token=server.token, binary=enc == "binary",
                                     clients=clients, requests_per_client=requests_per_client,
                                     blocks=blocks, size=size, max_seconds=max_seconds)
                       for enc in ("json", "binary")}
    return {"model": source, "cpus": os.cpu_count(), **results}
