"""Hardening, third round (issue 34): the costliest valid JSON in a loop, burst-then-stall
uploaders, and each hostile file the issue named against the commands that read it.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from .cli_run import ROOT, run_cli


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
    return {"costly_json": costly, "burst_then_stall": stall, "files": hostile_files(bundle)}


def hostile_files(bundle: str) -> list[dict[str, Any]]:
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
        rows.append({"case": "reference.exr -> /dev/zero: evaluate", **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "reference.exr -> /dev/zero: dataset check",
                     **run_cli(["dataset", "check", str(d)])})
        d = stack("bigmeta")
        with open(d / "checker" / "meta.json", "r+b") as f:
            f.truncate(3 << 30)                                   # sparse: no disk used
        rows.append({"case": "meta.json of 3 GB (sparse): evaluate", **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "meta.json of 3 GB (sparse): dataset check", **run_cli(["dataset", "check", str(d)])})
        d = stack("zerotail")
        level = sorted((d / "checker" / "levels").glob("*.exr"))[0]
        data = bytearray(level.read_bytes())
        data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
        level.write_bytes(bytes(data))
        rows.append({"case": "level EXR, zero-filled tail, same size: evaluate",
                     **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "level EXR, zero-filled tail, same size: dataset check",
                     **run_cli(["dataset", "check", str(d)])})
        home = tmp_path / "home"
        (home / "noisestop").mkdir(parents=True)
        user_flip = home / "noisestop" / "flip.json"
        with open(user_flip, "wb") as f:
            f.truncate(3 << 30)
        render = ["render", "--scene", "cornell", "--resolution", "64", "--max-spp", "32", "--criterion", "flip"]
        rows.append({"case": "user flip.json of 3 GB (sparse): render",
                     **run_cli([*render, "--out", str(tmp_path / "r1")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        user_flip.unlink()
        user_flip.write_text("[" * 100000 + "]" * 100000)
        rows.append({"case": "user flip.json nested 100000 deep: render",
                     **run_cli([*render, "--out", str(tmp_path / "r2")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        user_flip.write_text(json.dumps({"pooling": "tile8-max", "curve": [{"tau": -0.01, "c": 0.1},
                                                                          {"tau": 0.02, "c": 0.2}]}))
        rows.append({"case": "user flip.json with a negative tau: render",
                     **run_cli([*render, "--out", str(tmp_path / "r3")], {"NOISESTOP_DATA_DIR": str(home / "noisestop")})})
        rows.append({"case": "NOISESTOP_TOKEN_FILE=/dev/zero: serve",
                     **run_cli(["serve", "--model", bundle, "--port", "0"], {"NOISESTOP_TOKEN_FILE": "/dev/zero"})})
        rows.append({"case": "render --spp-budget 8 (step 16)",
                     **run_cli([*render, "--spp-budget", "8", "--out", str(tmp_path / "r4")])})
        rows.append({"case": "render --max-spp -1", **run_cli([*render, "--max-spp", "-1", "--out", str(tmp_path / "r5")])})
    return rows


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
