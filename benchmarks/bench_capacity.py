"""`noisestop bench capacity`: how many blocks a core decides per second, and the latency a
farm gets at a share of that.

* **Per core, in process**: one torch thread deciding requests of 16 blocks, the bundled
  model (`ServedModel.infer` on the two half buffers: FLIP between them, then the SVM) and
  the `flip` criterion (`FlipCriterion.decide`, what the render loop runs when it decides
  locally); blocks of 64x64 (the default block) and 128x128.
* **Served**: `noisestop serve` with the bundled model on loopback. Its capacity is the
  throughput of a saturating closed loop (8 clients, binary); then open-loop Poisson traffic
  (benchmarks/openloop.py) at 50 % and 80 % of that capacity gives p50/p99 latency from
  arrival to answer. Client and server share this machine's cores, so the served capacity
  is what the machine sustains with its own load generator on it.

Rounds alternate with a fresh server each; every cell is the median over rounds.
"""
from __future__ import annotations

import os
import statistics
from typing import Any

import numpy as np

from noisefeat.runtime import median_s, torch_threads

from .timing import MachineLoad

BLOCKS = 16
SIZES = (64, 128)
SERVED_SIZE = 64
SHARES = (0.5, 0.8)
SATURATING_CLIENTS = 8


def _halves(blocks: int, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two half buffers of a moderately noisy render (as `loadtest.make_request`)."""
    rng = np.random.default_rng(seed)
    even = rng.random((blocks, size, size, 3), dtype=np.float32)
    odd = np.clip(even + rng.normal(0, 0.02, even.shape), 0, None).astype(np.float32)
    return even, odd


def per_core(sizes: tuple[int, ...] = SIZES, repeats: int = 9) -> list[dict[str, Any]]:
    """Milliseconds per request of BLOCKS blocks and blocks per second on one core, for the
    bundled model and the flip criterion at each block size."""
    from renderer.criteria import UnitView, FlipCriterion
    from service.registry import ModelRegistry

    registry = ModelRegistry({"m": None})
    registry.load()
    served = registry.get("m")
    flip = FlipCriterion()
    rows = []
    with torch_threads(1):
        for size in sizes:
            even, odd = _halves(BLOCKS, size)
            views = [UnitView(mean=0.5 * (a + b), spp=64, halves=(a, b), half_spp=(32, 32))
                     for a, b in zip(even, odd)]
            ids = list(range(BLOCKS))
            runs = {"bundled model": lambda: served.infer({"even": even, "odd": odd}),
                    "flip criterion": lambda: flip.decide(ids, views)}
            for name, fn in runs.items():
                with MachineLoad() as load:
                    seconds = median_s(fn, repeats)
                rows.append({"what": name, "size": size, "blocks": BLOCKS, "ms_per_request": 1e3 * seconds,
                             "blocks_per_s_per_core": BLOCKS / seconds, "other_load": load.share})
    return rows


def served_round(size: int = SERVED_SIZE, shares: tuple[float, ...] = SHARES, seconds: float = 20.0,
                 seed: int = 0) -> dict[str, Any]:
    """One fresh server: its saturated throughput, then open-loop traffic at each share of it."""
    from tests.support.local_server import LocalServer
    from .loadtest import run_load
    from .openloop import run_open_loop

    with LocalServer({"bench": None}) as server:
        run_load(server.url, model="bench", token=server.token, binary=True, clients=2, requests_per_client=2,
                 blocks=BLOCKS, size=size)                                    # warm
        with MachineLoad(mine=(server.process.pid,)) as load:
            sat = run_load(server.url, model="bench", token=server.token, binary=True,
                           clients=SATURATING_CLIENTS, requests_per_client=24, blocks=BLOCKS, size=size,
                           max_seconds=120)
        sat["other_load"] = load.share
        capacity = sat["requests_per_s"]
        runs = []
        for i, share in enumerate(shares):
            rate = share * capacity
            n = int(min(1500, max(60, rate * seconds)))
            with MachineLoad(mine=(server.process.pid,)) as load:
                r = run_open_loop(server.url, model="bench", token=server.token, rate=rate, requests=n,
                                  blocks=BLOCKS, size=size, seed=seed + i)
            runs.append({"share": share, **r, "other_load": load.share})
    return {"saturated": sat, "capacity_rps": capacity, "open_loop": runs}


def bench_capacity(repeats: int = 3) -> dict[str, Any]:
    """Per-core figures, then `repeats` served rounds (medians)."""
    cores = per_core()
    rounds = [served_round(seed=100 * k) for k in range(repeats)]
    med = statistics.median

    def cell(i: int, key: str) -> float | None:
        vals = [r["open_loop"][i][key] for r in rounds if r["open_loop"][i][key] is not None]
        return med(vals) if vals else None
    served = {"capacity_rps": med(r["capacity_rps"] for r in rounds),
              "capacity_rounds": [r["capacity_rps"] for r in rounds],
              "saturated_p50_ms": med(r["saturated"]["p50_ms"] for r in rounds),
              "saturated_p99_ms": med(r["saturated"]["p99_ms"] for r in rounds),
              "open_loop": [{"share": share, "offered_rate": cell(i, "offered_rate"),
                             "achieved_rate": cell(i, "achieved_rate"), "p50_ms": cell(i, "p50_ms"),
                             "p99_ms": cell(i, "p99_ms"), "p99_rounds": [r["open_loop"][i]["p99_ms"] for r in rounds],
                             "requests": sum(r["open_loop"][i]["requests"] for r in rounds),
                             "errors": sum(r["open_loop"][i]["errors"] for r in rounds),
                             "other_load": cell(i, "other_load")}
                            for i, share in enumerate(SHARES)]}
    return {"cpus": os.cpu_count(), "blocks": BLOCKS, "served_size": SERVED_SIZE, "repeats": repeats,
            "per_core": cores, "served": served}


def md_capacity(r: dict[str, Any]) -> str:
    def f(v: float | None, digits: int = 0) -> str:
        return "-" if v is None else f"{v:.{digits}f}"

    def load(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.0f} %"
    lines = [f"**Per core, in process** (one torch thread, requests of {r['blocks']} blocks, warm, medians; "
             "the bundled model computes FLIP between the half buffers, then its SVM):", "",
             "| decides | block | ms per request | blocks per second per core | other processes' load |",
             "|---|---|---|---|---|"]
    for x in r["per_core"]:
        lines.append(f"| {x['what']} | {x['size']}x{x['size']} | {x['ms_per_request']:.1f} "
                     f"| {x['blocks_per_s_per_core']:.0f} | {load(x['other_load'])} |")
    s = r["served"]
    n, size = r["blocks"], r["served_size"]
    cap_blocks = s["capacity_rps"] * n
    lines += ["", f"**Served** (`noisestop serve`, bundled model, binary requests of {n} blocks of {size}x{size}, "
              f"loopback, {r['cpus']} CPUs shared by server and load generator, medians of {r['repeats']} rounds, "
              "a fresh server each): capacity "
              f"{s['capacity_rps']:.1f} requests/s = {cap_blocks:.0f} blocks/s "
              f"({cap_blocks / r['cpus']:.0f} per core) at {SATURATING_CLIENTS} closed-loop clients "
              f"(rounds: {', '.join(f(v, 1) for v in s['capacity_rounds'])} req/s; p50 {f(s['saturated_p50_ms'])} ms, "
              f"p99 {f(s['saturated_p99_ms'])} ms there). Open-loop Poisson arrivals at a share of it, latency "
              "from arrival to answer:", "",
              "| load | offered (req/s) | answered (req/s) | requests | p50 (ms) | p99 (ms) (each round) | errors "
              "| other processes' load |",
              "|---|---|---|---|---|---|---|---|"]
    for x in s["open_loop"]:
        each = ", ".join(f(v) for v in x["p99_rounds"])
        lines.append(f"| {100 * x['share']:.0f} % | {f(x['offered_rate'], 1)} | {f(x['achieved_rate'], 1)} "
                     f"| {x['requests']} | {f(x['p50_ms'])} | {f(x['p99_ms'])} ({each}) | {x['errors']} "
                     f"| {load(x['other_load'])} |")
    return "\n".join(lines)
