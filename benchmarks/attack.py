"""Attack scenarios against a running verdict server, bounded and on loopback only.

Each function drives one kind of abuse the attack found or the hardening must survive, and
returns what happened as plain numbers, so that tests assert on them and `noisestop bench
reliability` reports them (BENCHMARKS.md "Reliability under attack"):

* `idle_flood`: N connections that send nothing or half a request line, while health
  probes and one inference are timed; then how long the server takes to close them;
* `slow_headers`: one header byte at a time (slowloris), until the server hangs up;
* `stalled_body`: headers, then part of the body, then silence (expects 408);
* `over_the_limit`: `limit` requests held in flight, one more (expects 503) and a probe (200);
* `worst_shapes`: the largest and oddest requests the limits allow, and some they refuse.

Nothing here sends more than a few hundred megabytes or runs longer than a minute.
"""
from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from service.auth import is_loopback
from service.oip import HEADER_LENGTH

MAX_CONNECTIONS = 512


def _address(url: str) -> tuple[str, int]:
    parts = urlsplit(url)
    host = parts.hostname or ""
    if parts.scheme != "http" or not is_loopback(host):
        raise ValueError(f"{url}: attack scenarios run against a loopback http:// server only")
    return host, parts.port or 80


def _get(host: str, port: int, path: str, timeout: float = 10.0) -> tuple[int | str, float]:
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
    host, port = _address(url)
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


def _closed(sock: socket.socket, deadline: float) -> tuple[bool, bytes]:
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


def idle_flood(url: str, n: int = 64, probes: int = 10, wait: float = 30.0,
               infer: Callable[[], int | str] | None = None) -> dict[str, Any]:
    """n idle connections (half silent, half with a partial request line) held open while
    `probes` health checks (live and ready, alternating) and `infer` run; then the seconds
    until the server has closed every one (at most `wait`)."""
    host, port = _address(url)
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
        health = [_get(host, port, "/v2/health/live" if i % 2 == 0 else "/v2/health/ready")
                  for i in range(probes)]
        infer_status = infer() if infer is not None else None
        closed, statuses = 0, {}
        deadline = t_open + wait
        for s in socks:
            ok, got = _closed(s, deadline)
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
    host, port = _address(url)
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
        closed, rest = _closed(s, time.monotonic() + 5)
        got += rest
    finally:
        s.close()
    return {"bytes_sent": sent, "header_bytes": len(line), "cut_off": sent < len(line),
            "after_s": time.monotonic() - t0, "status": got.split(b" ", 2)[1].decode()
            if got.startswith(b"HTTP/1.1 ") else None}


def stalled_body(url: str, token: str | None, declared: int = 1000, sent: int = 10,
                 limit_s: float = 60.0) -> dict[str, Any]:
    """Headers announcing `declared` body bytes, `sent` of them, then silence."""
    host, port = _address(url)
    s = socket.create_connection((host, port), timeout=limit_s)
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    t0 = time.monotonic()
    try:
        s.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\n{auth}"
                   f"Content-Type: application/json\r\nContent-Length: {declared}\r\n\r\n").encode() + b"{" * sent)
        _, got = _closed(s, t0 + limit_s)
    finally:
        s.close()
    status = got.split(b" ", 2)[1].decode() if got.startswith(b"HTTP/1.1 ") else None
    return {"status": status, "after_s": time.monotonic() - t0}


def over_the_limit(url: str, token: str | None, limit: int) -> dict[str, Any]:
    """Hold `limit` requests in flight (stalled bodies), then send one more and probe health."""
    host, port = _address(url)
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
        health = _get(host, port, "/v2/health/ready")
        return {"held": limit, "extra_status": resp.status, "retry_after": retry_after, "attempts": attempts,
                "error": json.loads(body).get("error") if body.startswith(b"{") else None,
                "health_status": health[0]}
    finally:
        for s in held:
            s.close()


# --- the worst shapes ---------------------------------------------------------------------------

