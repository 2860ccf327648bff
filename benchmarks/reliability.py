"""`noisestop bench reliability`: the reliability table of BENCHMARKS.md.

Three sources, each counted as it ran, nothing typed by hand:

1. the attack scenarios of `benchmarks.attack` against `noisestop serve` in a subprocess with
   the default settings under RLIMIT_AS = 3 GiB: 64 idle connections (health latency),
   slow headers, a stalled body, the in-flight limit, the worst request shapes (status
   and the server's peak RSS after each);
2. a schemathesis stateful run against the app in process (calls, statuses, 5xx);
3. the attack test files run by pytest (`SUITES`: test_error_contract.py, test_fuzz.py,
   test_kill_resume.py, test_service_hardening.py): cases and outcomes from its JUnit
   report, hypothesis examples from its statistics. They need the source tree (tests/
   next to the package);
4. the hardening scenarios (`bench_hardening`, also the section `hardening` on its own):
   peak RSS of the worst JSON and binary shapes with and without the address-space cap,
   normal latency beside slow uploaders, every way of starting `serve` without a token,
   SIGHUP with a request in flight, a protocol error, a key twice; the hostile files of each
   round, scene-named ones included (`bench_scene_files`, issue 51).
"""
from __future__ import annotations

import json
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

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
SUITES = ("tests/cli/test_error_contract.py", "tests/service/test_fuzz.py", "tests/renderer/test_kill_resume.py",
          "tests/service/test_service_hardening.py")
ADDRESS_SPACE = 3 << 30
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


# ----------------------------------------------------------------------------- markdown


def _mib(n: int) -> str:
    return f"{n / (1 << 20):,.0f} MiB"


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
                     + f"; server peak RSS so far {_mib(w['peak_rss'])}"))
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
              "test_service_hardening": "issue 26 on the service: memory before parsing, slow uploaders, duplicate "
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
             f"Server (defaults, RLIMIT_AS {_mib(ADDRESS_SPACE)}): idle RSS {_mib(s['idle_memory']['rss'])}, peak RSS "
             f"{_mib(peak)} over every scenario above (ceiling {_mib(CEILING)}: "
             f"{'met' if peak < CEILING else 'EXCEEDED'}); still serving at the end: {'yes' if s['alive'] else 'NO'}. "
             f"5xx: {server_5xx} from the worst shapes, {st['server_errors']} from schemathesis, "
             f"1 deliberate 503 from the in-flight limit. Test suites: exit {su['exit']}, "
             f"{su['tracebacks_in_output']} tracebacks in their output, {su['seconds']:.0f} s."]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- hardening

#: the variables and flags `serve` is started with, to find any path that serves without a
#: token that nobody asked for (the issue: `NOISESTOP_TOKEN=` did)
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
                "round3": bench_round3(bundle), "round4": bench_round4(bundle), "round4_files": _round4_files(bundle),
                "round5_scene_files": bench_scene_files(),
                "round5_nonfinite": bench_nonfinite_scenes(), "round5_inline_json": bench_inline_json(bundle)}


# ----------------------------------------------------------------------------- issue 51

#: an element of a scene XML naming the file NAME, by the kind of file it names
SCENE_NAMING = {
    "mesh (ply)": '<shape type="ply"><string name="filename" value="{name}"/></shape>',
    "include": '<include filename="{name}"/>',
    "bitmap texture": ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                       '<string name="filename" value="{name}"/></texture></bsdf></shape>'),
    "environment map": '<emitter type="envmap"><string name="filename" value="{name}"/></emitter>',
}


