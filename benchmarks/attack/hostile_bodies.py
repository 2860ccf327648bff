"""The hostile bodies sent: each worst shape once (with the server's peak RSS), the 62 MiB
nested request, a key twice, and a costly body in a loop beside timed normal requests.
"""
from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from .bodies import costliest_valid_json, nested_json_request_62, worst_shapes
from .wire import loopback_address, post, timed_get


def run_worst_shapes(url: str, token: str | None, max_body: int, concurrent: int = 1,
                     memory: Callable[[], dict[str, int]] | None = None) -> list[dict[str, Any]]:
    """Each worst shape once (and `concurrent` copies at once of the largest binary one):
    status, error message and, with `memory`, the server's peak RSS after it."""
    out = []
    for name, make in worst_shapes(max_body).items():
        body, headers = make()
        t0 = time.perf_counter()
        status, answer = post(url, body, headers, token)
        del body
        row = {"request": name, "status": status, "seconds": time.perf_counter() - t0,
               "error": json.loads(answer).get("error") if answer.startswith(b"{\"error") else None}
        if memory is not None:
            row.update(memory())
        out.append(row)
    if concurrent > 1:
        name, make = next((k, v) for k, v in worst_shapes(max_body).items() if k.startswith("widest"))
        body, headers = make()
        with ThreadPoolExecutor(concurrent) as pool:
            statuses = list(pool.map(lambda _: post(url, body, headers, token)[0], range(concurrent)))
        row = {"request": f"{concurrent} x {name} at once", "status": ",".join(str(s) for s in statuses),
               "statuses": statuses}
        if memory is not None:
            row.update(memory())
        out.append(row)
    return out


def duplicate_keys(url: str, token: str | None) -> dict[str, Any]:
    """`exposure` twice in one parameters object (1e30, then 0): 400, never served at 0."""
    from tests.support.demo import make_request
    body, headers = make_request(blocks=1, size=16)
    body = body[:-1] + b', "parameters": {"exposure": 1e30, "exposure": 0}}'
    status, answer = post(url, body, headers, token)
    return {"status": status, "error": json.loads(answer).get("error") if answer.startswith(b"{") else None}


def nested_over_budget(url: str, token: str | None, megabytes: int = 62) -> dict[str, Any]:
    """The 62 MiB nested request: ~62 MiB of JSON, every value inside 20 nested lists (56x its
    size in memory once parsed). Answered how, and how fast."""
    body, headers = nested_json_request_62(megabytes)
    t0 = time.perf_counter()
    status, answer = post(url, body, headers, token)
    return {"bytes": len(body), "status": status, "seconds": time.perf_counter() - t0,
            "error": json.loads(answer).get("error") if answer.startswith(b"{") else None}


def costly_json_loop(url: str, token: str | None, seconds: float = 20.0, requests: int = 200,
                     make: Callable[[], tuple[bytes, dict[str, str]]] | None = None,
                     attack: Callable[[], tuple[bytes, dict[str, str]]] = costliest_valid_json,
                     attackers: int = 1) -> dict[str, Any]:
    """Normal requests (and health probes every 50 ms) timed alone, then while `attackers`
    clients post `attack()`'s body (default `costliest_valid_json`) in a loop for up to
    `seconds`: p50/p99 of each, the attackers' answers and the slowest probe."""
    from ..loadtest import make_request
    host, port = loopback_address(url)
    body, headers = make() if make is not None else make_request(blocks=16, size=128, binary=True)
    bad, bad_headers = attack()

    def measure(stop_after: float) -> tuple[list[float], list[int | str]]:
        lat, st = [], []
        t_end = time.monotonic() + stop_after
        while time.monotonic() < t_end and len(lat) < requests:
            t0 = time.perf_counter()
            status, _ = post(url, body, headers, token, timeout=120)
            lat.append(time.perf_counter() - t0)
            st.append(status)
        return lat, st

    def probes(stop: threading.Event, out: list[float]) -> None:
        while not stop.is_set():
            out.append(timed_get(host, port, "/v2/health/ready", timeout=10)[1])
            stop.wait(0.05)

    alone, alone_st = measure(seconds / 2)
    stop = threading.Event()
    probe_alone: list[float] = []
    pt = threading.Thread(target=probes, args=(stop, probe_alone), daemon=True)
    pt.start()
    time.sleep(1.0)
    stop.set()
    pt.join()
    attack_statuses: list[int | str] = []
    attack_s: list[float] = []

    def attacker(stop: threading.Event) -> None:
        while not stop.is_set():
            t0 = time.perf_counter()
            attack_statuses.append(post(url, bad, bad_headers, token, timeout=120)[0])
            attack_s.append(time.perf_counter() - t0)

    stop = threading.Event()
    probe_times: list[float] = []
    threads = [*(threading.Thread(target=attacker, args=(stop,), daemon=True) for _ in range(attackers)),
               threading.Thread(target=probes, args=(stop, probe_times), daemon=True)]
    for t in threads:
        t.start()
    time.sleep(1.0)
    loaded, loaded_st = measure(seconds)
    stop.set()
    for t in threads:
        t.join(130)
    a, b = np.array(alone) * 1e3, np.array(loaded) * 1e3
    return {"body_bytes": len(bad), "alone_p50_ms": float(np.percentile(a, 50)), "alone_p99_ms": float(np.percentile(a, 99)),
            "loaded_p50_ms": float(np.percentile(b, 50)), "loaded_p99_ms": float(np.percentile(b, 99)),
            "p99_ratio": float(np.percentile(b, 99) / np.percentile(a, 99)),
            "normal_statuses": sorted({str(s) for s in alone_st + loaded_st}),
            "normal_ok": sum(s == 200 for s in loaded_st), "normal_requests": len(loaded_st),
            "attacker_statuses": sorted({str(s) for s in attack_statuses}), "attacker_requests": len(attack_statuses),
            "attacker_mean_s": float(np.mean(attack_s)) if attack_s else None,
            "health_max_ms": float(max(probe_times) * 1e3) if probe_times else None,
            "health_p95_ms": float(np.percentile(probe_times, 95) * 1e3) if probe_times else None,
            "health_idle_max_ms": float(max(probe_alone) * 1e3) if probe_alone else None,
            "health_probes": len(probe_times)}
