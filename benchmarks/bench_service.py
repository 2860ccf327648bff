"""`noisestop bench service`: the verdict service under load, and where a request's time goes.

Two models: the bundled one (its input is `halves` composition `f`: FLIP between the half
buffers) and a model on the paper's feature input (features(quick) - features(current);
`loadtest.make_demo_bundle`, a DSVM fitted in a second on synthetic blocks: real inputs and
costs, meaningless verdicts). For each:

* stages of one request of 16 blocks of 128x128, in process, warm, medians: decoding the
  binary body, features (the fused pass; for `f`, only the flat test and non-finite counts),
  FLIP, the SVM, encoding the answer;
* a bounded load test on loopback (benchmarks/loadtest.py) with binary tensors at 1, 8 and 32
  clients and JSON at 1, with the server process's CPU per request split between its event
  loop (HTTP: reading 6.3 MB bodies) and its inference threads (Linux /proc);
* how long the server took to answer /ready, and how busy the machine was meanwhile.
"""
from __future__ import annotations

import collections
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from noisefeat.runtime import median_s, torch_threads

from .timing import MachineLoad

BLOCKS, SIZE = 16, 128
CLIENTS = (1, 8, 32)


def _median_ms(fn: Callable[[], Any], repeats: int) -> float:
    return median_s(fn, repeats) * 1e3


def stage_times(model: str | None, repeats: int = 9) -> dict[str, Any]:
    """Milliseconds of each stage of one binary request of BLOCKS blocks of SIZE x SIZE,
    on one torch thread as in the server (serve --torch-threads)."""
    with torch_threads(1), MachineLoad() as load:
        out = _stage_times(model, repeats)
    out["other_load"] = load.share
    return out


