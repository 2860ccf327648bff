"""The service's performance paths, by what they must do (no timings here; BENCHMARKS.md has those):
binary tensors used in place, one fused feature call per request, a lean server process,
large bodies through the guarded h11 protocol, and the heap trimmed only when much is free."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

import service.body as body_module
import service.infer as infer_module
from learning.models.bundle import load_model
from noisefeat.extract import analyse_blocks
from service import heap
from service.connections import H11_PIECE, guarded_protocol
from benchmarks.loadtest import run_load
from tests.support.demo import make_demo_bundle, make_request
from service.oip import HEADER_LENGTH
from tests.support.live_server import threaded_server
from service.serve import build

TOKEN = "perf-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> str:
    return str(make_demo_bundle(tmp_path_factory.mktemp("perf") / "demo", name="demo"))


def _binary_request(blocks: np.ndarray, quick: np.ndarray, pad: int) -> tuple[bytes, dict[str, str]]:
    """A binary infer request whose JSON header is padded with `pad` spaces (any length)."""
    inputs = [{"name": n, "shape": list(a.shape), "datatype": "FP32", "parameters": {"binary_data_size": a.nbytes}}
              for n, a in (("blocks", blocks), ("quick", quick))]
    header = json.dumps({"inputs": inputs}).encode() + b" " * pad
    return header + blocks.tobytes() + quick.tobytes(), {HEADER_LENGTH: str(len(header)), **AUTH,
                                                         "Content-Type": "application/octet-stream"}


def test_binary_tensors_are_views_of_the_body_whatever_the_header_length(bundle, monkeypatch):
    seen = []
    decode = infer_module.decode_tensors

    def spy(req, binary, *args, **kwargs):
        tensors = decode(req, binary, *args, **kwargs)
        seen.append((np.frombuffer(binary, np.uint8), tensors))
        return tensors
    monkeypatch.setattr(infer_module, "decode_tensors", spy)
    rng = np.random.default_rng(0)
    blocks = rng.random((3, 16, 16, 3), dtype=np.float32)
    quick = (0.5 * blocks + 0.2).astype(np.float32)
    answers = []
    with TestClient(build({"demo": bundle}, token=TOKEN)) as client:
        for pad in range(4):                      # header lengths with every remainder mod 4
            body, headers = _binary_request(blocks, quick, pad)
            r = client.post("/v2/models/demo/infer", content=body, headers=headers)
            assert r.status_code == 200, r.text
            answers.append(r.json()["outputs"])
    assert len(seen) == 4 and answers.count(answers[0]) == 4
    for raw, tensors in seen:
        for name, want in (("blocks", blocks), ("quick", quick)):
            arr = tensors[name]
            assert np.shares_memory(arr, raw), name            # no copy: a view of the body
            assert arr.flags.writeable and arr.ctypes.data % 4 == 0
            np.testing.assert_array_equal(arr, want)
        assert tensors["blocks"].ctypes.data % body_module.TENSOR_ALIGNMENT == 0


def test_one_fused_call_per_request_for_blocks_and_quick(bundle, monkeypatch):
    """A feature model's request: blocks and quick images go through noisefeat in one
    call (one spectral pass for both), and the verdicts equal the per-image computation."""
    import learning.models.model as bundle_module
    calls = []
    many = bundle_module.analyse_many

    def spy(batches, **kwargs):
        calls.append([np.shape(b) for b in batches])
        return many(batches, **kwargs)
    monkeypatch.setattr(bundle_module, "analyse_many", spy)
    model = load_model(bundle)
    rng = np.random.default_rng(1)
    blocks = rng.random((5, 32, 32, 3), dtype=np.float32)
    quick = (0.5 * blocks + 0.2).astype(np.float32)
    blocks[2] = 0.3                                          # a flat block
    verdict, score, counts = model.assess_blocks(blocks, quick)
    assert calls == [[(5, 32, 32, 3), (5, 32, 32, 3)]]
    x = analyse_blocks(quick)[0] - analyse_blocks(blocks)[0]
    np.testing.assert_allclose(score, model.decision_function(x), rtol=1e-6, atol=1e-6)
    assert verdict[2] == 1 and counts["blocks"].tolist() == [0] * 5 and counts["quick"].tolist() == [0] * 5


def test_server_process_imports_no_mitsuba_or_matplotlib(bundle):
    """What `noisestop serve` loads: the command line, the app, a feature model and the
    bundled (half-buffer, FLIP) model, one request to each; none of it imports Mitsuba,
    Dr.Jit or matplotlib, nor any room of the renderer but its names, settings, token rule and OIP codec."""
    code = f"""
