"""Hardening, fourth round (issue 42): issue 42's JSON bodies looped against a fresh server,
and its input slots (/dev/zero, a FIFO, a 3 GB sparse file) against the commands that read them.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

from .cli_run import ROOT, run_cli


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


def round4_files(bundle: str) -> list[dict[str, Any]]:
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
                         **run_cli([*render, "--resume", "--out", str(out)])})
            weights = bad(tmp_path / f"w{i}" / "weights.safetensors", kind)
            rows.append({"case": f"NOISESTOP_FEATURE_WEIGHTS as {kind}: evaluate --criterion model",
                         **run_cli([*evaluate, "--model", bundle], {"NOISESTOP_FEATURE_WEIGHTS": str(weights)})})
            for member in ("model.skops", "manifest.json"):
                b = tmp_path / f"b{i}{member}"
                shutil.copytree(bundle, b)
                (b / member).unlink()
                bad(b / member, kind)
                rows.append({"case": f"bundle {member} as {kind}: evaluate --criterion model",
                             **run_cli([*evaluate, "--model", str(b)])})
            if kind != "3 GB sparse":             # a lock file's content is never read past 200 bytes
                out = tmp_path / f"lk{i}"
                bad(out / ".noisestop.lock", kind)
                rows.append({"case": f"output lock file as {kind}: render", **run_cli([*render, "--out", str(out)])})
    return rows
