"""`noisestop bench hardening`: the hardening figures of BENCHMARKS.md ("Reliability"; the
tables in docs/benchmarks/reliability.md), also part of `bench reliability`.

Here, the server's own cases: peak RSS of the worst JSON and binary shapes with and
without the address-space cap, normal latency beside slow uploaders, every way of starting
`serve` without a token, SIGHUP with a request in flight, a protocol error, a key twice.
Then the cases of the other harnesses: hostile request bodies (`hardening_bodies`), hostile
files (`hardening_files`), non-finite scenes (`hardening_nonfinite`), what a scene XML makes
Mitsuba open (`hardening_scene_walk`), the loop's state (`hardening_loop_state`) and the
doors that check first (`hardening_doors`).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .cli_run import ROOT
from .hardening_bodies import (bench_burst_then_stall, bench_costly_json, bench_inline_json, bench_large_bodies,
                               md_burst_then_stall, md_costly_json, md_inline_json)
from .hardening_doors import bench_doors, md_doors
from .hardening_files import bench_scene_files, hostile_files, input_slot_files, md_hostile_files, md_scene_files
from .hardening_loop_state import bench_loop_state, md_loop_state
from .hardening_nonfinite import bench_nonfinite_scenes, md_nonfinite
from .hardening_scene_walk import bench_scene_walk, md_scene_walk

#: the address-space cap (RLIMIT_AS) the attacked server runs under
ADDRESS_SPACE = 3 << 30


def mib(n: int) -> str:
    """Bytes as the tables print them: whole MiB."""
    return f"{n / (1 << 20):,.0f} MiB"


#: the variables and flags `serve` is started with, to find any path that serves without a
#: token that nobody asked for (`NOISESTOP_TOKEN=`, empty, once did)
AUTH_CASES: tuple[tuple[str, dict[str, str], tuple[str, ...]], ...] = (
    ("NOISESTOP_TOKEN= (empty)", {"NOISESTOP_TOKEN": ""}, ()),
    ("NOISESTOP_TOKEN of spaces", {"NOISESTOP_TOKEN": "   "}, ()),
    ("NOISESTOP_TOKEN_FILE= (empty)", {"NOISESTOP_TOKEN_FILE": ""}, ()),
    ("NOISESTOP_TOKEN_FILE= with --no-auth", {"NOISESTOP_TOKEN_FILE": ""}, ("--no-auth",)),
    ("no token, no flag", {}, ()),
    ("no token, --no-auth on 0.0.0.0", {}, ("--no-auth", "--host", "0.0.0.0")),
    ("token and --no-auth", {"NOISESTOP_TOKEN": "a" * 24}, ("--no-auth",)),
    ("no token, --no-auth on loopback (explicit)", {}, ("--no-auth",)),
)


def bench_hardening() -> dict[str, Any]:
    """The hardening figures: peak RSS of the worst JSON and binary shapes with and without
    the 3 GiB address-space cap (a fresh server per shape, so that each peak is its own),
    the p99 of normal requests beside 0, 1, 4 and 16 slow uploaders, the auth paths of
    `serve`, SIGHUP, protocol errors and duplicate keys."""
    from tests.support.demo import make_demo_bundle

    with tempfile.TemporaryDirectory() as tmp:
        bundle = str(make_demo_bundle(Path(tmp) / "demo", name="demo"))
        return {"shapes": _shape_peaks(bundle), "slow": _slow_uploaders(bundle),
                "auth": _auth_paths(bundle), "sighup": _sighup(bundle), "protocol": _protocol(bundle),
                "costly_json": bench_costly_json(bundle), "burst_then_stall": bench_burst_then_stall(bundle),
                "hostile_files": hostile_files(bundle), "large_bodies": bench_large_bodies(bundle),
                "input_slots": input_slot_files(bundle), "scene_files": bench_scene_files(),
                "nonfinite": bench_nonfinite_scenes(), "inline_json": bench_inline_json(bundle),
                "scene_walk": bench_scene_walk(), "loop_state": bench_loop_state(), "doors": bench_doors()}


def _hardening_shapes() -> dict[str, Any]:
    """Named (body, headers) makers: the worst JSON shapes per byte, admitted or refused,
    and the largest binary ones."""
    from . import attack
    from service.limits import DEFAULT_MAX_BODY, DEFAULT_MEMORY_BUDGET
    from service.memory_cost import json_cost
    unit = b"[" * 20 + b"1.5" + b"]" * 20

    def nested_values(fraction_of_budget: float) -> tuple[bytes, dict[str, str]]:
        n = int(fraction_of_budget * DEFAULT_MEMORY_BUDGET / (json_cost(unit + b",") + len(unit) + 1))
        body = b'{"inputs":[{"name":"features","shape":[1,%d],"datatype":"FP32","data":[' % n \
            + b",".join([unit] * n) + b"]}]}"
        return body, {"Content-Type": "application/json"}

    def image(value: bytes, size: int, nested: bool) -> tuple[bytes, dict[str, str]]:
        per_pixel = 3 * (len(value) + 1) + (2 if nested else 0)
        w = max(8, int(0.98 * size) // (2 * 2 * 1024 * per_pixel))      # envelope: under the body limit
        if nested:
            return attack.nested_json_request((2, 1024, w, 3), value)
        data = b"[" + b",".join([value] * (2 * 1024 * w * 3)) + b"]"
        inputs = b",".join(b'{"name":"%s","shape":[2,1024,%d,3],"datatype":"FP32","data":%s}' % (nm, w, data)
                           for nm in (b"blocks", b"quick"))
        return b'{"inputs":[' + inputs + b"]}", {"Content-Type": "application/json"}

    def spaces(size: int) -> tuple[bytes, dict[str, str]]:
        data = (b"," + b" " * (size // 26)).join([b"0.5"] * 26)
        return (b'{"inputs":[{"name":"features","shape":[1,26],"datatype":"FP32","data":[' + data + b"]}]}",
                {"Content-Type": "application/json"})

    wide = int((DEFAULT_MAX_BODY - 4096) // (2 * 12)) // 2048
    return {
        "JSON: 62 MiB, 20 lists around every value": attack.nested_json_request_62,
        "JSON: 20 lists around every value, estimate 90% of the budget (parsed; 400: not 26 features)":
            lambda: nested_values(0.9),
        "JSON image [2, 1024, W, 3] x 2, one-digit numbers nested per pixel, 64 MiB":
            lambda: image(b"0", 64 << 20, nested=True),
        "JSON image, 3-digit integers, flat, 48 MiB": lambda: image(b"257", 48 << 20, nested=False),
        "JSON image, 9-digit floats nested per pixel, 60 MiB": lambda: image(b"0.1234567", 60 << 20, nested=True),
        "JSON: 26 features and 60 MiB of whitespace": lambda: spaces(60 << 20),
        f"binary: widest block [1, {wide}, 2048, 3] x 2 inputs, ~64 MiB": lambda: attack.binary_request((1, wide, 2048, 3)),
        "binary: many small blocks [1024, 40, 40, 3] x 2": lambda: attack.binary_request((1024, 40, 40, 3)),
    }


def _shape_peaks(bundle: str) -> list[dict[str, Any]]:
    from . import attack
    from tests.support.local_server import LocalServer
    rows = []
    for name, make in _hardening_shapes().items():
        for cap in (ADDRESS_SPACE, None):
            with LocalServer({"demo": bundle}, address_space=cap) as s:
                idle = s.memory()["peak_rss"]
                body, headers = make()
                t0 = time.perf_counter()
                status, answer = attack.post(s.url, body, headers, s.token)
                seconds = time.perf_counter() - t0
                del body
                health = attack._get("127.0.0.1", s.port, "/v2/health/ready")[0]
                mem = s.memory()
                alive = s.process.poll() is None
                log_text = s.log()
            rows.append({"request": name, "cap": cap, "status": status, "seconds": seconds, "idle_peak_rss": idle,
                         "peak_rss": mem["peak_rss"], "health_after": health, "alive": alive,
                         "tracebacks": log_text.count("Traceback"),
                         "error": json.loads(answer).get("error") if answer.startswith(b'{"error') else None})
    return rows


def _slow_uploaders(bundle: str, counts: tuple[int, ...] = (0, 1, 4, 16), requests: int = 600) -> list[dict[str, Any]]:
    """600 normal requests (~12 s here) per row: longer than the 10 s grace, so the slow
    uploaders are cut off (408) and reconnect while they are measured."""
    from . import attack
    from tests.support.local_server import LocalServer
    from tests.support.demo import make_request
    rows = []
    with LocalServer({"demo": bundle}) as s:
        attack.post(s.url, *make_request(blocks=16, size=128, binary=True), s.token)      # warm
        for n in counts:
            r = attack.normal_latency_under_slow_uploads(
                s.url, s.token, n, requests=requests, make=lambda: make_request(blocks=16, size=128, binary=True))
            rows.append(r)
        rows.append({"alive": s.process.poll() is None, "tracebacks": s.log().count("Traceback")})
    return rows


def _auth_paths(bundle: str) -> list[dict[str, Any]]:
    from tests.support.local_server import free_port
    rows = []
    for name, env, argv in AUTH_CASES:
        port = free_port()
        environ = {k: v for k, v in os.environ.items() if k not in ("NOISESTOP_TOKEN", "NOISESTOP_TOKEN_FILE")}
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "-q", "serve", "--model", bundle,
                                 "--port", str(port), *argv], env={**environ, **env, "PYTHONPATH": str(ROOT)},
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
        served = _answers(port, proc, 60)
        if proc.poll() is None:
            proc.terminate()
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        lines = [line for line in err.splitlines() if line.strip()]
        rows.append({"case": name, "served": served, "exit": proc.returncode, "lines": len(lines),
                     "message": lines[-1][:160] if lines else "", "explicit": "--no-auth" in argv,
                     "tracebacks": err.count("Traceback")})
    return rows


def _answers(port: int, proc: subprocess.Popen, timeout: float) -> bool:
    import urllib.error
    import urllib.request
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/v2/health/live", timeout=1):
                return True
        except (urllib.error.URLError, OSError):
            time.sleep(0.2)
    return False


def _sighup(bundle: str) -> dict[str, Any]:
    import signal
    import socket
    from . import attack
    from tests.support.local_server import LocalServer
    from tests.support.demo import make_request
    with LocalServer({"demo": bundle}) as s:
        body, headers = make_request(blocks=2, size=32, binary=True)
        sock = socket.create_connection(("127.0.0.1", s.port), timeout=30)
        sock.sendall((f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {s.token}\r\n"
                      + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
                      + f"Content-Length: {len(body)}\r\n\r\n").encode() + body[:100])
        time.sleep(0.5)
        t0 = time.monotonic()
        s.process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        alive_after_signal = s.process.poll() is None
        sock.sendall(body[100:])
        answer = attack._closed(sock, time.monotonic() + 30)[1]
        sock.close()
        code = s.process.wait(60)
        log_text = s.log()
    return {"in_flight_status": int(answer[9:12]) if answer.startswith(b"HTTP/1.1 ") else None,
            "alive_after_signal": alive_after_signal, "exit_after_s": time.monotonic() - t0, "exit": code,
            "logged": "SIGHUP: draining" in log_text, "tracebacks": log_text.count("Traceback")}


def _protocol(bundle: str) -> dict[str, Any]:
    from . import attack
    from tests.support.local_server import LocalServer
    with LocalServer({"demo": bundle}) as s:
        return {"protocol_error": attack.protocol_error(s.url), "duplicate_keys": attack.duplicate_keys(s.url, s.token),
                "openapi_without_token": attack._get("127.0.0.1", s.port, "/openapi.json")[0],
                "metadata_without_token": attack._get("127.0.0.1", s.port, "/v2/models/default")[0]}


def md_hardening(r: dict[str, Any]) -> str:
    lines = ["| request | cap | answer | seconds | server peak RSS (idle peak) | after it |", "|---|---|---|---|---|---|"]
    for w in r["shapes"]:
        lines.append(f"| {w['request']} | {'3 GiB' if w['cap'] else 'none'} | {w['status']} | {w['seconds']:.1f} | "
                     f"{mib(w['peak_rss'])} ({mib(w['idle_peak_rss'])}) | health {w['health_after']}, "
                     f"{'alive' if w['alive'] else 'EXITED'}, {w['tracebacks']} tracebacks |")
    slow = [x for x in r["slow"] if "slow_clients" in x]
    base = slow[0]["p99_ms"] if slow and slow[0]["slow_clients"] == 0 else None
    lines += ["", "| slow uploaders connected | normal requests (16 blocks 128x128, binary) | p50 ms | p99 ms | "
                  "p99 / p99 with none | slow connections: answers, longest held |", "|---|---|---|---|---|---|"]
    for x in slow:
        ratio = f"{x['p99_ms'] / base:.2f}" if base else "-"
        lines.append(f"| {x['slow_clients']} | {x['ok']}/{x['requests']} answered 200 | {x['p50_ms']:.0f} | "
                     f"{x['p99_ms']:.0f} | {ratio} | {x['slow_connections']}: "
                     f"{', '.join(x['slow_statuses']).replace('None', 'still uploading at the end') or '-'}, "
                     f"{x['slow_held_max_s']:.1f} s |")
    lines += ["", "| serve started with | served? | exit | stderr lines | message |", "|---|---|---|---|---|"]
    for a in r["auth"]:
        lines.append(f"| {a['case']} | {'yes' if a['served'] else 'no'} | {a['exit']} | {a['lines']} | "
                     f"{a['message'].replace('|', '/')} |")
    silent = sum(a["served"] and not a["explicit"] for a in r["auth"])
    h, p = r["sighup"], r["protocol"]
    tracebacks = sum(w["tracebacks"] for w in r["shapes"]) + sum(a["tracebacks"] for a in r["auth"]) \
        + h["tracebacks"] + sum(x.get("tracebacks", 0) for x in r["slow"])
    hangs = sum(not w["alive"] or w["health_after"] != 200 for w in r["shapes"])
    lines += ["", f"SIGHUP with a request in flight: the request answered {h['in_flight_status']}, the server "
                  f"{'still up' if h['alive_after_signal'] else 'gone'} 0.5 s after the signal, exited "
                  f"{h['exit_after_s']:.1f} s after it (status {h['exit']}), log line: {'yes' if h['logged'] else 'NO'}. "
                  f"A protocol error (bad header line): HTTP {p['protocol_error']['status']}, "
                  f"{p['protocol_error']['content_type']}, error {p['protocol_error']['error']!r}. `exposure` twice: "
                  f"HTTP {p['duplicate_keys']['status']}. /openapi.json without a token: {p['openapi_without_token']} "
                  f"(model metadata without one: {p['metadata_without_token']}).",
              "", f"Hangs (a server not answering health after a shape): {hangs}; tracebacks in any server or "
                  f"command output: {tracebacks}; silent auth-off paths (served without a token and without "
                  f"--no-auth): {silent}."]
    if "costly_json" in r:
        lines += ["", md_costly_json(r["costly_json"]), md_burst_then_stall(r["burst_then_stall"]),
                  "", md_hostile_files(r["hostile_files"])]
    for key, md in (("scene_files", md_scene_files), ("nonfinite", md_nonfinite), ("inline_json", md_inline_json),
                    ("scene_walk", md_scene_walk), ("loop_state", md_loop_state), ("doors", md_doors)):
        if key in r:
            lines += ["", md(r[key])]
    return "\n".join(lines)
