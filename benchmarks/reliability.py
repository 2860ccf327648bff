"""`noisestop bench reliability`: the reliability table of BENCHMARKS.md.

Four sources, each counted as it ran, nothing typed by hand:

1. the attack scenarios of `benchmarks.attack` against `noisestop serve` in a subprocess with
   the default settings under RLIMIT_AS = 3 GiB: 64 idle connections (health latency),
   slow headers, a stalled body, the in-flight limit, the worst request shapes (status
   and the server's peak RSS after each);
2. a schemathesis stateful run against the app in process (calls, statuses, 5xx);
3. the attack test files run by pytest (`SUITES`: test_error_contract.py, test_fuzz.py,
   test_kill_resume.py, test_service_hardening.py): cases and outcomes from its JUnit
   report, hypothesis examples from its statistics. They need the source tree (tests/
   next to the package);
4. the hardening scenarios (`benchmarks.hardening.bench_hardening`, also the section
   `hardening` on its own): peak RSS of the worst JSON and binary shapes with and without
   the address-space cap, normal latency beside slow uploaders, every way of starting
   `serve` without a token, SIGHUP with a request in flight, a protocol error, a key twice;
   hostile bodies and files (scene-named ones included), non-finite scenes, the scene
   walk, the loop's state and the doors that check first.
"""
from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path
from typing import Any

from .cli_run import ROOT
from .hardening import ADDRESS_SPACE, bench_hardening, mib

log = logging.getLogger(__name__)

SUITES = ("tests/cli/test_error_contract.py", "tests/service/test_fuzz.py", "tests/renderer/test_kill_resume.py",
          "tests/service/test_service_hardening.py")
#: the peak RSS the attacked server must stay under
CEILING = 2 << 30


def bench_reliability() -> dict[str, Any]:
    return {"server": _server_scenarios(), "stateful": _stateful(), "suites": _suites(),
            "hardening": bench_hardening()}


def _server_scenarios() -> dict[str, Any]:
    from . import attack
    from service.limits import DEFAULT_MAX_BODY
    from tests.support.local_server import LocalServer
    from tests.support.demo import make_demo_bundle, make_request

    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_demo_bundle(Path(tmp) / "demo", name="demo")
        with LocalServer({"demo": str(bundle)}, address_space=ADDRESS_SPACE) as s:
            body, headers = make_request(blocks=2, size=32, binary=True)
            out: dict[str, Any] = {"idle_memory": s.memory()}
            out["flood"] = attack.idle_flood(s.url, n=64, probes=20, wait=30,
                                             infer=lambda: attack.post(s.url, body, headers, s.token)[0])
            out["slow_headers"] = attack.slow_headers(s.url, interval=0.1)
            out["stalled_body"] = attack.stalled_body(s.url, s.token)
            out["over_limit"] = attack.over_the_limit(s.url, s.token, limit=64)
            out["worst"] = attack.run_worst_shapes(s.url, s.token, DEFAULT_MAX_BODY, concurrent=3, memory=s.memory)
            out["memory"] = s.memory()
            out["alive"] = s.process.poll() is None
    return out


def _stateful(max_examples: int = 60) -> dict[str, Any]:
    import schemathesis
    from hypothesis import HealthCheck, settings
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import (content_type_conformance, negative_data_rejection,
                                                   response_headers_conformance, response_schema_conformance,
                                                   status_code_conformance)

    from service.app import create_app
    from tests.support.demo import make_demo_bundle
    from service.registry import ModelRegistry

    checks = [not_a_server_error, status_code_conformance, content_type_conformance,
              response_headers_conformance, response_schema_conformance, negative_data_rejection]
    token = "reliability-token-0123456789"
    calls: list[int] = []
    with tempfile.TemporaryDirectory() as tmp:
        bundle = make_demo_bundle(Path(tmp) / "demo", name="demo")
        schema = schemathesis.openapi.from_asgi("/openapi.json", create_app(ModelRegistry({"demo": str(bundle)}),
                                                                             token=token))

        class Workflow(schema.as_state_machine()):   # type: ignore[misc]
            def get_call_kwargs(self, case):
                return {"headers": {"Authorization": f"Bearer {token}"}}

            def after_call(self, response, case):
                calls.append(response.status_code)

            def validate_response(self, response, case, additional_checks=None, **kwargs):
                case.validate_response(response, checks=checks)

        failure = None
        try:
            Workflow.run(settings=settings(max_examples=max_examples, stateful_step_count=6, deadline=None,
                                           database=None, suppress_health_check=list(HealthCheck)))
        except Exception as exc:      # a failed check: reported in the table, not raised
            failure = " ".join(str(exc).split())[:200]
    return {"calls": len(calls), "statuses": dict(sorted(Counter(calls).items())),
            "server_errors": sum(c >= 500 for c in calls), "failure": failure}


def _suites() -> dict[str, Any]:
    missing = [s for s in SUITES if not (ROOT / s).is_file()]
    if missing:
        raise FileNotFoundError(f"bench reliability runs {', '.join(missing)} from the source tree "
                                f"({ROOT}); not found")
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "junit.xml"
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                               "--hypothesis-show-statistics", f"--junitxml={report}", *SUITES],
                              cwd=ROOT, capture_output=True, text=True, timeout=1800,
                              env={**os.environ, "PYTHONPATH": os.pathsep.join(
                                  [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])})
        cases = _junit(report) if report.exists() else []
    return {"seconds": time.perf_counter() - t0, "exit": proc.returncode, "cases": cases,
            "examples": _hypothesis_examples(proc.stdout),
            "tracebacks_in_output": proc.stdout.count("Traceback (most recent call last)")}