def binary_request(shape: tuple[int, ...], names: tuple[str, ...] = ("blocks", "quick"),
                   seed: int = 0) -> tuple[bytes, dict[str, str]]:
    """Body and headers of a binary-tensor request of FP32 `shape` per input (random values)."""
    n = int(np.prod(shape))
    head = json.dumps({"inputs": [{"name": nm, "shape": list(shape), "datatype": "FP32",
                                   "parameters": {"binary_data_size": 4 * n}} for nm in names]}).encode()
    data = np.random.default_rng(seed).random(n, dtype=np.float32).tobytes()
    return head + data * len(names), {HEADER_LENGTH: str(len(head)), "Content-Type": "application/octet-stream"}


def nested_json_request(shape: tuple[int, int, int, int], value: bytes = b"0") -> tuple[bytes, dict[str, str]]:
    """The costliest JSON to parse per byte: nested lists of one-character numbers."""
    n, h, w, c = shape
    pixel = b"[" + b",".join([value] * c) + b"]"
    row = b"[" + b",".join([pixel] * w) + b"]"
    image = b"[" + b",".join([row] * h) + b"]"
    data = b"[" + b",".join([image] * n) + b"]"
    inputs = b",".join(b'{"name":"%s","shape":%s,"datatype":"FP32","data":%s}'
                       % (nm, json.dumps(list(shape)).encode(), data) for nm in (b"blocks", b"quick"))
    return b'{"inputs":[' + inputs + b"]}", {"Content-Type": "application/json"}


