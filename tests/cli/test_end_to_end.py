"""End to end: the render loop against a live verdict server on loopback."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from tests.support.demo import make_demo_bundle
from tests.support.local_server import LocalServer

RENDER = ["--scene", "cornell", "--resolution", "64", "--grid", "4", "4", "--step", "4", "--min-spp", "4",
          "--max-spp", "32", "--json"]


def render(out, *extra: str, env: dict | None = None) -> dict:
    cmd = [sys.executable, "-m", "service.cli", "render", "--out", str(out), *RENDER, *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})})
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


@pytest.mark.slow
def test_server_criterion_gives_the_in_process_verdicts(tmp_path):
    bundle = make_demo_bundle(tmp_path / "demo", size=16)
    local = render(tmp_path / "local", "--model", str(bundle))
    with LocalServer({"demo": str(bundle)}) as server:
        remote = render(tmp_path / "remote", "--server", server.url,
                        env={"NOISESTOP_TOKEN": server.token})
    strip = [{k: b[k] for k in ("spp", "converged")} | {"history": b.get("history")}
             for b in local["blocks"]]
    assert strip == [{k: b[k] for k in ("spp", "converged")} | {"history": b.get("history")}
                     for b in remote["blocks"]]
    verdicts = {v for b in local["blocks"] for _, v in b["history"]}
    assert len(local["blocks"]) == 16 and verdicts == {-1, 1}, "both verdicts should occur"


@pytest.mark.slow
def test_server_without_token_is_refused_with_a_clear_error(tmp_path):
    bundle = make_demo_bundle(tmp_path / "demo", size=16)
    with LocalServer({"demo": str(bundle)}) as server:
        cmd = [sys.executable, "-m", "service.cli", "render", "--out", str(tmp_path / "r"),
               *RENDER, "--server", server.url]
        env = {k: v for k, v in os.environ.items() if k != "NOISESTOP_TOKEN"}
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "401" in proc.stderr or "unauthorized" in proc.stderr.lower()
