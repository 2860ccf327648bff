"""A bounded load test of the verdict service: JSON vs binary tensors, on loopback only.

`run_load` drives a running server with N client threads x M requests of `blocks` sub-images
(blocks + quick, FP32) and reports throughput and latency percentiles. `bench` starts a
server in a subprocess (so the clients do not share its interpreter lock), runs both
encodings and stops it. Counts and time are capped: this is a measurement, not a stress
test. `LocalServer` and `make_demo_bundle` are also what the service tests use.
"""
from __future__ import annotations

import http.client
import json
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from ..auth import ENV_TOKEN, is_loopback
from ..oip import HEADER_LENGTH

log = logging.getLogger(__name__)

MAX_CLIENTS = 32
MAX_REQUESTS = 1000
MAX_SECONDS = 600.0


def make_demo_bundle(path: str | os.PathLike, seed: int = 0, name: str = "demo", n: int = 160,
                     size: int = 32) -> Path:
    """A DSVM bundle for tests and benches, fitted in well under a second on synthetic blocks
    (smooth colour ramps, as quick images, plus Gaussian noise of random strength; +1 where
    the noise is weak). Its verdicts mean nothing about real renders; its inputs and costs
    are those of a real feature model."""
    from learning.models.bundle import save_model
    from learning.models.estimators import DSVM
    from noisefeat import extract_features
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0.0, 1.0, size, dtype=np.float32)[None, :, None, None]
    quick = (0.1 + 0.6 * rng.random((n, 1, 1, 3), dtype=np.float32) * ramp).repeat(size, 2)
    sigma = rng.uniform(0.0, 0.2, n).astype(np.float32)
    current = quick + sigma[:, None, None, None] * rng.standard_normal(quick.shape, dtype=np.float32)
    X = extract_features(quick) - extract_features(current)
    y = np.where(sigma < 0.05, 1, -1)
    return save_model(DSVM(C=10.0).fit(X, y), path, kind="dsvm", input="features", name=name,
                      training={"data": f"{n} synthetic {size}x{size} blocks (demo)"})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalServer:
    """`noisestop serve` in a subprocess on 127.0.0.1 with a fresh token (or none, with
    `no_auth=True`, which the server then needs as `--no-auth`); stopped by SIGTERM."""

    def __init__(self, models: dict[str, str | None], *, port: int | None = None,
                 token: str | None = None, startup_timeout: float = 120.0,
                 env: dict[str, str] | None = None, address_space: int | None = None,
                 no_auth: bool = False, **serve_kwargs: Any) -> None:
        self.models = {k: (None if v is None else str(v)) for k, v in models.items()}
        self.port = port or free_port()
        if no_auth and token is not None:
            raise ValueError("a token and no_auth: choose one")
        self.token = None if no_auth else (token or secrets.token_urlsafe(24))
        if no_auth:
            serve_kwargs["no_auth"] = True
        self.url = f"http://127.0.0.1:{self.port}"
        self.startup_timeout = startup_timeout
        self.env = env or {}
        self.serve_kwargs = serve_kwargs
        self.address_space = address_space     # RLIMIT_AS of the server process, bytes (None: no limit)
        self.process: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    def __enter__(self) -> "LocalServer":
        code = ("import json, logging, sys; logging.basicConfig(level=logging.INFO, stream=sys.stderr); "
                "from service.serve import run; a = json.loads(sys.argv[1]); "
                "run(a['models'], '127.0.0.1', a['port'], **a['kwargs'])")
        arg = json.dumps({"models": self.models, "port": self.port, "kwargs": self.serve_kwargs})
        env = {**os.environ, **self.env}
        env.pop("NOISESTOP_TOKEN_FILE", None)
        env.pop(ENV_TOKEN, None)
        if self.token is not None:
            env[ENV_TOKEN] = self.token
        self.process = subprocess.Popen([sys.executable, "-c", code, arg], env=env,
                                        stdout=subprocess.DEVNULL, stderr=self._log,
                                        preexec_fn=self._limit if self.address_space else None)
        deadline = time.monotonic() + self.startup_timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with status {self.process.returncode}:\n{self.log()}")
            try:
                with urllib.request.urlopen(self.url + "/v2/health/ready", timeout=1) as r:
                    if r.status == 200:
                        return self
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                time.sleep(0.2)
        self.__exit__(None, None, None)
        raise RuntimeError(f"server not ready after {self.startup_timeout} s:\n{self.log()}")

    def _limit(self) -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (self.address_space, self.address_space))

    def memory(self) -> dict[str, int]:
        """The server process's peak and current resident and virtual memory, bytes (Linux)."""
        assert self.process is not None
        fields = {"VmHWM": "peak_rss", "VmRSS": "rss", "VmPeak": "peak_vm", "VmSize": "vm"}
        out = {}
        with open(f"/proc/{self.process.pid}/status") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in fields:
                    out[fields[key]] = int(value.split()[0]) * 1024
        return out

    def terminate(self, timeout: float = 60.0) -> int:
        """SIGTERM, then wait for the graceful shutdown; the exit status."""
        assert self.process is not None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout)

    def __exit__(self, *exc: Any) -> None:
        if self.process is not None and self.process.poll() is None:
            try:
                self.terminate(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def log(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")


#: the two image inputs of a request, by what the served model reads
IMAGE_INPUTS = {"blocks": ("blocks", "quick"), "halves": ("even", "odd")}


def make_request(blocks: int = 16, size: int = 128, binary: bool = False, seed: int = 0,
                 inputs: str = "blocks") -> tuple[bytes, dict[str, str]]:
    """(body, headers) of one infer request for `blocks` random blocks and their quick images
    (`inputs` 'blocks'), or their two half buffers (`inputs` 'halves')."""
    rng = np.random.default_rng(seed)
    current = rng.random((blocks, size, size, 3), dtype=np.float32)
    other = (0.5 * current + 0.25).astype(np.float32) if inputs == "blocks" else \
        np.clip(current + rng.normal(0, 0.02, current.shape), 0, None).astype(np.float32)
    named = tuple(zip(IMAGE_INPUTS[inputs], (current, other)))
    shape = list(current.shape)
    outputs = [{"name": n, "parameters": {"binary_data": binary}} for n in ("verdict", "score")]
    if not binary:
        tensors = [{"name": n, "shape": shape, "datatype": "FP32", "data": a.ravel().tolist()} for n, a in named]
        return json.dumps({"inputs": tensors, "outputs": outputs}).encode(), \
            {"Content-Type": "application/json"}
    tensors = [{"name": n, "shape": shape, "datatype": "FP32", "parameters": {"binary_data_size": a.nbytes}}
               for n, a in named]
    header = json.dumps({"inputs": tensors, "outputs": outputs}).encode()
    return header + current.tobytes() + other.tobytes(), \
        {"Content-Type": "application/octet-stream", HEADER_LENGTH: str(len(header))}


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
    from ..registry import bundle_name
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
