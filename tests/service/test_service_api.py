"""The verdict API in process (FastAPI TestClient): protocol, verdicts, errors, limits, metrics."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from fastapi.testclient import TestClient

from learning.models.bundle import load_model, save_model
from learning.models.estimators import SVM
from noisefeat import extract_features
from service.app import create_app
from service.limits import Limits
from tests.support.demo import make_demo_bundle
from service.registry import ModelRegistry

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MAX_BODY = 200_000
MAX_BATCH = 8


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    root = tmp_path_factory.mktemp("bundles")
    demo = make_demo_bundle(root / "demo", name="dsvm_demo")
    rng = np.random.default_rng(1)
    X = rng.random((60, 16 * 16))
    y = np.where(X.mean(1) > 0.5, 1, -1)
    raw = save_model(SVM().fit(X, y), root / "raw", kind="svm", input="raw", name="svm_raw")
    return {"dsvm_demo": str(demo), "svm_raw": str(raw)}


@pytest.fixture(scope="module")
def client(bundles):
    app = create_app(ModelRegistry(dict(bundles)), token=TOKEN,
                     limits=Limits(max_body_bytes=MAX_BODY, max_batch=MAX_BATCH))
    with TestClient(app) as c:
        yield c


def blocks_pair(n=3, size=16, seed=0):
    rng = np.random.default_rng(seed)
    current = rng.random((n, size, size, 3), dtype=np.float32)
    return current, (0.6 * current + 0.2).astype(np.float32)


def tensor(name, arr, datatype="FP32"):
    return {"name": name, "shape": list(arr.shape), "datatype": datatype, "data": arr.ravel().tolist()}


def infer(client, body, model="default", **kw):
    content = json.dumps(body) if isinstance(body, (dict, list)) else body
    headers = {**AUTH, **kw.pop("headers", {})}
    return client.post(f"/v2/models/{model}/infer", content=content, headers=headers, **kw)


def binary_body(inputs, outputs=None, parameters=None):
    """Request body and headers in the binary tensor extension."""
    head = {"inputs": [{"name": n, "shape": list(a.shape), "datatype": "FP32",
                        "parameters": {"binary_data_size": a.nbytes}} for n, a in inputs]}
    if outputs is not None:
        head["outputs"] = outputs
    if parameters is not None:
        head["parameters"] = parameters
    header = json.dumps(head).encode()
    body = header + b"".join(a.tobytes() for _, a in inputs)
    return body, {"Inference-Header-Content-Length": str(len(header))}


def decode_binary(resp):
    n = int(resp.headers["Inference-Header-Content-Length"])
    head = json.loads(resp.content[:n])
    out, offset = {}, n
    for o in head["outputs"]:
        size = o["parameters"]["binary_data_size"]
        dtype = {"INT8": np.int8, "FP32": np.float32}[o["datatype"]]
        out[o["name"]] = np.frombuffer(resp.content[offset:offset + size], dtype).reshape(o["shape"])
        offset += size
    assert offset == len(resp.content)
    return head, out


def outputs_of(resp):
    assert resp.status_code == 200, resp.text
    return {o["name"]: np.asarray(o["data"]) for o in resp.json()["outputs"]}


# --- health, metadata, auth -------------------------------------------------------------

def test_health_needs_no_token(client):
    assert client.get("/v2/health/live").json() == {"live": True}
    r = client.get("/v2/health/ready")
    assert r.status_code == 200 and r.json() == {"ready": True}


def test_server_metadata_advertises_binary_extension(client):
    r = client.get("/v2", headers=AUTH)
    assert r.status_code == 200
    assert r.json()["name"] == "noisestop" and r.json()["extensions"] == ["binary_tensor_data"]


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN},
                                     {"Authorization": f"Basic {TOKEN}"}])
def test_wrong_or_missing_token_is_one_fixed_401(client, headers):
    for method, path in (("GET", "/v2"), ("GET", "/v2/models/default"), ("POST", "/v2/models/default/infer"),
                         ("GET", "/metrics")):
        r = client.request(method, path, headers=headers)
        assert r.status_code == 401, path
        assert r.json() == {"error": "unauthorized"}
        assert r.headers["www-authenticate"] == "Bearer"


def test_model_metadata_default_alias_and_names(client):
    default = client.get("/v2/models/default", headers=AUTH).json()
    named = client.get("/v2/models/dsvm_demo", headers=AUTH).json()
    assert default["name"] == "default" and named["name"] == "dsvm_demo"
    for meta in (default, named):
        assert meta["platform"] == "noisestop-sklearn" and meta["versions"] == ["1"]
        assert {t["name"]: (t["datatype"], t["shape"]) for t in meta["inputs"]} == {
            "blocks": ("FP32", [-1, -1, -1, 3]), "quick": ("FP32", [-1, -1, -1, 3]),
            "features": ("FP32", [-1, 26])}
        assert {t["name"]: (t["datatype"], t["shape"]) for t in meta["outputs"]} == {
            "verdict": ("INT8", [-1]), "score": ("FP32", [-1])}
        assert meta["parameters"]["quick"] == "albedo"   # which quick image clients must send
    raw = client.get("/v2/models/svm_raw", headers=AUTH).json()
    assert [t["name"] for t in raw["inputs"]] == ["blocks", "quick"] and raw["parameters"]["input"] == "raw"
    assert client.get("/v2/models/dsvm_demo/versions/1", headers=AUTH).status_code == 200
    ready = client.get("/v2/models/svm_raw/versions/1/ready", headers=AUTH)
    assert ready.json() == {"name": "svm_raw", "ready": True}


def test_unknown_model_or_version_is_404(client):
    for path in ("/v2/models/nope", "/v2/models/nope/ready", "/v2/models/dsvm_demo/versions/7"):
        r = client.get(path, headers=AUTH)
        assert r.status_code == 404 and "error" in r.json(), path
    r = infer(client, {"inputs": [tensor("features", np.zeros((1, 26), np.float32))]}, model="nope")
    assert r.status_code == 404 and "dsvm_demo" in r.json()["error"]


def test_repository_index_lists_every_model_and_the_alias(client):
    for method in ("GET", "POST"):
        index = client.request(method, "/v2/repository/index", headers=AUTH).json()
        assert {m["name"] for m in index} == {"default", "dsvm_demo", "svm_raw"}
        assert all(m["state"] == "READY" for m in index)


# --- inference ----------------------------------------------------------------------------

def test_features_input_gives_the_models_verdicts(client, bundles):
    model = load_model(bundles["dsvm_demo"])
    X = np.random.default_rng(3).normal(size=(5, 26)).astype(np.float32)
    r = infer(client, {"id": "req-1", "inputs": [tensor("features", X)]})
    out = outputs_of(r)
    expected = model.decision_function(X)
    assert r.json()["id"] == "req-1" and r.json()["model_name"] == "dsvm_demo"
    np.testing.assert_allclose(out["score"], expected, rtol=1e-5, atol=1e-6)
    assert out["verdict"].tolist() == np.where(expected > model.offset, 1, -1).tolist()
    assert {o["name"]: o["datatype"] for o in r.json()["outputs"]} == {"verdict": "INT8", "score": "FP32"}


def test_blocks_and_quick_match_the_model_api(client, bundles):
    model = load_model(bundles["dsvm_demo"])
    current, quick = blocks_pair()
    out = outputs_of(infer(client, {"inputs": [tensor("blocks", current), tensor("quick", quick)]},
                           model="dsvm_demo"))
    verdict, score = model.score_blocks(current, quick)
    np.testing.assert_allclose(out["score"], score, rtol=1e-4, atol=1e-5)
    assert out["verdict"].tolist() == verdict.tolist()


def test_binary_request_and_response_equal_json(client):
    current, quick = blocks_pair(n=4, seed=5)
    as_json = outputs_of(infer(client, {"inputs": [tensor("blocks", current), tensor("quick", quick)]}))
    body, headers = binary_body([("blocks", current), ("quick", quick)],
                                outputs=[{"name": "verdict", "parameters": {"binary_data": True}},
                                         {"name": "score", "parameters": {"binary_data": True}}])
    r = infer(client, body, headers=headers)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/octet-stream"
    head, out = decode_binary(r)
    assert all("data" not in o for o in head["outputs"])
    assert out["verdict"].tolist() == as_json["verdict"].tolist()
    np.testing.assert_array_equal(out["score"], as_json["score"].astype(np.float32))


def test_binary_input_json_output_and_binary_data_output_flag(client):
    X = np.random.default_rng(4).normal(size=(3, 26)).astype(np.float32)
    body, headers = binary_body([("features", X)])
    r = infer(client, body, headers=headers)
    assert "inference-header-content-length" not in r.headers and len(outputs_of(r)["verdict"]) == 3
    body, headers = binary_body([("features", X)], parameters={"binary_data_output": True})
    _, out = decode_binary(infer(client, body, headers=headers))
    assert set(out) == {"verdict", "score"} and out["verdict"].dtype == np.int8


def test_requested_outputs_are_honoured(client):
    X = np.zeros((2, 26), np.float32)
    r = infer(client, {"inputs": [tensor("features", X)], "outputs": [{"name": "score"}]})
    assert [o["name"] for o in r.json()["outputs"]] == ["score"]


def test_nonfinite_pixels_are_counted_and_read_by_the_display_rule(client):
    current, quick = blocks_pair(n=3, seed=7)
    bad = current.copy()
    bad[0, 0, 0, 0] = np.nan
    bad[0, 1, 1, :] = np.inf
    bad[2, 3, 3, 1] = -np.inf
    quick_bad = quick.copy()
    quick_bad[1, 0, 0, 2] = np.nan
    body, headers = binary_body([("blocks", bad), ("quick", quick_bad)])
    r = infer(client, body, headers=headers)
    assert r.status_code == 200, r.text
    assert r.json()["parameters"] == {"offset": 0.0, "nonfinite_pixels": [2, 0, 1], "nonfinite_quick_pixels": [0, 1, 0]}
    # NaN/-Inf read as black, +Inf as white: the same answer as the cleaned blocks
    clean = np.nan_to_num(bad, nan=0.0, posinf=1.0, neginf=0.0)
    quick_clean = np.nan_to_num(quick_bad, nan=0.0)
    expected = outputs_of(infer(client, {"inputs": [tensor("blocks", clean), tensor("quick", quick_clean)]}))
    np.testing.assert_allclose(outputs_of(r)["score"], expected["score"], rtol=1e-5, atol=1e-6)
    feats = extract_features(quick_clean) - extract_features(clean)
    assert np.isfinite(feats).all()


def test_raw_model_takes_blocks_of_its_size(client, bundles):
    current, quick = blocks_pair(n=2, size=16)
    out = outputs_of(infer(client, {"inputs": [tensor("blocks", current)]}, model="svm_raw"))
    verdict, score = load_model(bundles["svm_raw"]).score_blocks(current)
    assert out["verdict"].tolist() == verdict.tolist()
    with_quick = infer(client, {"inputs": [tensor("blocks", current), tensor("quick", quick)]},
                       model="svm_raw")   # accepted and ignored: one client serves both kinds
    np.testing.assert_allclose(outputs_of(with_quick)["score"], score, rtol=1e-5, atol=1e-6)
    wrong, _ = blocks_pair(n=2, size=24)
    r = infer(client, {"inputs": [tensor("blocks", wrong)]}, model="svm_raw")
    assert r.status_code == 400 and "256 pixels" in r.json()["error"]


def test_exposure_parameter_changes_the_reading(client):
    current, quick = blocks_pair(n=2, seed=9)
    body = {"inputs": [tensor("blocks", current), tensor("quick", quick)]}
    plain = outputs_of(infer(client, body))["score"]
    darker = outputs_of(infer(client, {**body, "parameters": {"exposure": -3}}))["score"]
    assert not np.allclose(plain, darker)


# --- bad input: 4xx with {"error"}, never 500 ---------------------------------------------

def _features(n=2):
    return np.zeros((n, 26), np.float32)


def _bad_requests():
    cur, q = blocks_pair(n=2)
    small, small_q = blocks_pair(n=2, size=4)
    feats = tensor("features", _features())
    return {
        "invalid JSON": b'{"inputs": [',
        "not an object": b"[1, 2, 3]",
        "not utf-8": b'{"inputs": "\xff"}',
        "deep nesting": b"[" * 1000,        # deeper still is over the memory bound: 413 (test_limits)
        "no inputs": {"inputs": []},
        "shape as strings": {"inputs": [{**feats, "shape": ["2", "26"]}]},
        "negative shape": {"inputs": [{**feats, "shape": [-2, 26]}]},
        "wrong features shape": {"inputs": [{**feats, "shape": [1, 52]}]},
        "wrong blocks shape": {"inputs": [{**tensor("blocks", cur.reshape(2, 16, 48)), },
                                          tensor("quick", q)]},
        "wrong datatype": {"inputs": [{**feats, "datatype": "FP64"}]},
        "unknown datatype": {"inputs": [{**feats, "datatype": "BYTES"}]},
        "length mismatch": {"inputs": [{**feats, "data": feats["data"][:-1]}]},
        "ragged data": {"inputs": [{**feats, "shape": [2, 2], "data": [[1, 2], [3]]}]},
        "strings in data": {"inputs": [{**feats, "shape": [1, 2], "data": ["1", "2"]}]},
        "no data": {"inputs": [{k: v for k, v in feats.items() if k != "data"}]},
        "unknown input": {"inputs": [feats, tensor("extra", _features())]},
        "duplicate input": {"inputs": [feats, feats]},
        "features and blocks": {"inputs": [feats, tensor("blocks", cur), tensor("quick", q)]},
        "missing quick": {"inputs": [tensor("blocks", cur)]},
        "quick shape differs": {"inputs": [tensor("blocks", cur), tensor("quick", q[:1])]},
        "blocks smaller than 8x8": {"inputs": [tensor("blocks", small), tensor("quick", small_q)]},
        "NaN features": {"inputs": [{**feats, "shape": [1, 26], "data": [float("nan")] * 26}]},
        "unknown output": {"inputs": [feats], "outputs": [{"name": "probability"}]},
        "binary_data not a bool": {"inputs": [feats],
                                   "outputs": [{"name": "score", "parameters": {"binary_data": 1}}]},
        "exposure a string": {"inputs": [feats], "parameters": {"exposure": "2"}},
        "exposure infinite": {"inputs": [feats], "parameters": {"exposure": float("inf")}},
    }


@pytest.mark.parametrize("case", list(_bad_requests()))
def test_bad_json_requests_are_400_with_an_error(client, case):
    body = _bad_requests()[case]
    r = infer(client, body)
    assert r.status_code == 400, (case, r.text)
    assert set(r.json()) == {"error"} and r.json()["error"]


def test_raw_model_refuses_features(client):
    r = infer(client, {"inputs": [tensor("features", _features())]}, model="svm_raw")
    assert r.status_code == 400 and "features" in r.json()["error"]


def test_binary_framing_errors_are_400(client):
    X = _features(3)
    body, headers = binary_body([("features", X)])
    n = int(headers["Inference-Header-Content-Length"])
    cases = {
        "truncated": (body[:-5], headers),
        "extra bytes": (body + b"\0" * 4, headers),
        "header longer than body": (body, {"Inference-Header-Content-Length": str(len(body) + 1)}),
        "header length not a number": (body, {"Inference-Header-Content-Length": "abc"}),
        "header length zero": (body, {"Inference-Header-Content-Length": "0"}),
        "header cut short": (body, {"Inference-Header-Content-Length": str(n - 3)}),
        "size does not match shape": (body.replace(b'"binary_data_size": 312', b'"binary_data_size": 300'),
                                      headers),
    }
    for name, (content, hdrs) in cases.items():
        r = infer(client, content, headers=hdrs)
        assert r.status_code == 400, (name, r.text)
        assert "error" in r.json(), name
    assert "truncated" in infer(client, body[:-5], headers=headers).json()["error"]


def test_compressed_body_is_415(client):
    r = infer(client, b"\x1f\x8b...", headers={"Content-Encoding": "gzip"})
    assert r.status_code == 415 and "error" in r.json()


# --- limits --------------------------------------------------------------------------------

def test_declared_body_over_the_limit_is_413_before_reading(client):
    r = infer(client, b"x" * (MAX_BODY + 1))
    assert r.status_code == 413
    assert str(MAX_BODY) in r.json()["error"]


def test_streamed_body_over_the_limit_is_413(client):
    def chunks():  # chunked transfer: no Content-Length to check up front
        for _ in range(30):
            yield b"y" * 10_000
    r = infer(client, chunks())
    assert r.status_code == 413 and str(MAX_BODY) in r.json()["error"]


def test_streamed_body_under_the_limit_is_read(client):
    body = json.dumps({"inputs": [tensor("features", _features())]}).encode()
    r = infer(client, iter([body[:10], body[10:]]))
    assert r.status_code == 200 and len(outputs_of(r)["verdict"]) == 2


def test_batch_over_the_limit_is_413_with_the_limit(client):
    X = _features(MAX_BATCH + 1)
    r = infer(client, {"inputs": [tensor("features", X)]})
    assert r.status_code == 413 and f"limit is {MAX_BATCH}" in r.json()["error"]
    assert infer(client, {"inputs": [tensor("features", X[:MAX_BATCH])]}).status_code == 200


# --- metrics and schema --------------------------------------------------------------------

def _sample(text, name, **labels):
    for line in text.splitlines():
        if line.startswith(name + "{") and all(f'{k}="{v}"' in line for k, v in labels.items()):
            return float(line.rsplit(" ", 1)[1])
    return None


def test_metrics_count_blocks_requests_and_load_time(client):
    before = client.get("/metrics", headers=AUTH).text
    X = np.random.default_rng(11).normal(size=(6, 26)).astype(np.float32)
    verdict = outputs_of(infer(client, {"inputs": [tensor("features", X)]}))["verdict"]
    client.get("/v2/health/live")
    text = client.get("/metrics", headers=AUTH).text
    assert text.startswith("# HELP") or "# HELP" in text
    converged = int((verdict > 0).sum())
    for label, n in (("converged", converged), ("noisy", 6 - converged)):
        old = _sample(before, "noisestop_blocks_classified_total", model="dsvm_demo", verdict=label) or 0
        assert _sample(text, "noisestop_blocks_classified_total", model="dsvm_demo", verdict=label) == old + n
    assert _sample(text, "noisestop_model_load_seconds", model="svm_raw") > 0
    assert _sample(text, "http_requests_total", handler="/v2/health/live", method="GET") >= 1
    assert _sample(text, "http_request_duration_seconds_count", handler="/v2/models/{model_name}/infer") >= 1
    assert not re.search(r'http_request_duration_seconds\w*\{[^}]*handler="/v2/health', text)


def test_openapi_documents_errors_and_the_infer_body(client):
    doc = client.get("/openapi.json").json()
    op = doc["paths"]["/v2/models/{model_name}/infer"]["post"]
    for code in ("400", "401", "404", "413"):
        schema = op["responses"][code]["content"]["application/json"]["schema"]
        assert schema["$ref"].endswith("/ErrorResponse")
    ref = op["requestBody"]["content"]["application/json"]["schema"]["$ref"]
    assert ref.rsplit("/", 1)[1] in doc["components"]["schemas"]
    assert "RequestInput" in doc["components"]["schemas"]
    assert "bearer" in json.dumps(doc["components"]["securitySchemes"]).lower()


def test_quick_none_model_needs_no_quick_input(tmp_path):
    from learning.models.estimators import DSVM
    rng = np.random.default_rng(3)
    X = rng.normal(size=(80, 26))
    bundle = save_model(DSVM().fit(X, np.where(X[:, 0] > 0, 1, -1)), tmp_path / "qn", kind="dsvm",
                        input="features", name="dsvm_none", extra={"quick": "none"})
    app = create_app(ModelRegistry({"dsvm_none": str(bundle)}), token=TOKEN)
    current, _ = blocks_pair()
    with TestClient(app) as c:
        out = outputs_of(infer(c, {"inputs": [tensor("blocks", current)]}, model="dsvm_none"))
        assert c.get("/v2/models/dsvm_none", headers=AUTH).json()["parameters"]["quick"] == "none"
    verdict, score = load_model(bundle).score_blocks(current)
    np.testing.assert_allclose(out["score"], score, rtol=1e-4, atol=1e-5)
    assert out["verdict"].tolist() == verdict.tolist()


# --- the one stop rule over HTTP: offset and flat blocks --------------------------------------

def test_verdicts_follow_the_stop_rule_offset_and_flat_blocks(client):
    current, quick = blocks_pair(n=4)
    current[3] = 0.42                                  # a flat block: converged whatever its score
    body, headers = binary_body([("blocks", current), ("quick", quick)])
    r = infer(client, body, headers=headers)
    out = outputs_of(r)
    score = out["score"]
    assert r.json()["parameters"]["offset"] == 0.0 and out["verdict"][3] == 1
    np.testing.assert_array_equal(out["verdict"][:3], np.where(score[:3] > 0.0, 1, -1))
    mid = float(np.sort(score[:3])[:2].mean())          # between two scores: no float32 tie
    for off in (mid, -1e6, 1e6):
        body, headers = binary_body([("blocks", current), ("quick", quick)], parameters={"offset": off})
        r = infer(client, body, headers=headers)
        got = outputs_of(r)
        assert r.json()["parameters"]["offset"] == off
        np.testing.assert_array_equal(got["score"], score)                  # the knob moves verdicts only
        np.testing.assert_array_equal(got["verdict"][:3], np.where(score[:3] > off, 1, -1))
        assert got["verdict"][3] == 1
    # rows of features carry no image: no flat test, the offset still applies
    feats = np.zeros((2, 26), np.float32)
    r = infer(client, {"inputs": [tensor("features", feats)], "parameters": {"offset": 1e6}})
    assert outputs_of(r)["verdict"].tolist() == [-1, -1]


@pytest.mark.parametrize("bad", ["0.5", True, None, 1e400])
def test_a_bad_offset_is_a_400(client, bad):
    current, quick = blocks_pair(n=1)
    body = {"inputs": [tensor("blocks", current), tensor("quick", quick)], "parameters": {"offset": bad}}
    r = infer(client, json.dumps(body).replace("Infinity", "1e400"))
    if bad is None:            # null: as if not given
        assert r.status_code == 200
    else:
        assert r.status_code == 400 and "offset" in r.json()["error"]


def test_serve_offset_overrides_every_model(bundles):
    app = create_app(ModelRegistry(dict(bundles), offset=0.75), token=TOKEN)
    with TestClient(app) as c:
        meta = c.get("/v2/models/dsvm_demo", headers=AUTH).json()["parameters"]
        assert meta["offset"] == 0.75 and meta["calibrated_offset"] == 0.0
        current, quick = blocks_pair(n=2)
        r = infer(c, {"inputs": [tensor("blocks", current), tensor("quick", quick)]})
        out = outputs_of(r)
        assert r.json()["parameters"]["offset"] == 0.75
        np.testing.assert_array_equal(out["verdict"], np.where(out["score"] > 0.75, 1, -1))
    with pytest.raises(ValueError, match="finite"):
        ModelRegistry(dict(bundles), offset=float("nan"))


# --- the noise target over HTTP ---------------------------------------------------------------

def test_tau_picks_the_models_offset_for_that_noise_target(tmp_path, bundles):
    est = load_model(bundles["dsvm_demo"]).estimator
    curve = [{"tau": 0.01, "offset": 0.5}, {"tau": 0.02, "offset": 0.0}, {"tau": 0.04, "offset": -0.5}]
    bundle = save_model(est, tmp_path / "curve", kind="dsvm", input="features", name="curve",
                        training={"tau": 0.02, "calibration": {"offsets_by_tau": curve}})
    app = create_app(ModelRegistry({"curve": str(bundle), "demo": bundles["dsvm_demo"]}), token=TOKEN)
    feats = np.zeros((1, 26), np.float32)
    with TestClient(app) as c:
        for tau, want in ((0.01, 0.5), (0.04, -0.5), (0.02 * 2 ** 0.5, -0.25)):    # log-linear between points
            r = infer(c, {"inputs": [tensor("features", feats)], "parameters": {"tau": tau}}, model="curve")
            assert r.status_code == 200 and r.json()["parameters"]["offset"] == pytest.approx(want)
            assert r.json()["parameters"]["tau"] == tau
        r = infer(c, {"inputs": [tensor("features", feats)], "parameters": {"tau": 0.01, "offset": 2.0}},
                  model="curve")
        assert r.json()["parameters"]["offset"] == 2.0                   # an explicit offset wins
        assert c.get("/v2/models/curve", headers=AUTH).json()["parameters"]["tau_range"] == [0.01, 0.04]
        for bad, where in ((0.2, "curve"), (0.005, "curve"), (0.04, "demo")):
            r = infer(c, {"inputs": [tensor("features", feats)], "parameters": {"tau": bad}}, model=where)
            assert r.status_code == 400 and "outside" in r.json()["error"]
        for bad in ("0.02", True, -0.01, 1e400):
            body = json.dumps({"inputs": [tensor("features", feats)], "parameters": {"tau": bad}})
            r = infer(c, body.replace("Infinity", "1e400"), model="curve")
            assert r.status_code == 400 and "tau" in r.json()["error"]
        body = json.dumps({"inputs": [tensor("features", feats)]})[:-1] + ', "parameters": {"tau": NaN}}'
        assert infer(c, body, model="curve").status_code == 400


def test_serve_tau_sets_every_models_default_and_refuses_an_uncalibrated_one(bundles):
    with pytest.raises(ValueError, match="outside"):
        ModelRegistry({"demo": bundles["dsvm_demo"]}, tau=0.04).load()
    reg = ModelRegistry({"demo": bundles["dsvm_demo"]}, tau=0.02)
    reg.load()
    assert reg.get("demo").effective_offset == load_model(bundles["dsvm_demo"]).offset
