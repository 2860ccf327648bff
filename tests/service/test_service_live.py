"""The verdict service over real sockets: tritonclient, schemathesis, concurrency, SIGTERM drain.

Clients nobody here wrote: tritonclient.http (Triton's own client) and schemathesis (which
derives its requests from our /openapi.json and checks every answer against it).
"""
from __future__ import annotations

import http.client
import json
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import schemathesis
from schemathesis import GenerationMode
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, negative_data_rejection,
                                               response_headers_conformance,
                                               response_schema_conformance, status_code_conformance)

from benchmarks.loadtest import run_load
from tests.support.demo import make_demo_bundle, make_request
from tests.support.local_server import LocalServer
from tests.support.live_server import threaded_server
from service.serve import build

TOKEN = "live-test-token-abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return str(make_demo_bundle(tmp_path_factory.mktemp("live") / "demo", name="dsvm_live"))


@pytest.fixture(scope="module")
def live_url(bundle):
    """uvicorn on 127.0.0.1:<free port> in a thread, with a token and small limits."""
    app = build({"dsvm_live": bundle}, "127.0.0.1", token=TOKEN, max_body_bytes=4_000_000, max_batch=64)
    with threaded_server(app) as port:
        yield f"127.0.0.1:{port}"


def _blocks(n=3, size=32, seed=0):
    rng = np.random.default_rng(seed)
    current = rng.random((n, size, size, 3), dtype=np.float32)
    return current, (0.5 * current + 0.25).astype(np.float32)


# --- tritonclient ----------------------------------------------------------------------------

def test_tritonclient_metadata_and_readiness(live_url):
    import tritonclient.http as httpclient
    client = httpclient.InferenceServerClient(url=live_url)
    try:
        assert client.is_server_live() and client.is_server_ready()
        meta = client.get_server_metadata(headers=AUTH)
        assert meta["name"] == "noisestop" and "binary_tensor_data" in meta["extensions"]
        assert client.is_model_ready("default", headers=AUTH)
        assert client.is_model_ready("dsvm_live", model_version="1", headers=AUTH)
        assert not client.is_model_ready("missing", headers=AUTH)
        model = client.get_model_metadata("default", headers=AUTH)
        assert {i["name"] for i in model["inputs"]} == {"blocks", "quick", "features"}
        index = client.get_model_repository_index(headers=AUTH)
        assert {m["name"] for m in index} >= {"default", "dsvm_live"}
    finally:
        client.close()


def _triton_infer(client, current, quick, binary):
    import tritonclient.http as httpclient
    inputs = []
    for name, arr in (("blocks", current), ("quick", quick)):
        t = httpclient.InferInput(name, list(arr.shape), "FP32")
        t.set_data_from_numpy(arr, binary_data=binary)
        inputs.append(t)
    outputs = [httpclient.InferRequestedOutput(n, binary_data=binary) for n in ("verdict", "score")]
    # a copy: tritonclient writes Inference-Header-Content-Length into the dict it is given
    result = client.infer("default", inputs, outputs=outputs, headers=dict(AUTH))
    return result.as_numpy("verdict"), result.as_numpy("score"), result.get_response()


def test_tritonclient_infer_json_and_binary_agree(live_url, bundle):
    import tritonclient.http as httpclient
    from learning.models.bundle import load_model
    current, quick = _blocks()
    client = httpclient.InferenceServerClient(url=live_url)
    try:
        v_json, s_json, resp = _triton_infer(client, current, quick, binary=False)
        v_bin, s_bin, _ = _triton_infer(client, current, quick, binary=True)
    finally:
        client.close()
    expected_v, expected_s = load_model(bundle).score_blocks(current, quick)
    assert v_bin.dtype == np.int8 and s_bin.dtype == np.float32 and v_bin.shape == (3,)
    assert v_json.tolist() == v_bin.tolist() == expected_v.tolist()
    np.testing.assert_allclose(s_bin, expected_s, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(s_json, s_bin, rtol=1e-6)
    assert resp["model_name"] == "dsvm_live"


def test_tritonclient_sees_errors_as_exceptions(live_url):
    import tritonclient.http as httpclient
    from tritonclient.utils import InferenceServerException
    client = httpclient.InferenceServerClient(url=live_url)
    try:
        t = httpclient.InferInput("blocks", [1, 4, 4, 3], "FP32")
        t.set_data_from_numpy(np.zeros((1, 4, 4, 3), np.float32))
        q = httpclient.InferInput("quick", [1, 4, 4, 3], "FP32")
        q.set_data_from_numpy(np.zeros((1, 4, 4, 3), np.float32))
        with pytest.raises(InferenceServerException, match="8x8"):
            client.infer("default", [t, q], headers=dict(AUTH))
        with pytest.raises(InferenceServerException, match="unauthorized"):
            client.get_server_metadata()
    finally:
        client.close()


# --- schemathesis against /openapi.json -----------------------------------------------------

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance, negative_data_rejection]


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_openapi_conformance_and_no_server_errors(live_url, mode):
    """Every operation of /openapi.json, schema-valid and schema-invalid requests alike: no
    5xx, documented status codes and content types, bodies that match their schemas, and
    schema-invalid requests rejected."""
    api = schemathesis.openapi.from_url(f"http://{live_url}/openapi.json")
    operations = [result.ok() for result in api.get_all_operations()]
    assert len(operations) >= 12
    for operation in operations:
        if mode is GenerationMode.NEGATIVE and operation.path.startswith("/v2/health"):
            continue  # no parameters, no token: nothing there can be made invalid
        # real model names, so that requests reach the decoder, not only the 404
        known = {k: v for k, v in (("model_name", "dsvm_live"), ("model_version", "1"))
                 if k in {p.name for p in operation.path_parameters}}

        @settings(max_examples=30, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy(generation_mode=mode, path_parameters=known or None))
        def check(case):
            case.call_and_validate(headers=AUTH, timeout=60, checks=CHECKS)

        check()