def _stage_times(model: str | None, repeats: int) -> dict[str, Any]:
    from learning.inputs.halves import halves_flip
    from noisefeat import fused
    from noisefeat.extract import analyse_many
    from service.infer import infer_sync
    from service.limits import Limits
    from tests.support.demo import make_request
    from service.metrics import ServiceMetrics
    from service.oip import InferenceResponse, ResponseOutput, decode_tensors, encode_response, parse_request, split_body
    from service.registry import OUTPUTS, ModelRegistry

    registry = ModelRegistry({"m": model})
    registry.load()
    served = registry.get("m")
    halves = served.model.needs_halves
    body, headers = make_request(BLOCKS, SIZE, binary=True, inputs="halves" if halves else "blocks")
    length = int(headers["Inference-Header-Content-Length"])
    limits = Limits()

    def decode() -> dict[str, np.ndarray]:
        head, tail = split_body(memoryview(bytearray(body)), length)
        return decode_tensors(parse_request(bytes(head)), tail, limits.max_batch, scan_bools=False)
    tensors = decode()
    out: dict[str, Any] = {"decode_ms": _median_ms(decode, repeats),
                           "support_vectors": int(served.model.estimator.n_support_)}
    import torch
    with torch.inference_mode():
        if halves:
            even, odd = (torch.as_tensor(tensors[k]) for k in ("even", "odd"))
            out["features_ms"] = _median_ms(lambda: fused.halves_stats(even, odd, 0.0), repeats)
            out["features_what"] = "flat test and non-finite counts only (composition f reads no features)"
            out["flip_ms"] = _median_ms(lambda: halves_flip(tensors["even"], tensors["odd"]), max(3, repeats // 2))
            x = served.model.inputs_from_halves(tensors["even"][:1], tensors["odd"][:1])
            x = np.repeat(x, BLOCKS, axis=0)
        else:
            images = [tensors["blocks"], tensors["quick"]]
            out["features_ms"] = _median_ms(lambda: analyse_many(images, display_range=[True, False]), repeats)
            out["features_what"] = f"{2 * BLOCKS} images (blocks and quick) in one fused call"
            out["flip_ms"] = 0.0
            x = served.model.inputs_from_blocks(tensors["blocks"], tensors["quick"])
    out["svm_ms"] = _median_ms(lambda: served.model.decision_function(x), repeats)
    arrays, params = served.infer(tensors)

    def encode() -> tuple[bytes, int | None]:
        resp = InferenceResponse(model_name="m", outputs=[ResponseOutput(name=n, shape=[BLOCKS], datatype=OUTPUTS[n])
                                                          for n in OUTPUTS])
        return encode_response(resp, arrays, set(OUTPUTS))
    out["encode_ms"] = _median_ms(encode, repeats)
    metrics = ServiceMetrics()
    out["in_process_ms"] = _median_ms(lambda: infer_sync(served, [bytearray(body)], length, limits, metrics),
                                      max(3, repeats // 2) if halves else repeats)
    out["request_mb"] = len(body) / 1e6
    return out


def _thread_cpu(pid: int) -> dict[str, tuple[str, float]] | None:
    """CPU seconds of each thread of a process (Linux), by thread id."""
    hz = os.sysconf("SC_CLK_TCK")
    out = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[tid] = ("event loop" if tid == str(pid) else "inference", (int(fields[11]) + int(fields[12])) / hz)
    return out


def load_runs(model: str | None, clients: tuple[int, ...] = CLIENTS) -> dict[str, Any]:
    """Binary load at each client count and JSON at 1 client, against one server."""
    from tests.support.local_server import LocalServer
    from .loadtest import run_load

    t0 = time.perf_counter()
    with LocalServer({"bench": model}) as server:
        ready_s = time.perf_counter() - t0
        runs = []
        run_load(server.url, token=server.token, binary=True, clients=2, requests_per_client=1,
                 blocks=BLOCKS, size=SIZE)                                    # warm
        for binary, c in [(True, c) for c in clients] + [(False, 1)]:
            before = _thread_cpu(server.process.pid)
            with MachineLoad(mine=(server.process.pid,)) as load:
                r = run_load(server.url, token=server.token, binary=binary, clients=c,
                             requests_per_client=max(2, (64 if binary else 16) // c), blocks=BLOCKS, size=SIZE,
                             max_seconds=90)
            after = _thread_cpu(server.process.pid)
            cpu = collections.Counter()
            if before is not None and after is not None and r["requests"]:
                for tid, (kind, sec) in after.items():
                    cpu[kind] += sec - before.get(tid, (kind, 0.0))[1]
            r["server_cpu_ms"] = {k: 1e3 * v / r["requests"] for k, v in cpu.items()} if cpu else None
            r["other_load"] = load.share
            runs.append(r)
    return {"ready_s": ready_s, "runs": runs}


def bench_service(clients: tuple[int, ...] = CLIENTS, repeats: int = 3) -> dict[str, Any]:
    """Both models, `repeats` rounds each (the models alternate, a fresh server per round);
    every cell of the tables is the median over the rounds."""
    from tests.support.demo import make_demo_bundle
    from service.registry import bundle_name

    out: dict[str, Any] = {"cpus": os.cpu_count(), "blocks": BLOCKS, "size": SIZE, "repeats": repeats,
                           "models": {}}
    with tempfile.TemporaryDirectory() as tmp:
        models: dict[str, str | None] = {}
        try:
            bundle_name(None)
            models["bundled (input halves, composition f: FLIP)"] = None
        except FileNotFoundError:
            pass
        models["paper's feature input (quick albedo; demo DSVM)"] = str(make_demo_bundle(Path(tmp) / "demo"))
        rounds: dict[str, list[dict[str, Any]]] = {label: [] for label in models}
        for _ in range(repeats):
            for label, path in models.items():
                rounds[label].append(load_runs(path, clients))
        for label, path in models.items():
            out["models"][label] = {"stages": stage_times(path), **_merge(rounds[label])}
    return out


def _merge(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians over rounds, cell by cell (errors summed; every round's p99 kept)."""
    def med(values: list[float | None]) -> float | None:
        values = [v for v in values if v is not None]
        return statistics.median(values) if values else None
    runs = []
    for cells in zip(*(r["runs"] for r in rounds)):
        first = cells[0]
        cpu_kinds = {k for c in cells for k in (c.get("server_cpu_ms") or {})}
        runs.append({**first, "requests": sum(c["requests"] for c in cells), "errors": sum(c["errors"] for c in cells),
                     **{k: med([c[k] for c in cells]) for k in ("p50_ms", "p99_ms", "requests_per_s", "other_load")},
                     "p99_rounds": [c["p99_ms"] for c in cells],
                     "server_cpu_ms": {k: med([(c.get("server_cpu_ms") or {}).get(k) for c in cells])
                                       for k in cpu_kinds} or None})
    return {"ready_s": med([r["ready_s"] for r in rounds]), "runs": runs}


def md_service(r: dict[str, Any]) -> str:
    def f(v: float | None, digits: int = 0) -> str:
        return "-" if v is None else f"{v:.{digits}f}"
    lines = [f"{r['blocks']} blocks of {r['size']}x{r['size']} per request, loopback, {r['cpus']} CPUs shared by "
             f"client and server; medians of {r.get('repeats', 1)} rounds (a fresh server each). Closed loop: "
             "each client waits for its answer; no errors at 32 clients is the goal here, capacity and "
             "latency at a given traffic are in the capacity table above.", ""]
    for label, m in r["models"].items():
        st = m["stages"]
        lines += [f"**{label}**: server ready in {m['ready_s']:.1f} s; {st['support_vectors']} support vectors.", "",
                  "| clients | encoding | requests | req/s | p50 (ms) | p99 (ms) (each round) | errors "
                  "| server CPU per request: event loop / inference (ms) | other processes' load |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for x in m["runs"]:
            cpu = x.get("server_cpu_ms") or {}
            share = x.get("other_load")
            each = ", ".join(f(v) for v in x.get("p99_rounds", []))
            lines.append(f"| {x['clients']} | {x['encoding']} | {x['requests']} | {x['requests_per_s']:.1f} "
                         f"| {f(x['p50_ms'])} | {f(x['p99_ms'])} ({each}) | {x['errors']} "
                         f"| {f(cpu.get('event loop'), 1)} / {f(cpu.get('inference'), 1)} "
                         f"| {'-' if share is None else f'{100 * share:.0f} %'} |")
        lines += ["", f"One request in process (binary, {st['request_mb']:.1f} MB, warm, medians): "
                  f"decode {st['decode_ms']:.2f} ms, features {st['features_ms']:.1f} ms ({st['features_what']}), "
                  f"FLIP {st['flip_ms']:.1f} ms, SVM {st['svm_ms']:.2f} ms, encode {st['encode_ms']:.2f} ms; "
                  f"all of it {st['in_process_ms']:.1f} ms (one torch thread, as served"
                  + ("" if st.get("other_load") is None else f"; other processes' load {100 * st['other_load']:.0f} %")
                  + ").", ""]
    return "\n".join(lines).rstrip()
