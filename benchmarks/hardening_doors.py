"""Doors that check first (in `noisestop bench hardening`): a damaged reference under
`dataset relabel`, `bench --update` at a file that cannot be rewritten, unknown `bench`
model names, tokens with spaces or given by flag, a header line the HTTP layer cannot parse,
a folder as `render --reference` and a looping checkpoint link under `--resume`.

Each case is one command in a fresh process (`cli_run.run_cli`, with -q: exit, seconds,
stderr lines, peak RSS, last line); the goal is exit 2, one line, within 5 s and 500 MiB
(relabel's progress bar, on stderr by design, counts as a line of its own). The
header case is one request to a server in this process: its status and what its body
quotes of the request (goal: 400, nothing).
"""
from __future__ import annotations

import os
import shutil
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

from .cli_run import ROOT, run_cli

#: what the token and checkpoint cases run: a tiny render, and serve on a port never reached
TINY_RENDER = ["render", "--scene", "cornell", "--resolution", "32", "--block", "16", "--step", "4",
               "--min-spp", "4", "--max-spp", "8", "--criterion", "uniform"]
SECRET = "bench-secret-0123456789"


def _spoiled_stack(tmp: Path, value: float) -> Path:
    """The fixture's checker stack with one pixel of its reference set to `value`."""
    import numpy as np

    from learning.data.exr import read_exr, write_exr
    root = tmp / f"data-{value}"
    shutil.copytree(ROOT / "tests" / "fixtures" / "dataset" / "checker", root / "checker",
                    ignore=shutil.ignore_patterns(".cache"))
    ref = read_exr(root / "checker" / "reference.exr")
    ref[3, 3, 0] = np.float32(value)
    write_exr(root / "checker" / "reference.exr", ref)
    return root


def _cli_cases(tmp: Path) -> list[tuple[str, list[str], dict[str, str] | None]]:
    """(case, argv, environment) of every command-line case, their files made in `tmp`."""
    os.mkfifo(tmp / "fifo.md")
    (tmp / "empty").mkdir()
    (tmp / "empty-token").write_text("")
    loop = tmp / "loop"
    loop.mkdir()
    os.symlink("checkpoint.npz", loop / "checkpoint.npz")
    return [
        ("E10 relabel, one NaN pixel in the reference", ["dataset", "relabel", str(_spoiled_stack(tmp, float("nan"))),
                                                         "--tau", "0.03"], None),
        ("E10 relabel, one +Inf pixel in the reference", ["dataset", "relabel", str(_spoiled_stack(tmp, float("inf"))),
                                                          "--tau", "0.03"], None),
        ("E11 bench --update /dev/zero", ["bench", "stability", "--update", "/dev/zero"], None),
        ("E11 bench --update FIFO", ["bench", "stability", "--update", str(tmp / "fifo.md")], None),
        ("E11 bench --update folder", ["bench", "stability", "--update", str(tmp)], None),
        ("E12 bench --kinds zzz", ["bench", "models", "--kinds", "zzz"], None),
        ("E12 bench --arches zzz", ["bench", "models", "--arches", "zzz"], None),
        ("E13 serve, NOISESTOP_TOKEN=' abc'", ["serve", "--port", "1"], {"NOISESTOP_TOKEN": " abc"}),
        ("D13 render --reference FOLDER", [*TINY_RENDER, "--reference", str(tmp / "empty"),
                                           "--out", str(tmp / "o-ref")], None),
        ("D14 render --resume, checkpoint links to itself", [*TINY_RENDER, "--out", str(loop), "--resume"], None),
        ("D14 serve --token-file EMPTY", ["serve", "--port", "1", "--token-file", str(tmp / "empty-token")], None),
    ]


def _header_case() -> dict[str, Any]:
    """A request whose Authorization line holds a NUL, to a server in this process: the
    400's status, seconds, and whether its body quotes the token or the header."""
    from service.app import create_app
    from service.connections import guarded_protocol
    from service.registry import ModelRegistry
    from tests.support.demo import make_demo_bundle
    from tests.support.live_server import threaded_server

    from .attack.wire import status_of, wait_closed
    with tempfile.TemporaryDirectory() as tmp:
        bundle = str(make_demo_bundle(Path(tmp) / "demo", name="demo"))
        with threaded_server(create_app(ModelRegistry({"demo": bundle}), token=SECRET),
                             http=guarded_protocol(10.0)) as port:
            t0 = time.monotonic()
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            try:
                s.sendall(f"GET /v2/health/live HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {SECRET}\x00\r\n\r\n"
                          .encode())
                _, got = wait_closed(s, time.monotonic() + 10)
            finally:
                s.close()
    body = got.partition(b"\r\n\r\n")[2].decode("utf-8", "replace")
    echoed = SECRET in body or "Bearer" in body
    return {"case": "E13 Authorization line with a NUL (HTTP)", "exit": status_of(got),
            "seconds": time.monotonic() - t0, "lines": 1, "peak_rss_kib": 0,
            "message": body[:200] + (" (ECHOES THE HEADER)" if echoed else " (no header content)")}


def bench_doors() -> list[dict[str, Any]]:
    """One row per case: exit (or HTTP status), seconds, stderr lines, peak RSS, message."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case, argv, env in _cli_cases(Path(tmp)):
            rows.append({"case": case, **run_cli(["-q", *argv], env=env, timeout=60.0)})
    rows.append(_header_case())
    return rows


def md_doors(rows: list[dict[str, Any]]) -> str:
    lines = ["| case | exit | seconds | stderr lines | peak RSS | message |", "|---|---|---|---|---|---|"]
    for r in rows:
        peak = f"{r['peak_rss_kib'] / 1024:.0f} MiB" if r["peak_rss_kib"] else "(in process)"
        lines.append(f"| {r['case']} | {r['exit']} | {r['seconds']:.1f} | {r['lines']} | {peak} | "
                     f"{r['message'].replace('|', '/')} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(md_doors(bench_doors()))