# --- concurrency and load -------------------------------------------------------------------

def _post(url, body, headers):
    host, port = url.split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=60)
    try:
        conn.request("POST", "/v2/models/default/infer", body=body, headers={**AUTH, **headers})
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def test_concurrent_requests_get_their_own_answers(live_url):
    def one(seed):
        current, quick = _blocks(n=2, size=32, seed=seed)
        body = json.dumps({"inputs": [
            {"name": n, "shape": list(a.shape), "datatype": "FP32", "data": a.ravel().tolist()}
            for n, a in (("blocks", current), ("quick", quick))]})
        status, data = _post(live_url, body, {"Content-Type": "application/json"})
        assert status == 200, data
        return json.loads(data)["outputs"][1]["data"]

    serial = [one(s) for s in range(6)]
    with ThreadPoolExecutor(6) as pool:
        parallel = list(pool.map(one, range(6)))
    assert parallel == serial
    assert len({tuple(s) for s in serial}) == 6  # different inputs, different scores


def test_load_test_runs_both_encodings(live_url):
    for binary in (False, True):
        r = run_load(f"http://{live_url}", token=TOKEN, clients=2, requests_per_client=2, blocks=2,
                     size=32, binary=binary, max_seconds=60)
        assert r["requests"] == 4 and r["errors"] == 0, r
        assert r["inputs"] == ["blocks", "quick"]          # what the served (quick-image) model reads
        assert r["p50_ms"] > 0 and r["p99_ms"] >= r["p50_ms"] and r["blocks_per_s"] > 0
    with pytest.raises(ValueError, match="loopback"):
        run_load("http://example.org:80", clients=1, requests_per_client=1)


# --- graceful shutdown ----------------------------------------------------------------------

def test_sigterm_drains_the_request_in_flight(bundle):
    body, headers = make_request(blocks=4, size=64, binary=True, seed=3)
    with LocalServer({"dsvm_live": bundle}) as server:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
        conn.putrequest("POST", "/v2/models/default/infer")
        for k, v in {**headers, "Authorization": f"Bearer {server.token}",
                     "Content-Length": str(len(body))}.items():
            conn.putheader(k, v)
        conn.endheaders()
        half = len(body) // 2
        conn.send(body[:half])                 # the request is now in flight
        time.sleep(0.3)
        server.process.send_signal(15)         # SIGTERM
        # no new connections while draining: polled (a busy machine takes its time to stop
        # listening), the server alive all along with the request in flight
        deadline, refused = time.monotonic() + 60, False
        while not refused and time.monotonic() < deadline:
            assert server.process.poll() is None, "server exited with a request in flight"
            probe = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
            try:
                probe.request("GET", "/v2/health/live")
                probe.getresponse().read()
                time.sleep(0.1)
            except OSError:
                refused = True
            finally:
                probe.close()
        assert refused and server.process.poll() is None
        conn.send(body[half:])
        resp = conn.getresponse()
        data = resp.read()
        assert resp.status == 200, data
        n = int(resp.getheader("Inference-Header-Content-Length"))
        head = json.loads(data[:n])
        assert [o["shape"] for o in head["outputs"]] == [[4], [4]]
        # uvicorn re-raises the signal once it has shut down cleanly, hence -SIGTERM
        assert server.process.wait(30) in (0, -15)
        assert "Finished server process" in server.log(), server.log()
