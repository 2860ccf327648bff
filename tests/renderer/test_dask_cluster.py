"""Many scenes on an existing Dask cluster, as a farm runs it: a real
`dask scheduler` and `dask worker` processes started and stopped by the test (not a
LocalCluster), `noisestop render --scheduler tcp://...` submitting to them."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from learning.data.exr import read_exr

DASK = shutil.which("dask", path=os.path.dirname(sys.executable)) or shutil.which("dask")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for_workers(address: str, n: int, timeout: float = 90.0) -> None:
    from dask.distributed import Client

    with Client(address, timeout="30s") as client:
        client.wait_for_workers(n, timeout=timeout)


@pytest.fixture()
def cluster(tmp_path):
    """tcp address of a scheduler with two single-thread worker processes; stopped after."""
    if DASK is None:
        pytest.skip("the dask command line is not installed")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    logs = tmp_path / "logs"
    logs.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[2]),
                                                        os.environ.get("PYTHONPATH", "")])}
    procs = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", ":0", "--no-show"],
                              stdout=subprocess.DEVNULL, stderr=open(logs / "scheduler.log", "w"), env=env)]
    try:
        time.sleep(1.0)
        for i in range(2):
            procs.append(subprocess.Popen([DASK, "worker", address, "--nthreads", "1", "--nworkers", "1",
                                           "--name", f"w{i}", "--no-dashboard",
                                           "--local-directory", str(tmp_path / f"w{i}")],
                                          stdout=subprocess.DEVNULL, stderr=open(logs / f"w{i}.log", "w"),
                                          env=env))
        _wait_for_workers(address, 2)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.mark.slow
def test_render_many_scenes_on_real_scheduler_and_workers(cluster, tmp_path):
    out = tmp_path / "farm"
    render = [sys.executable, "-m", "service.cli", "-q", "render"]
    settings = ["--criterion", "variance", "--threshold", "0.3", "--resolution", "32", "--grid", "2", "2",
                "--step", "8", "--min-spp", "8", "--max-spp", "32", "--json"]
    done = subprocess.run([*render, "--scene", "cornell,sky,checker", "--out", str(out), "--scheduler", cluster,
                           *settings], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["failed"] == {} and sorted(summary["scenes"]) == ["checker", "cornell", "sky"]
    for name, report in summary["scenes"].items():
        assert report["resolution"] == [32, 32]
        assert read_exr(out / name / "final.exr").shape == (32, 32, 3)
    # the same scene rendered in this process is the same image: the cluster ran the same code
    local = subprocess.run([*render, "--scene", "cornell", "--out", str(tmp_path / "local"), *settings],
                           capture_output=True, text=True, timeout=600)
    assert local.returncode == 0, local.stderr
    np.testing.assert_array_equal(read_exr(tmp_path / "local" / "final.exr"), read_exr(out / "cornell" / "final.exr"))


@pytest.mark.slow
def test_unreachable_scheduler_is_a_one_line_error(tmp_path):
    port = _free_port()
    done = subprocess.run([sys.executable, "-m", "service.cli", "render", "--scene", "cornell,sky",
                           "--out", str(tmp_path), "--scheduler", f"tcp://127.0.0.1:{port}",
                           "--criterion", "uniform", "--resolution", "16", "--grid", "1", "1",
                           "--max-spp", "4", "--step", "4", "--min-spp", "4"],
                          capture_output=True, text=True, timeout=120)
    lines = [line for line in done.stderr.splitlines() if line.strip() and "%|" not in line]
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "cannot reach Dask scheduler" in lines[-1], done.stderr