def worst_shapes(max_body: int) -> dict[str, Callable[[], tuple[bytes, dict[str, str]]]]:
    """Named requests at and beyond the default limits (64 MiB body, 2048 px side, 4 Mi px)."""
    side_px = lambda n: int((max_body - 4096) // (2 * 12 * n))     # noqa: E731 pixels a body holds
    wide = side_px(1) // 2048
    return {
        "issue shape [1, 8, 40000, 3]": lambda: binary_request((1, 8, 40000, 3)),
        f"widest block [1, {wide}, 2048, 3]": lambda: binary_request((1, wide, 2048, 3)),
        "thin blocks [160, 8, 2048, 3]": lambda: binary_request((160, 8, 2048, 3)),
        "many small blocks [1024, 40, 40, 3]": lambda: binary_request((1024, 40, 40, 3)),
        "odd sizes [2, 999, 1001, 3]": lambda: binary_request((2, 999, 1001, 3)),
        "pixel budget exceeded [2, 2048, 1100, 3] (one input)": lambda: binary_request((2, 2048, 1100, 3), ("blocks",)),
        "nested JSON of one-digit numbers, ~body limit": lambda: nested_json_request(
            (2, 1024, max(8, int(max_body * 0.98 / (2 * 2 * 1024 * 8))), 3)),
        "body over the limit (declared)": lambda: (b"", {"Content-Length": str(max_body + 1),
                                                         "Content-Type": "application/octet-stream"}),
    }


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


# --- slow uploaders, protocol errors, duplicate keys -------------------------------------------

def _status_of(raw: bytes) -> int | None:
    return int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/1.1 ") and raw[9:12].isdigit() else None


def slow_upload(url: str, token: str | None, stop: threading.Event, declared: int | None = 64 << 20,
                interval: float = 1.0, limit_s: float = 600.0,
                out: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """One client trickling a body, one byte every `interval` seconds (chunked when
    `declared` is None, else under that Content-Length), reconnecting whenever the server
    hangs up, until `stop` is set. Each connection: its answer and how long it was held
    (appended to `out` as each ends, if given)."""
    host, port = _address(url)
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
                    got += _closed(s, time.monotonic() + 5)[1]
                    break
        except OSError:
            pass
        finally:
            s.close()
        out.append({"status": _status_of(got), "held_s": time.monotonic() - t0,
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


def protocol_error(url: str) -> dict[str, Any]:
    """A request h11 cannot parse: the status, content type and {"error"} body of the answer."""
    host, port = _address(url)
    s = socket.create_connection((host, port), timeout=10)
    try:
        s.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nBad Header Line\r\n\r\n")
        _, got = _closed(s, time.monotonic() + 10)
    finally:
        s.close()
    head, _, body = got.partition(b"\r\n\r\n")
    ctype = next((line.split(b":", 1)[1].strip().decode() for line in head.split(b"\r\n")
                  if line.lower().startswith(b"content-type:")), None)
    try:
        error = json.loads(body).get("error")
    except ValueError:
        error = None
    return {"status": _status_of(got), "content_type": ctype, "error": error}


def duplicate_keys(url: str, token: str | None) -> dict[str, Any]:
    """`exposure` twice in one parameters object (1e30, then 0): 400, never served at 0."""
    from tests.support.demo import make_request
    body, headers = make_request(blocks=1, size=16)
    body = body[:-1] + b', "parameters": {"exposure": 1e30, "exposure": 0}}'
    status, answer = post(url, body, headers, token)
    return {"status": status, "error": json.loads(answer).get("error") if answer.startswith(b"{") else None}


def nested_over_budget(url: str, token: str | None, megabytes: int = 62) -> dict[str, Any]:
    """The issue's request: ~62 MiB of JSON, every value inside 20 nested lists (56x its
    size in memory once parsed). Answered how, and how fast."""
    body, headers = nested_json_request_62(megabytes)
    t0 = time.perf_counter()
    status, answer = post(url, body, headers, token)
    return {"bytes": len(body), "status": status, "seconds": time.perf_counter() - t0,
            "error": json.loads(answer).get("error") if answer.startswith(b"{") else None}


def nested_json_request_62(megabytes: int = 62) -> tuple[bytes, dict[str, str]]:
    """Body and headers of `nested_over_budget`'s request."""
    unit = b"[" * 20 + b"1" + b"]" * 20
    n = (megabytes << 20) // (len(unit) + 1)
    data = b"[" + b",".join([unit] * n) + b"]"
    return (b'{"inputs":[{"name":"features","shape":[%d,1,1,1,1,1,1,1],"datatype":"FP32","data":' % n + data + b"}]}",
            {"Content-Type": "application/json"})


# --- issue 34: burst-then-stall uploaders, the costliest valid JSON in a loop -------------------

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
    out.update(status=_status_of(got) or got.decode(errors="replace")[:40] or None, held_s=time.monotonic() - t0)


def burst_then_stall(url: str, token: str | None, stallers: int = 16, megabytes: int = 63,
                     hold_s: float = 20.0, after_s: float = 10.0,
                     make: Callable[[], tuple[bytes, dict[str, str]]] | None = None) -> dict[str, Any]:
    """`stallers` clients each declare a body of `megabytes` + 1 MiB, send `megabytes` fast,
    then stall; normal requests run one after another the whole time. After `hold_s` the
    stallers hang up; normal requests go on for `after_s`. Statuses of the normal requests
    while the stallers held on, and how long after they hung up the first 200 came."""
    from .loadtest import make_request
    host, port = _address(url)
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


def costliest_valid_json(budget_fraction: float = 0.9, budget: int | None = None) -> tuple[bytes, dict[str, str]]:
    """The JSON body that costs the most CPU to parse per byte among those a default server
    admits: a rank-8 `features` tensor whose every value sits in 7 nested lists (the most
    nesting its shape allows), sized to `budget_fraction` of the memory budget's estimate."""
    from service.limits import DEFAULT_MEMORY_BUDGET, json_cost
    unit = b"[" * 7 + b"1" + b"]" * 7
    per = json_cost(unit + b",") + len(unit) + 1
    n = int(budget_fraction * (budget or DEFAULT_MEMORY_BUDGET) / per)
    data = b"[" + b",".join([unit] * n) + b"]"
    return (b'{"inputs":[{"name":"features","shape":[%d,1,1,1,1,1,1,1],"datatype":"FP32","data":' % n
            + data + b"}]}", {"Content-Type": "application/json"})


def nested_json_255k(depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """Issue 42's body: 255 kB of `[[[[[[[0]]]]]]]` (11 deep with the envelope, the most a
    request may nest), a rank-8 `features` tensor: parsed in full, then refused (400)."""
    unit = b"[" * depth + b"0" + b"]" * depth
    n = (255_000 - 100) // (len(unit) + 1)
    return (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (n, b",1" * depth)
            + b",".join([unit] * n) + b"]}]}", {"Content-Type": "application/json"})


def nested_json(size: int, depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """Issue 42's nested body at about `size` bytes (issue 51: 16.3 kB, just under the
    parse pool's threshold, was parsed on the server's own thread)."""
    unit = b"[" * depth + b"0" + b"]" * depth
    n = (size - 100) // (len(unit) + 1)
    return (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (n, b",1" * depth)
            + b",".join([unit] * n) + b"]}]}", {"Content-Type": "application/json"})


def bound_json(size: int, units: int = 35, depth: int = 7) -> tuple[bytes, dict[str, str]]:
    """The costliest body still parsed on the server's own thread (issue 51): `units`
    values nested `depth` deep (253 lists and objects with the envelope, under
    `parsepool.INLINE_CONTAINERS`), padded with a flat list of zeros to about `size` bytes."""
    unit = b"[" * depth + b"0" + b"]" * depth
    head = (b'{"inputs":[{"name":"features","shape":[%d%s],"datatype":"FP32","data":[' % (units, b",1" * depth)
            + b",".join([unit] * units) + b']},{"name":"pad","shape":[%d],"datatype":"FP32","data":[')
    n = max(1, (size - len(head) - 20) // 2)
    return head % n + b",".join([b"0"] * n) + b"]}]}", {"Content-Type": "application/json"}


def valid_halves_json(size: int) -> tuple[bytes, dict[str, str]]:
    """The largest valid halves request (`even` and `odd`, [k, 8, 8, 3] of 0.5, for the
    bundled model) of at most `size` bytes: issue 51's valid 16 kB body."""
    def body(k: int) -> bytes:
        values = b"[" + b",".join([b"0.5"] * (k * 8 * 8 * 3)) + b"]"
        return (b'{"inputs":[{"name":"even","shape":[%d,8,8,3],"datatype":"FP32","data":' % k + values +
                b'},{"name":"odd","shape":[%d,8,8,3],"datatype":"FP32","data":' % k + values + b"}]}")
    k = 1
    while len(body(k + 1)) <= size:
        k += 1
    return body(k), {"Content-Type": "application/json"}


def valid_json_255k() -> tuple[bytes, dict[str, str]]:
    """Issue 42's other body: a fully valid JSON request (184 kB), 8x8 blocks as the demo
    model takes them (120 blocks and their 120 quick images: 240 of [8, 8, 3])."""
    values = b"[" + b",".join([b"0.5"] * (120 * 8 * 8 * 3)) + b"]"
    return (b'{"inputs":[{"name":"blocks","shape":[120,8,8,3],"datatype":"FP32","data":' + values +
            b'},{"name":"quick","shape":[120,8,8,3],"datatype":"FP32","data":' + values + b"}]}",
            {"Content-Type": "application/json"})


def costly_json_loop(url: str, token: str | None, seconds: float = 20.0, requests: int = 200,
                     make: Callable[[], tuple[bytes, dict[str, str]]] | None = None,
                     attack: Callable[[], tuple[bytes, dict[str, str]]] = costliest_valid_json,
                     attackers: int = 1) -> dict[str, Any]:
    """Normal requests (and health probes every 50 ms) timed alone, then while `attackers`
    clients post `attack()`'s body (default `costliest_valid_json`) in a loop for up to
    `seconds`: p50/p99 of each, the attackers' answers and the slowest probe."""
    from .loadtest import make_request
    host, port = _address(url)
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
            out.append(_get(host, port, "/v2/health/ready", timeout=10)[1])
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
