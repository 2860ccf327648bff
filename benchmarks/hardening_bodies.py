"""Hostile request bodies against a live server (in `noisestop bench hardening`): the
costliest valid JSON looped beside normal requests, uploaders that send a burst and then
stall, large nested and valid JSON bodies, and bodies at the parse pool's threshold (what
the server parses on its own thread and what it hands to the pool).

Each case runs against a fresh server (`loadtest.LocalServer`) while normal requests and
health probes are timed. Goals: a normal request's p99 at most 2x its p99 alone, health p95
at most 100 ms, no traceback (docs/benchmarks/reliability.md).
"""
from __future__ import annotations

from typing import Any


def bench_costly_json(bundle: str, seconds: float = 20.0) -> dict[str, Any]:
    """The costliest valid JSON (every value in 7 nested lists) looped against a fresh server
    while normal requests and health probes are timed."""
    from . import attack
    from .loadtest import LocalServer
    with LocalServer({"demo": bundle}) as s:
        costly = attack.costly_json_loop(s.url, s.token, seconds=seconds)
        costly["tracebacks"] = s.log().count("Traceback")
    return costly


def bench_burst_then_stall(bundle: str) -> dict[str, Any]:
    """16 uploaders that each send 63 MiB of a body and then stall for 15 s: how normal
    requests fare while they hold their memory, and how soon after they hang up."""
    from . import attack
    from .loadtest import LocalServer
    with LocalServer({"demo": bundle}) as s:
        stall = attack.burst_then_stall(s.url, s.token, stallers=16, megabytes=63, hold_s=15.0, after_s=8.0)
        stall["tracebacks"] = s.log().count("Traceback")
    return stall


def md_costly_json(c: dict[str, Any]) -> str:
    """One line: normal requests and health while the costliest JSON loops."""
    return (f"Costliest valid JSON ({c['body_bytes'] / 2**20:.1f} MiB, every value in 7 nested lists) in a loop: "
            f"normal requests p99 {c['alone_p99_ms']:.0f} -> {c['loaded_p99_ms']:.0f} ms ({c['p99_ratio']:.2f}x), "
            f"{c['normal_ok']}/{c['normal_requests']} answered 200; health slowest {c['health_max_ms']:.0f} ms over "
            f"{c['health_probes']} probes; the attacker got {', '.join(c['attacker_statuses'])}.")


def md_burst_then_stall(b: dict[str, Any]) -> str:
    """One line: normal requests while the stallers hold on, and after they hang up."""
    first = b["first_200_after_s"] if b["first_200_after_s"] is not None else "never"
    return (f"Burst-then-stall x{b['stallers']} ({b['megabytes']} MiB each, held {b['hold_s']:.0f} s): normal "
            f"requests {b['during_ok']}/{b['during']} answered 200 (statuses {', '.join(b['during_statuses'])}), "
            f"p99 {b['during_p99_ms']:.0f} ms; after the stallers hung up: first 200 after {first} s, "
            f"{b['after_ok']}/{b['after']} 200.")


def bench_large_bodies(bundle: str, seconds: float = 10.0) -> list[dict[str, Any]]:
    """Large JSON bodies looped against a fresh server: 255 kB nested 11 deep, and a valid
    255 kB [240, 8, 8, 3] request, by 1 and by 4 clients; normal p99 against alone and
    health p95 (goals: at most 2x, at most 100 ms)."""
    from . import attack
    from .loadtest import LocalServer
    rows = []
    for name, body in (("255 kB nested 11 deep", attack.nested_json_255k),
                       ("valid 184 kB, 2 x [120,8,8,3]", attack.valid_json_255k)):
        for clients in (1, 4):
            with LocalServer({"demo": bundle}) as s:
                r = attack.costly_json_loop(s.url, s.token, seconds=seconds, attack=body, attackers=clients)
                r["tracebacks"] = s.log().count("Traceback")
            rows.append({"body": name, "clients": clients, **r})
    return rows


def bench_inline_json(bundle: str, seconds: float = 8.0, clients: tuple[int, ...] = (1, 4)) -> list[dict[str, Any]]:
    """Bodies at the parse pool's threshold (16 KiB) looped against a fresh server: 16.3 kB
    nested 11 deep (under the byte threshold, but too many lists for `parsepool.parse_inline`
    to keep it on the server's thread), the same at 16.5 kB (over the byte threshold), the
    costliest body still parsed inline (`attack.bound_json`) and a valid 16 kB halves
    request, by 1 and by 4 clients; normal p99 against alone and health p95 (goals: at most
    2x, at most 100 ms)."""
    from functools import partial

    from . import attack
    from .loadtest import LocalServer, make_request
    rows = []
    halves = partial(make_request, blocks=16, size=128, binary=True, inputs="halves")
    for name, body, models, normal in (
            ("16.3 kB nested 11 deep", partial(attack.nested_json, 16_300), {"demo": bundle}, None),
            ("16.5 kB nested 11 deep", partial(attack.nested_json, 16_500), {"demo": bundle}, None),
            ("16 kB at the inline bound (253 lists)", partial(attack.bound_json, 16_300), {"demo": bundle}, None),
            ("valid 16 kB halves", partial(attack.valid_halves_json, 16_000), {"bundled": None}, halves)):
        for n in clients:           # the halves body, and the normal requests beside it, to the bundled model
            with LocalServer(models) as s:
                r = attack.costly_json_loop(s.url, s.token, seconds=seconds, attack=body, attackers=n, make=normal)
                r["tracebacks"] = s.log().count("Traceback")
            rows.append({"body": name, "clients": n, **r})
    return rows


def md_inline_json(rows: list[dict[str, Any]]) -> str:
    lines = ["| body | clients | answered | normal p99 alone -> loaded | ratio | health p95 |",
             "|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['body']} ({x['body_bytes']} B) | {x['clients']} | {', '.join(x['attacker_statuses'])} | "
                     f"{x['alone_p99_ms']:.0f} -> {x['loaded_p99_ms']:.0f} ms | {x['p99_ratio']:.2f}x | "
                     f"{x['health_p95_ms']:.0f} ms |")
    return "\n".join(lines)
