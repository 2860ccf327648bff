"""The service under hostile bodies: JSON depth refused from the bytes, large JSON parsed in a
worker process with a time budget, upload claims ranked and reclaimed, health outside every
layer, SIGHUP during start-up."""
from __future__ import annotations

import json
import random
import signal
import subprocess
import sys

import anyio
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.jsonguard import max_depth
from tests.support.demo import make_demo_bundle, make_request
from service.memory_budget import MemoryBudget
from service.oip import MAX_JSON_DEPTH, ApiError, parse_request
from service.registry import ModelRegistry


def _depth(obj):
    if isinstance(obj, (list, dict)):
        return 1 + max((_depth(v) for v in (obj.values() if isinstance(obj, dict) else obj)), default=0)
    return 0


def test_depth_scan_matches_the_parsed_depth_with_brackets_in_strings(monkeypatch):
    rnd = random.Random(1)

    def gen(d):
        r = rnd.random()
        if d > 6 or r < 0.3:
            return rnd.choice([1, 'a]]\\"[[{', "\\\\", 'x\\\\"]]', None])
        if r < 0.65:
            return [gen(d + 1) for _ in range(rnd.randint(0, 3))]
        return {rnd.choice(["k", "[[", '\\"{']) + str(i): gen(d + 1) for i in range(rnd.randint(0, 3))}

    for chunk in (1, 3, 1 << 20):
        monkeypatch.setattr("service.jsonguard.CHUNK", chunk)
        for _ in range(200):
            obj = gen(0)
            assert max_depth(json.dumps(obj).encode()) == _depth(obj)


def test_json_deeper_than_a_request_needs_is_refused_before_parsing():
    deep = b'{"inputs":[{"name":"features","shape":[1,26],"datatype":"FP32","data":' + b"[" * 20 + b"1" \
        + b"]" * 20 + b"}]}"
    with pytest.raises(ApiError, match=f"nested 23 deep; a request needs at most {MAX_JSON_DEPTH}"):
        parse_request(deep)
    ok = b'{"inputs":[{"name":"x","shape":[1,1,1,1,1,1,1,1],"datatype":"FP32","data":' + b"[" * 8 + b"1" \
        + b"]" * 8 + b"}]}"
    assert parse_request(ok).inputs[0].name == "x"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return str(make_demo_bundle(tmp_path_factory.mktemp("i34") / "demo", name="demo"))


def test_a_large_json_request_is_answered_the_same_through_the_worker(bundle, monkeypatch):
    body, headers = make_request(blocks=2, size=32, binary=False)
    assert len(body) > 4096
    answers = []
    for inline in (1 << 30, 4096):               # in the server's thread, then in a worker
        monkeypatch.setattr("service.infer.INLINE_BYTES", inline)
        app = create_app(ModelRegistry({"demo": bundle}))
        with TestClient(app) as c:
            r = c.post("/v2/models/default/infer", content=body, headers=headers)
            bad = c.post("/v2/models/default/infer", content=body.replace(b'"FP32"', b'"FP99"', 1), headers=headers)
        answers.append((r.status_code, r.json()["outputs"], bad.status_code, bad.json()["error"]))
    assert answers[0] == answers[1] and answers[0][0] == 200 and answers[0][2] == 400


def test_a_parse_over_its_time_budget_is_413_and_the_worker_replaced(bundle, monkeypatch):
    monkeypatch.setattr("service.infer.INLINE_BYTES", 1024)
    app = create_app(ModelRegistry({"demo": bundle}), parse_seconds=0.001)
    body, headers = make_request(blocks=4, size=64, binary=False)
    with TestClient(app) as c:
        r = c.post("/v2/models/default/infer", content=body, headers=headers)
        assert r.status_code == 413 and "took over 0.001 s" in r.json()["error"]
        assert c.get("/v2/health/ready").json() == {"ready": True}


def test_waiting_claims_are_granted_smallest_rank_first():
    async def main():
        budget = MemoryBudget(10, timeout=5)
        assert await budget.acquire(10)
        order = []

        async def claim(n, rank, name):
            assert await budget.acquire(n, rank)
            order.append(name)

        async with anyio.create_task_group() as tg:
            tg.start_soon(claim, 5, 100, "large")
            await anyio.sleep(0.01)
            tg.start_soon(claim, 5, 1, "small")
            await anyio.sleep(0.01)
            budget.release(5)
            await anyio.sleep(0.01)
            budget.release(5)
        return order
    assert anyio.run(main) == ["small", "large"]


def test_a_waiting_claim_asks_holders_to_give_memory_back():
    calls = []

    async def main():
        budget = MemoryBudget(10, timeout=0.3, reclaim=calls.append)
        assert await budget.acquire(10)
        return await budget.acquire(1, rank=7)
    assert anyio.run(main) is False and calls and set(calls) == {7}


def test_sighup_during_start_up_is_logged_and_ends_as_sigterm():
    code = ("import logging, os, signal, time; from service.startup import guard_start_up; guard_start_up(); "
            "os.kill(os.getpid(), signal.SIGHUP); time.sleep(10)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGTERM
    assert "SIGHUP during start-up" in proc.stderr and "Traceback" not in proc.stderr


def test_the_parse_workers_wire_carries_no_pickle():
    """The worker's answer comes back as JSON and raw array bytes: an array round-trips
    (writable, same values); an object dtype or bytes left over are refused, not executed."""
    import json as _json

    import numpy as np

    from service.oip import InferenceRequest
    from service.parsepool import _LEN, decode_answer, encode_answer

    req = InferenceRequest.model_validate({"id": "r", "inputs": [
        {"name": "features", "shape": [2, 26], "datatype": "FP32", "data": [0.0] * 52}]})
    req.inputs[0].data = np.arange(52, dtype=np.float32).reshape(2, 26)
    blob = bytearray(b"".join(bytes(p) for p in encode_answer(("ok", req))))
    kind, back = decode_answer(blob)
    assert kind == "ok" and back.id == "r" and back.inputs[0].data.flags.writeable
    np.testing.assert_array_equal(back.inputs[0].data, req.inputs[0].data)
    assert decode_answer(bytearray(b"".join(bytes(p) for p in encode_answer(("error", 413, "too big", {}))))) == \
        ("error", 413, "too big", {})
    doc = _json.dumps({"request": req.model_dump(exclude={"inputs": {0: {"data"}}}),
                       "arrays": [{"input": 0, "dtype": "|O", "shape": [1]}]}).encode()
    with pytest.raises(ValueError, match="unexpected array type"):
        decode_answer(bytearray(_LEN.pack(len(doc)) + doc + b"\0" * 8))
    with pytest.raises(ValueError, match="left over"):
        decode_answer(blob + b"x")