def bench_scene_files() -> list[dict[str, Any]]:
    """Issue 51's scene-named files: each kind a scene XML names (mesh, include, bitmap,
    environment map) as /dev/zero, a FIFO, a 3 GB sparse file and a missing file, against
    `render --scene FILE.xml` (goal: exit 2, one line naming the file, at most 5 s and 500 MiB)."""
    from tests.support.bad_files import BAD_KINDS, bad_file

    sensor = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="16"/>'
              '<integer name="height" value="16"/></film></sensor>')
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (element, naming) in enumerate(SCENE_NAMING.items()):
            for j, kind in enumerate(BAD_KINDS):
                d = Path(tmp) / f"s{i}{j}"
                d.mkdir()
                target = bad_file(d / "named.dat", kind)
                xml = d / "scene.xml"
                xml.write_text(f'<scene version="3.0.0">{naming.format(name=target.name)}{sensor}</scene>')
                r = _run_cli(["render", "--scene", str(xml), "--max-spp", "16", "--criterion", "uniform",
                              "--out", str(d / "out")])
                rows.append({"case": f"{element} as {kind}: render", "names_file": str(target.name) in r["message"],
                             **r})
    return rows


def md_scene_files(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene names | exit | seconds | stderr lines | peak RSS | names the file | message |",
             "|---|---|---|---|---|---|---|"]
    for f in rows:
        lines.append(f"| {f['case']} | {f['exit']} | {f['seconds']:.1f} | {f['lines']} | "
                     f"{f['peak_rss_kib'] / 1024:.0f} MiB | {'yes' if f['names_file'] else 'NO'} | "
                     f"{f['message'].replace('|', '/')} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- issue 42

def bench_round4(bundle: str, seconds: float = 10.0) -> list[dict[str, Any]]:
    """Issue 42's bodies looped against a fresh server: 255 kB nested 11 deep, and a valid
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
    """Issue 51's bodies at the parse pool's threshold (16 KiB) looped against a fresh server:
    16.3 kB nested 11 deep (was parsed on the server's own thread), the same at 16.5 kB
    (in the pool before too), the costliest body still parsed inline (`attack.bound_json`)
    and a valid 16 kB halves request, by 1 and by 4 clients; normal
    p99 against alone and health p95 (goals: at most 2x, at most 100 ms)."""
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
    lines = ["| body | clients | answered | normal p99 alone -> loaded | ratio | health p95 |", "|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['body']} ({x['body_bytes']} B) | {x['clients']} | {', '.join(x['attacker_statuses'])} | "
                     f"{x['alone_p99_ms']:.0f} -> {x['loaded_p99_ms']:.0f} ms | {x['p99_ratio']:.2f}x | "
                     f"{x['health_p95_ms']:.0f} ms |")
    return "\n".join(lines)


def _round4_files(bundle: str) -> list[dict[str, Any]]:
    """Issue 42's input slots, each as /dev/zero, a FIFO and a 3 GB sparse file, against the
    command that reads it (goal: exit 2, one line naming the file, at most 5 s and 400 MiB)."""
    import shutil

    rows = []
    render = ["render", "--scene", "cornell", "--resolution", "32", "--max-spp", "16", "--criterion", "variance"]
    evaluate = ["evaluate", "--data", str(ROOT / "tests" / "fixtures" / "dataset"), "--criterion", "model"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)

        def bad(path: Path, kind: str) -> Path:
            path.parent.mkdir(parents=True, exist_ok=True)
            if kind == "/dev/zero":
                path.symlink_to("/dev/zero")
            elif kind == "FIFO":
                os.mkfifo(path)
            else:
                with open(path, "wb") as f:
                    f.truncate(3 << 30)
            return path

        for i, kind in enumerate(("/dev/zero", "FIFO", "3 GB sparse")):
            out = tmp_path / f"ck{i}"
            bad(out / "checkpoint.npz", kind)
            rows.append({"case": f"checkpoint.npz as {kind}: render --resume",
                         **_run_cli([*render, "--resume", "--out", str(out)])})
            weights = bad(tmp_path / f"w{i}" / "weights.safetensors", kind)
            rows.append({"case": f"NOISESTOP_FEATURE_WEIGHTS as {kind}: evaluate --criterion model",
                         **_run_cli([*evaluate, "--model", bundle], {"NOISESTOP_FEATURE_WEIGHTS": str(weights)})})
            for member in ("model.skops", "manifest.json"):
                b = tmp_path / f"b{i}{member}"
                shutil.copytree(bundle, b)
                (b / member).unlink()
                bad(b / member, kind)
                rows.append({"case": f"bundle {member} as {kind}: evaluate --criterion model",
                             **_run_cli([*evaluate, "--model", str(b)])})
            if kind != "3 GB sparse":             # a lock file's content is never read past 200 bytes
                out = tmp_path / f"lk{i}"
                bad(out / ".noisestop.lock", kind)
                rows.append({"case": f"output lock file as {kind}: render", **_run_cli([*render, "--out", str(out)])})
    return rows


# ----------------------------------------------------------------------------- issue 51

#: the non-finite scenes of issue 51: (name, constant emitter radiance, sphere reflectance)
NONFINITE_SCENES = (("NaN emitter", "nan", None), ("Inf emitter", "inf", None), ("1e38 emitter", "1e38", None),
                    ("NaN reflectance sphere", "0.5", "nan"))


def bench_nonfinite_scenes(criteria: tuple[str, ...] = ("flip", "model", "variance")) -> list[dict[str, Any]]:
    """Issue 51's scenes rendered 32x32 (16-px blocks, 4..16 spp) by each criterion: units
    converged (goal: 0 among those with pixels without a finite sample), exit status
    (3: finished with such pixels), and whether the end says so (stderr and summary)."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, radiance, reflectance in NONFINITE_SCENES:
            scene = Path(tmp) / f"{len(rows)}.xml"
            sphere = "" if reflectance is None else (
                '<shape type="sphere"><float name="radius" value="0.7"/><bsdf type="diffuse">'
                f'<rgb name="reflectance" value="{reflectance}, {reflectance}, {reflectance}"/></bsdf></shape>')
            scene.write_text(
                '<scene version="3.0.0"><integrator type="path"/><sensor type="perspective"><float name="fov" '
                'value="40"/><transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>'
                '</transform><film type="hdrfilm"><integer name="width" value="32"/><integer name="height" '
                f'value="32"/></film></sensor><emitter type="constant"><rgb name="radiance" value="{radiance}, '
                f'{radiance}, {radiance}"/></emitter>{sphere}</scene>')
            for criterion in criteria:
                out = Path(tmp) / f"out{len(rows)}"
                run = _run_cli(["render", "--scene", str(scene), "--out", str(out), "--block", "16", "--step", "4",
                                "--min-spp", "4", "--max-spp", "16", "--criterion", criterion])
                rep = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
                nf = rep.get("nonfinite", {})
                units = rep.get("tiles", rep.get("blocks", []))
                rows.append({"scene": name, "criterion": criterion, "exit": run["exit"], "seconds": run["seconds"],
                             "units": len(units), "converged": sum(u["converged"] for u in units),
                             "held_units": nf.get("units"), "pixels_without_sample": nf.get("pixels"),
                             "dropped": nf.get("dropped"), "warning_lines": run["stderr_nonfinite"],
                             "tracebacks": run["tracebacks"]})
    return rows


def md_nonfinite(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene (32x32, 16-px blocks, 4..16 spp) | criterion | units converged | units without a finite "
             "pixel (never converged) | pixels without a finite sample | exit | stderr warning lines |", "|---|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['scene']} | {x['criterion']} | {x['converged']} of {x['units']} | {x['held_units']} | "
                     f"{x['pixels_without_sample']} | {x['exit']} | {x['warning_lines']} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- issue 34

def bench_round3(bundle: str) -> dict[str, Any]:
    """Issue 34's cases: the costliest valid JSON in a loop, burst-then-stall x16, the
    hostile files (one line, exit 2, peak RSS, seconds) and the renders that ended wrong."""
    from . import attack
    from .loadtest import LocalServer
    with LocalServer({"demo": bundle}) as s:
        costly = attack.costly_json_loop(s.url, s.token, seconds=20.0)
        costly["tracebacks"] = s.log().count("Traceback")
    with LocalServer({"demo": bundle}) as s:
        stall = attack.burst_then_stall(s.url, s.token, stallers=16, megabytes=63, hold_s=15.0, after_s=8.0)
        stall["tracebacks"] = s.log().count("Traceback")
    return {"costly_json": costly, "burst_then_stall": stall, "files": _hostile_files(bundle)}


def _run_cli(argv: list[str], env: dict[str, str] | None = None, timeout: float = 60.0) -> dict[str, Any]:
    """One `noisestop` command: exit status, seconds, stderr lines, last line, peak RSS (KiB)."""
    t0 = time.monotonic()
    environ = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    environ = {k: v for k, v in environ.items() if k not in ("NOISESTOP_TOKEN",) or "NOISESTOP_TOKEN_FILE" not in (env or {})}
    wrapper = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
               "print('PEAK_RSS_KIB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
               "sys.exit(r.returncode)")
    proc = subprocess.Popen([sys.executable, "-c", wrapper, sys.executable, "-m", "service.cli", *argv], env=environ, cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, err = proc.communicate(timeout=timeout)
        code: int | str = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        code = "hung"
    peak = [int(x.split()[1]) for x in err.splitlines() if x.startswith("PEAK_RSS_KIB ")]
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("PEAK_RSS_KIB ")]
    return {"exit": code, "seconds": time.monotonic() - t0, "lines": len(lines),
            "message": lines[-1][:200] if lines else "", "tracebacks": err.count("Traceback"),
            "stderr_nonfinite": sum("non-finite samples:" in x for x in lines),
            "peak_rss_kib": peak[0] if peak else 0}


def _hostile_files(bundle: str) -> list[dict[str, Any]]:
    """Each hostile file the issue named, against the commands that read it."""
    import shutil
    fixtures = ROOT / "tests" / "fixtures" / "dataset"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)

        def stack(name: str) -> Path:
            d = tmp_path / name / "data"
            shutil.copytree(fixtures, d)
            return d

        d = stack("devzero")
        (d / "checker" / "reference.exr").unlink(missing_ok=True)
        (d / "checker" / "reference.exr").symlink_to("/dev/zero")
        rows.append({"case": "reference.exr -> /dev/zero: evaluate", **_run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "reference.exr -> /dev/zero: dataset check",
                     **_run_cli(["dataset", "check", str(d)])})
        d = stack("bigmeta")
        with open(d / "checker" / "meta.json", "r+b") as f:
            f.truncate(3 << 30)                                   # sparse: no disk used
        rows.append({"case": "meta.json of 3 GB (sparse): evaluate", **_run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "meta.json of 3 GB (sparse): dataset check", **_run_cli(["dataset", "check", str(d)])})
        d = stack("zerotail")
        level = sorted((d / "checker" / "levels").glob("*.exr"))[0]
        data = bytearray(level.read_bytes())
        data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
        level.write_bytes(bytes(data))
        rows.append({"case": "level EXR, zero-filled tail, same size: evaluate",
                     **_run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "level EXR, zero-filled tail, same size: dataset check",
                     **_run_cli(["dataset", "check", str(d)])})
        home = tmp_path / "home"
        (home / "noisestop").mkdir(parents=True)
        user_flip = home / "noisestop" / "flip.json"
        with open(user_flip, "wb") as f:
            f.truncate(3 << 30)
        render = ["render", "--scene", "cornell", "--resolution", "64", "--max-spp", "32", "--criterion", "flip"]
        rows.append({"case": "user flip.json of 3 GB (sparse): render",
                     **_run_cli([*render, "--out", str(tmp_path / "r1")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        user_flip.unlink()
        user_flip.write_text("[" * 100000 + "]" * 100000)
        rows.append({"case": "user flip.json nested 100000 deep: render",
                     **_run_cli([*render, "--out", str(tmp_path / "r2")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        user_flip.write_text(json.dumps({"pooling": "tile8-max", "curve": [{"tau": -0.01, "c": 0.1},
                                                                          {"tau": 0.02, "c": 0.2}]}))
        rows.append({"case": "user flip.json with a negative tau: render",
                     **_run_cli([*render, "--out", str(tmp_path / "r3")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        rows.append({"case": "NOISESTOP_TOKEN_FILE=/dev/zero: serve",
                     **_run_cli(["serve", "--model", bundle, "--port", "0"], {"NOISESTOP_TOKEN_FILE": "/dev/zero"})})
        rows.append({"case": "render --spp-budget 8 (step 16)",
                     **_run_cli([*render, "--spp-budget", "8", "--out", str(tmp_path / "r4")])})
        rows.append({"case": "render --max-spp -1", **_run_cli([*render, "--max-spp", "-1", "--out", str(tmp_path / "r5")])})
    return rows


def _hardening_shapes() -> dict[str, Any]:
    """Named (body, headers) makers: the worst JSON shapes per byte, admitted or refused,
    and the largest binary ones."""
    from . import attack
    from service.limits import DEFAULT_MAX_BODY, DEFAULT_MEMORY_BUDGET, json_cost
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
        "JSON: 62 MiB, 20 lists around every value (the issue's)": attack.nested_json_request_62,
        "JSON: 20 lists around every value, estimate 90% of the budget (parsed; 400: not 26 features)":
            lambda: nested_values(0.9),
        "JSON image [2, 1024, W, 3] x 2, one-digit numbers nested per pixel, 64 MiB (issue 14's worst)":
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


def md_round3(r: dict[str, Any]) -> str:
    c, b = r["costly_json"], r["burst_then_stall"]
    lines = [f"Costliest valid JSON ({c['body_bytes'] / 2**20:.1f} MiB, every value in 7 nested lists) in a loop: "
             f"normal requests p99 {c['alone_p99_ms']:.0f} -> {c['loaded_p99_ms']:.0f} ms ({c['p99_ratio']:.2f}x), "
             f"{c['normal_ok']}/{c['normal_requests']} answered 200; health slowest {c['health_max_ms']:.0f} ms over "
             f"{c['health_probes']} probes; the attacker got {', '.join(c['attacker_statuses'])}.",
             f"Burst-then-stall x{b['stallers']} ({b['megabytes']} MiB each, held {b['hold_s']:.0f} s): normal requests "
             f"{b['during_ok']}/{b['during']} answered 200 (statuses {', '.join(b['during_statuses'])}), p99 "
             f"{b['during_p99_ms']:.0f} ms; after the stallers hung up: first 200 after "
             f"{b['first_200_after_s'] if b['first_200_after_s'] is not None else 'never'} s, {b['after_ok']}/{b['after']} 200.",
             "", "| hostile input | exit | seconds | stderr lines | peak RSS | message |", "|---|---|---|---|---|---|"]
    for f in r["files"]:
        lines.append(f"| {f['case']} | {f['exit']} | {f['seconds']:.1f} | {f['lines']} | "
                     f"{f['peak_rss_kib'] / 1024:.0f} MiB | {f['message'].replace('|', '/')} |")
    return "\n".join(lines)


def md_hardening(r: dict[str, Any]) -> str:
    lines = ["| request | cap | answer | seconds | server peak RSS (idle peak) | after it |", "|---|---|---|---|---|---|"]
    for w in r["shapes"]:
        lines.append(f"| {w['request']} | {'3 GiB' if w['cap'] else 'none'} | {w['status']} | {w['seconds']:.1f} | "
                     f"{_mib(w['peak_rss'])} ({_mib(w['idle_peak_rss'])}) | health {w['health_after']}, "
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
    if "round3" in r:
        lines += ["", md_round3(r["round3"])]
    if "round5_scene_files" in r:
        lines += ["", md_scene_files(r["round5_scene_files"])]
    if "round5_nonfinite" in r:
        lines += ["", md_nonfinite(r["round5_nonfinite"])]
    if "round5_inline_json" in r:
        lines += ["", md_inline_json(r["round5_inline_json"])]
    return "\n".join(lines)
