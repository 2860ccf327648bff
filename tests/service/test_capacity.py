"""Open-loop load and the capacity section: arrivals on schedule, waiting counted in latency."""
from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler

import numpy as np
import pytest

from benchmarks.bench_capacity import md_capacity
from benchmarks.openloop import arrival_times, run_open_loop
from tests.support.live_server import handler_server

SERVICE_S = 0.05
BLOCKS = 4


class _SlowVerdicts(BaseHTTPRequestHandler):
    """A stand-in server that takes SERVICE_S per verdict, one at a time."""

    lock = threading.Lock()

    def log_message(self, *args: object) -> None:
        pass

    def do_GET(self) -> None:
        self._send(json.dumps({"inputs": [{"name": "blocks"}, {"name": "quick"}]}).encode())

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["Content-Length"]))
        with self.lock:
            time.sleep(SERVICE_S)
        self._send(json.dumps({"outputs": [{"name": "verdict", "shape": [BLOCKS]}]}).encode())

    def _send(self, body: bytes) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)


@pytest.fixture
def slow_server():
    with handler_server(_SlowVerdicts) as url:
        yield url


def test_arrivals_are_a_seeded_poisson_process_of_the_rate():
    t = arrival_times(50.0, 4000, seed=3)
    assert np.all(np.diff(t) > 0) and t[0] > 0
    assert np.array_equal(t, arrival_times(50.0, 4000, seed=3))
    assert abs(np.diff(t).mean() - 1 / 50.0) < 0.1 / 50.0
    gaps = np.diff(t)
    assert abs(gaps.std() / gaps.mean() - 1.0) < 0.1          # exponential: coefficient of variation 1


@pytest.mark.parametrize("rate, n", [(0.0, 10), (-1.0, 10), (float("nan"), 10), (float("inf"), 10), (5.0, 0)])
def test_arrivals_refuse_bad_rates_and_counts(rate, n):
    with pytest.raises(ValueError, match="rate must be"):
        arrival_times(rate, n)


def test_open_loop_refuses_remote_servers():
    with pytest.raises(ValueError, match="loopback"):
        run_open_loop("http://example.com:80", rate=1.0, requests=1)


def test_open_loop_counts_the_wait_for_a_busy_server_in_latency(slow_server):
    """Ten requests arrive within ~10 ms at one connection of a 50 ms server: the k-th answer
    comes about k x 50 ms after its arrival, which a closed loop would have hidden."""
    r = run_open_loop(slow_server, rate=1000.0, requests=10, blocks=BLOCKS, size=8, connections=1)
    assert r["requests"] == 10 and r["errors"] == 0
    assert r["p50_ms"] >= 4 * SERVICE_S * 1e3
    assert r["p99_ms"] >= 8 * SERVICE_S * 1e3
    assert r["max_lag_ms"] >= 7 * SERVICE_S * 1e3


def test_open_loop_below_capacity_answers_about_as_fast_as_the_server(slow_server):
    """Below capacity nothing waits: the median is the server's time plus the machine's own
    delay, which a busy CI box makes large (the bound is generous; the figures are
    BENCHMARKS.md's)."""
    r = run_open_loop(slow_server, rate=5.0, requests=8, blocks=BLOCKS, size=8, connections=2, seed=1)
    assert r["requests"] == 8 and r["errors"] == 0
    assert SERVICE_S * 1e3 <= r["p50_ms"] < 20 * SERVICE_S * 1e3


def test_capacity_markdown_has_a_row_per_decider_and_load_share():
    result = {"cpus": 2, "blocks": 16, "served_size": 64, "repeats": 3,
              "per_core": [{"what": w, "size": s, "blocks": 16, "ms_per_request": 16.0,
                            "blocks_per_s_per_core": 1000.0, "other_load": 0.01}
                           for w in ("bundled model", "flip criterion") for s in (64, 128)],
              "served": {"capacity_rps": 40.0, "capacity_rounds": [39.0, 40.0, 41.0], "saturated_p50_ms": 190.0,
                         "saturated_p99_ms": 260.0,
                         "open_loop": [{"share": sh, "offered_rate": 40 * sh, "achieved_rate": 40 * sh, "p50_ms": 30.0,
                                        "p99_ms": 90.0, "p99_rounds": [80.0, 90.0, 95.0], "requests": 900,
                                        "errors": 0, "other_load": None} for sh in (0.5, 0.8)]}}
    md = md_capacity(result)
    assert md.count("| bundled model |") == 2 and md.count("| flip criterion |") == 2
    assert "640 blocks/s (320 per core)" in md
    assert "| 50 % | 20.0 | 20.0 | 900 | 30 | 90 (80, 90, 95) | 0 | - |" in md
    assert "| 80 % | 32.0 |" in md


@pytest.fixture(scope="module")
def real_server():
    """The command itself, `noisestop serve` with the bundled model on 127.0.0.1, at most two
    blocks a request (--max-batch 2); stopped when the module's tests end."""
    from tests.support.local_server import LocalServer

    with LocalServer({"default": None}, argv=["--max-batch", "2"]) as server:
        yield server


@pytest.mark.timeout(300)
def test_open_loop_against_a_real_noisestop_serve(real_server):
    """Bounded open-loop traffic (24 requests of 2 blocks, 8 a second, loopback) gets a
    verdict of the right shape for every request; control: requests over the server's
    --max-batch are counted as errors, none as answers."""
    common = {"token": real_server.token, "size": 32, "connections": 2, "timeout": 60.0}
    r = run_open_loop(real_server.url, rate=8.0, requests=24, blocks=2, seed=5, **common)
    assert r["requests"] == 24 and r["errors"] == 0 and r["first_error"] is None
    assert 0 < r["p50_ms"] <= r["p99_ms"] and r["achieved_rate"] > 0
    assert r["blocks_per_s"] == pytest.approx(2 * r["achieved_rate"])
    refused = run_open_loop(real_server.url, rate=8.0, requests=4, blocks=4, seed=6, **common)
    assert refused["requests"] == 0 and refused["errors"] == 4 and "HTTP 413" in refused["first_error"]
