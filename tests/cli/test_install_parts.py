"""`pip install 'noisestop[serve]'` in a fresh virtual environment: the wheel built from this
tree, torch first (as the Makefile installs it), then the core and the [serve] extra only.
There Mitsuba, Dr.Jit, Dask, matplotlib, flip-evaluator and torchvision are absent,
`noisestop serve` (the bundled model, a token) gives verdicts over HTTP, and a command that
needs another extra says which in one line. pip's cache is reused; the first run downloads
the serve stack (a few minutes)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from tests.support import ROOT

TOKEN = "install-parts-test-token"
ABSENT = ("mitsuba", "drjit", "dask", "distributed", "matplotlib", "flip_evaluator", "torchvision")
#: what the Makefile installs first (its TORCH_SPEC); CI may point it elsewhere
TORCH_SPEC = os.environ.get("TORCH_SPEC", "torch==2.13.0")


def _run(*cmd: str, timeout: float = 900, **kw) -> subprocess.CompletedProcess:
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)
    assert out.returncode == 0, f"{' '.join(cmd)}\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out


def _source_copy(dest: Path) -> Path:
    """The files a wheel is built from, copied (building in place would leave build/ here)."""
    skip = shutil.ignore_patterns("__pycache__", "*.pyc", ".cache", "*.egg-info")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, dest / name)
    for pkg in ("noisefeat", "learning", "renderer", "service"):
        shutil.copytree(ROOT / pkg, dest / pkg, ignore=skip)
    return dest


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, path: str) -> dict:
    req = urllib.request.Request(url + path, headers={"Authorization": f"Bearer {TOKEN}"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read())


def _infer(url: str, inputs: dict[str, np.ndarray]) -> dict:
    body = {"inputs": [{"name": k, "datatype": "FP32", "shape": list(v.shape), "data": v.ravel().tolist()}
                       for k, v in inputs.items()]}
    req = urllib.request.Request(url + "/v2/models/default/infer", data=json.dumps(body).encode(),
                                 headers={"Authorization": f"Bearer {TOKEN}",
                                          "Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.loads(r.read())


def _request_for(model: dict) -> dict[str, np.ndarray]:
    """Two 32x32 blocks in the input the served model takes: a flat one and a noisy one."""
    names = {i["name"] for i in model["inputs"]}
    rng = np.random.default_rng(0)
    flat = np.full((32, 32, 3), 0.3, np.float32)
    noisy = (0.3 + 0.2 * rng.standard_normal((32, 32, 3))).clip(0, None).astype(np.float32)
    current = np.stack([flat, noisy])
    if {"even", "odd"} <= names:
        other = (0.3 + 0.2 * rng.standard_normal((32, 32, 3))).clip(0, None).astype(np.float32)
        return {"even": current, "odd": np.stack([flat, other])}
    return {"blocks": current, "quick": np.full_like(current, 0.3)}


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_serve_extra_alone_in_a_fresh_virtual_environment(tmp_path):
    t0 = time.monotonic()
    src = tmp_path / "src"
    src.mkdir()
    _source_copy(src)
    wheels = tmp_path / "wheels"
    _run(sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src))
    (wheel,) = wheels.glob("noisestop-*.whl")
    t_wheel = time.monotonic() - t0

    venv = tmp_path / "venv"
    _run(sys.executable, "-m", "venv", str(venv))
    py, pip = venv / "bin" / "python", [str(venv / "bin" / "python"), "-m", "pip", "install", "-q"]
    _run(*pip, TORCH_SPEC, timeout=1800)
    _run(*pip, f"{wheel}[serve]", timeout=1800)
    t_install = time.monotonic() - t0 - t_wheel

    # the optional packages of the other extras are absent; the core and [serve] import
    probe = ("import importlib.util as u, json; print(json.dumps([m for m in %r if u.find_spec(m)]))" % (ABSENT,))
    assert json.loads(_run(str(py), "-c", probe).stdout) == []
    _run(str(py), "-c", "import OpenEXR, PIL, fastapi, uvicorn, h11, prometheus_fastapi_instrumentator, "
                        "learning.data.exr, service.serve")

    # another extra's command: one line naming it, exit 2
    noisestop = str(venv / "bin" / "noisestop")
    out = subprocess.run([noisestop, "render", "--scene", "cornell", "--out", str(tmp_path / "r"),
                          "--criterion", "uniform"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr.strip().splitlines()[-1].endswith("pip install 'noisestop[render]'"), out.stderr

    # the service: bundled model, token, verdicts over HTTP
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NOISESTOP_", "PYTHONPATH"))}
    env["NOISESTOP_TOKEN"] = TOKEN
    server = subprocess.Popen([noisestop, "serve", "--host", "127.0.0.1", "--port", str(port)], cwd=tmp_path,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            assert server.poll() is None, server.stdout.read()
            assert time.monotonic() < deadline, "the service did not become ready"
            try:
                with urllib.request.urlopen(url + "/v2/health/ready", timeout=5) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError):
                time.sleep(0.5)
        with pytest.raises(urllib.error.HTTPError) as refused:   # the token is required
            urllib.request.urlopen(url + "/v2/models/default", timeout=30)
        assert refused.value.code == 401
        answer = _infer(url, _request_for(_get(url, "/v2/models/default")))
        outputs = {o["name"]: o for o in answer["outputs"]}
        assert outputs["verdict"]["shape"] == [2] and set(outputs["verdict"]["data"]) <= {-1, 1}
        assert outputs["verdict"]["data"][0] == 1                 # the flat block stops at once
        assert all(np.isfinite(outputs["score"]["data"]))
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait(10)
    size_mb = sum(f.stat().st_size for f in venv.rglob("*") if f.is_file()) / 2**20
    print(f"\nwheel {t_wheel:.0f} s, installs {t_install:.0f} s, total {time.monotonic() - t0:.0f} s, "
          f"[serve] venv {size_mb:.0f} MiB")