import json, sys
import service.cli, service.commands
from fastapi.testclient import TestClient
from tests.support.demo import make_request
from service.serve import build
for spec, inputs in (({{"m": {bundle!r}}}, "blocks"), ({{"m": None}}, "halves")):
    with TestClient(build(spec, token="t" * 24)) as c:
        body, headers = make_request(2, 16, binary=True, inputs=inputs)
        r = c.post("/v2/models/m/infer", content=body, headers={{**headers, "Authorization": "Bearer " + "t" * 24}})
        assert r.status_code == 200, r.text
print(json.dumps(sorted(sys.modules)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    modules = set(json.loads(out.stdout.strip().splitlines()[-1]))
    loaded = {m.split(".")[0] for m in modules}
    assert {"torch", "sklearn", "fastapi", "noisefeat", "learning", "service"} <= loaded
    # (dask is left out: where installed, skops' scan of scikit-learn's estimators imports it
    # through sklearn's array-API shim; tests/cli/test_install_parts.py serves without it)
    optional = {"mitsuba", "drjit", "matplotlib", "flip_evaluator", "torchvision"}
    assert not loaded & optional, loaded & optional
    # of the renderer, only the rooms the command line reads (the render spec, and the
    # criteria's declarations: its choices; none imports torch or Mitsuba when loaded), the
    # token rule and the OIP codec the client shares with the server live in
    light = {"renderer", "renderer.spec", "renderer.settings", "renderer.setting_kinds", "renderer.client",
             "renderer.client.token", "renderer.client.oip_codec", "renderer.criteria"}
    assert {m for m in modules if m.split(".")[0] == "renderer" and not m.startswith("renderer.criteria.")} <= light


def test_large_binary_bodies_through_the_guarded_protocol(bundle):
    """16 blocks of 128x128 with their quick images (6.3 MB, far more than one H11_PIECE)
    over a real socket and the header-deadline protocol: every answer complete and right."""
    with threaded_server(build({"demo": bundle}, token=TOKEN), http=guarded_protocol(10.0)) as port:
        body, _ = make_request(16, 128, binary=True)
        assert len(body) > 20 * H11_PIECE
        r = run_load(f"http://127.0.0.1:{port}", token=TOKEN, model="demo", clients=2, requests_per_client=2,
                     blocks=16, size=128, binary=True, max_seconds=120)
        assert r["requests"] == 4 and r["errors"] == 0, r


def test_heap_is_trimmed_only_when_much_of_it_is_free(monkeypatch):
    trimmed = []

    class Info:
        fordblks = 0

    monkeypatch.setattr(heap, "_libc", lambda: (trimmed.append, lambda: Info))
    Info.fordblks = heap.RELEASE_ABOVE // 2
    assert heap.release_memory() is False and trimmed == []
    Info.fordblks = heap.RELEASE_ABOVE * 2
    assert heap.release_memory() is True and trimmed == [0]
    monkeypatch.setattr(heap, "_libc", lambda: (trimmed.append, None))     # no mallinfo2: as before
    assert heap.release_memory() is True and trimmed == [0, 0]
    monkeypatch.setattr(heap, "_libc", lambda: (None, None))               # not glibc
    assert heap.release_memory() is False


def test_service_bench_merges_rounds_and_writes_every_figure(bundle):
    """The bench's bookkeeping (no timing asserted): rounds merge cell by cell into medians
    with every round's p99 kept, errors summed; the markdown carries each figure; the
    stage breakdown of one request names each stage."""
    from benchmarks.bench_service import _merge, md_service, stage_times

    def run(p99, errors):
        return {"clients": 8, "encoding": "binary", "requests": 10, "errors": errors, "requests_per_s": 40.0,
                "p50_ms": p99 / 2, "p99_ms": p99, "other_load": 0.5,
                "server_cpu_ms": {"event loop": 10.0, "inference": p99 / 10}}
    merged = _merge([{"ready_s": 4.0, "runs": [run(p, e)]} for p, e in ((300.0, 0), (100.0, 1), (200.0, 0))])
    cell = merged["runs"][0]
    assert cell["p99_ms"] == 200.0 and cell["p99_rounds"] == [300.0, 100.0, 200.0]
    assert cell["errors"] == 1 and cell["requests"] == 30 and cell["server_cpu_ms"]["inference"] == 20.0
    stages = stage_times(bundle, repeats=1)
    assert {"decode_ms", "features_ms", "flip_ms", "svm_ms", "encode_ms", "in_process_ms"} <= set(stages)
    assert stages["flip_ms"] == 0.0 and stages["features_ms"] > 0 and stages["request_mb"] > 6
    text = md_service({"cpus": 2, "blocks": 16, "size": 128, "repeats": 3,
                       "models": {"demo": {"stages": stages, **merged}}})
    assert "| 8 | binary | 30 | 40.0 | 100 | 200 (300, 100, 200) | 1 | 10.0 / 20.0 | 50 % |" in text
    assert "medians of 3 rounds" in text and "FLIP 0.0 ms" in text