def _junit(path: Path) -> list[dict[str, str]]:
    out = []
    for case in ET.parse(path).getroot().iter("testcase"):
        outcome = "passed"
        for tag in ("failure", "error", "skipped"):
            if case.find(tag) is not None:
                outcome = {"failure": "failed", "error": "error", "skipped": "skipped"}[tag]
        out.append({"file": case.get("classname", "").rsplit(".", 1)[-1], "name": case.get("name", ""),
                    "outcome": outcome})
    return out


def _hypothesis_examples(text: str) -> dict[str, int]:
    """Examples run per fuzz test, from pytest --hypothesis-show-statistics."""
    out: dict[str, int] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"^(?:tests/)?\S+::(\S+):", line.strip())
        if m:
            current = m.group(1)
            continue
        m = re.search(r"(\d+) passing(?: examples?)?, (\d+) failing", line)
        if current and m:
            out[current] = out.get(current, 0) + int(m.group(1)) + int(m.group(2))
    return out


def md_reliability(r: dict[str, Any]) -> str:
    s, st, su = r["server"], r["stateful"], r["suites"]
    flood, slow, stalled, over = s["flood"], s["slow_headers"], s["stalled_body"], s["over_limit"]
    rows = [
        ("64 idle connections (32 silent, 32 half a request line)",
         f"{flood['probes']} health probes + 1 infer",
         f"health {flood['health_ok']}/{flood['probes']} answered 200 (median {flood['health_median_s'] * 1e3:.0f} ms, "
         f"max {flood['health_max_s'] * 1e3:.0f} ms); infer {flood['infer_status']}; all {flood['closed_by_server']} "
         f"closed by the server after {flood['all_closed_after_s']:.1f} s" if flood["all_closed_after_s"] is not None
         else f"health {flood['health_ok']}/{flood['probes']}; {flood['closed_by_server']} of 64 closed"),
        ("slow headers, one byte per 0.1 s", "1",
         f"cut off after {slow['after_s']:.1f} s, {slow['bytes_sent']} of {slow['header_bytes']} header bytes "
         f"sent, answer {slow['status'] or 'none (closed)'}"),
        ("stalled body (10 of 1000 bytes, then silence)", "1", f"HTTP {stalled['status']} after {stalled['after_s']:.1f} s"),
        ("64 requests held in flight, one more (--limit-concurrency 64)", "1 + 1 probe",
         f"HTTP {over['extra_status']} (Retry-After {over['retry_after']}); health probe {over['health_status']}"),
    ]
    for w in s["worst"]:
        rows.append((f"worst shape: {w['request']}", str(len(w.get("statuses", [w["status"]]))),
                     f"HTTP {w['status']}" + (f" ({w['error'][:90]})" if w.get("error") else "")
                     + f"; server peak RSS so far {mib(w['peak_rss'])}"))
    rows.append(("schemathesis stateful (links inferred: index -> model -> metadata / ready / infer)",
                 str(st["calls"]), ", ".join(f"{k}: {v}" for k, v in st["statuses"].items())
                 + f"; 5xx: {st['server_errors']}" + (f"; check failed: {st['failure']}" if st["failure"] else "")))
    by_file: dict[str, Counter] = {}
    for c in su["cases"]:
        by_file.setdefault(c["file"], Counter())[c["outcome"]] += 1
    labels = {"test_error_contract": "command-line error contract (every case of the issue; tests/cli/test_error_contract.py)",
              "test_fuzz": "hypothesis fuzzing: tensor decoder, JSON parser and its memory estimate, duplicate keys, "
                           "manifest and checkpoint readers",
              "test_kill_resume": "kill -9 at 3 random passes, then --resume (bit-identical image and report)",
              "test_service_hardening": "the service's hardening: memory before parsing, slow uploaders, duplicate "
                                        "keys, protocol 400s, /openapi.json, out of memory, SIGHUP"}
    for f, counts in sorted(by_file.items()):
        extra = ""
        if f == "test_fuzz" and su["examples"]:
            extra = f"; {sum(su['examples'].values()):,} examples (" + ", ".join(
                f"{k.replace('test_', '')}: {v}" for k, v in su["examples"].items()) + ")"
        rows.append((labels.get(f, f), str(sum(counts.values())),
                     ", ".join(f"{n} {k}" for k, n in sorted(counts.items())) + extra))
    peak = s["memory"]["peak_rss"]
    server_5xx = sum(1 for w in s["worst"] for x in w.get("statuses", [w["status"]])
                     if isinstance(x, int) and x >= 500)
    lines = ["| attack | cases | outcome |", "|---|---|---|", *(f"| {a} | {b} | {c} |" for a, b, c in rows), "",
             f"Server (defaults, RLIMIT_AS {mib(ADDRESS_SPACE)}): idle RSS {mib(s['idle_memory']['rss'])}, peak RSS "
             f"{mib(peak)} over every scenario above (ceiling {mib(CEILING)}: "
             f"{'met' if peak < CEILING else 'EXCEEDED'}); still serving at the end: {'yes' if s['alive'] else 'NO'}. "
             f"5xx: {server_5xx} from the worst shapes, {st['server_errors']} from schemathesis, "
             f"1 deliberate 503 from the in-flight limit. Test suites: exit {su['exit']}, "
             f"{su['tracebacks_in_output']} tracebacks in their output, {su['seconds']:.0f} s."]
    return "\n".join(lines)
