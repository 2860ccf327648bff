"""The service's hardening: memory bounded from the body before parsing,
slow uploaders cut off without denying service, duplicate JSON keys, JSON bodies for the
HTTP layer's 400s, /openapi.json, out-of-memory answers, SIGHUP. The scenarios on real
sockets are benchmarks.attack's, the ones `noisestop bench reliability` reports."""
from __future__ import annotations

import json
import signal
import socket
import threading
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service import infer as infer_mod
from service.app import create_app
from service.connections import guarded_protocol
from benchmarks import attack
from tests.support.demo import make_demo_bundle, make_request
from tests.support.local_server import LocalServer
from service.limits import Limits
from service.memory_cost import decode_cost, json_cost, request_cost
from service.upload_policy import UploadPolicy
from service.registry import ModelRegistry
from tests.support.live_server import threaded_server

TOKEN = "hardening-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MAX_BODY = 1 << 20


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return str(make_demo_bundle(tmp_path_factory.mktemp("h") / "demo", name="demo"))


@pytest.fixture(scope="module")
def client(bundle):
    app = create_app(ModelRegistry({"demo": bundle}), token=TOKEN, limits=Limits(max_body_bytes=MAX_BODY))
    with TestClient(app) as c:
        yield c


def _features(n=2):
    return {"name": "features", "shape": [n, 26], "datatype": "FP32",
            "data": np.random.default_rng(0).random(n * 26).round(4).tolist()}


def _post(client, content):
    return client.post("/v2/models/default/infer", content=content, headers=AUTH)


# --- memory bounded before parsing ---------------------------------------------------------------

def test_nested_json_over_the_budget_is_413_without_being_parsed(client, monkeypatch):
    """The 62 MiB nested shape (every value in 20 nested lists), scaled to this server's budget:
    its cost estimate (a byte count) is over the budget, so it is refused unparsed."""
    parsed = []
    monkeypatch.setattr(infer_mod, "parse_request", lambda head: parsed.append(1))
    budget = client.app.state.memory_budget.total
    unit = b"[" * 20 + b"1" + b"]" * 20
    n = (MAX_BODY - 200) // (len(unit) + 1)
    body = b'{"inputs":[{"name":"features","shape":[%d],"datatype":"FP32","data":[' % n \
        + b",".join([unit] * n) + b"]}]}"
    assert len(body) <= MAX_BODY < budget / 16 + 1 and json_cost(body) > budget
    r = _post(client, body)
    assert r.status_code == 413 and "working memory" in r.json()["error"], r.text
    assert parsed == []
    assert client.get("/v2/health/ready").status_code == 200


def test_the_same_values_flat_are_served(client):
    """Not a size rule: the same number of values without the nesting fits and is answered."""
    body = json.dumps({"inputs": [_features(400)]}).encode()
    assert len(body) <= MAX_BODY and json_cost(body) + len(body) < client.app.state.memory_budget.total
    assert _post(client, body).status_code == 200


def test_binary_cost_is_the_documented_factor():
    head = b'{"inputs": []}'
    body = head + b"\0" * 1000
    assert decode_cost(body, len(head)) == decode_cost(head, None) + 15 * 1000
    assert decode_cost(head, None) == json_cost(head) + (1 << 20)
    assert request_cost(1000) == 16 * 1000 + (1 << 20)


# --- duplicate keys ----------------------------------------------------------------------------------

DUPLICATES = {
    "exposure twice": '{"inputs": [%s], "parameters": {"exposure": 1e30, "exposure": 0}}',
    "inputs twice": '{"inputs": [], "inputs": [%s]}',
    "datatype twice in a tensor": '{"inputs": [%s]}',
    "key twice in an output's parameters": '{"inputs": [%s], "outputs": [{"name": "score", '
                                           '"parameters": {"binary_data": false, "binary_data": false}}]}',
}


@pytest.mark.parametrize("case", list(DUPLICATES))
def test_a_key_twice_in_one_object_is_400(client, case):
    t = json.dumps(_features())
    if case == "datatype twice in a tensor":
        t = t[:-1] + ', "datatype": "FP64"}'
    r = _post(client, DUPLICATES[case] % t)
    assert r.status_code == 400 and "appears twice" in r.json()["error"], r.text


def test_colons_in_strings_are_not_taken_for_duplicates(client):
    body = {"id": "a:b::c", "inputs": [_features()], "parameters": {"note:x": "y:z", "exposure": 0}}
    r = _post(client, json.dumps(body))
    assert r.status_code == 200 and r.json()["id"] == "a:b::c", r.text
    escaped = json.dumps(body).replace("a:b", "a\\u003ab")          # a colon the text does not show
    assert _post(client, escaped).status_code == 200


# --- /openapi.json, out of memory ------------------------------------------------------------------

def test_openapi_is_open_and_names_no_model(client):
    """Decision (docs/guide/serving.md): the API's description is public, as the protocol is; it holds
    no model name, token or setting of this server."""
    r = client.get("/openapi.json")
    assert r.status_code == 200
    text = r.text
    assert "demo" not in text and TOKEN not in text and "/v2/models/{model_name}/infer" in text
    assert client.get("/v2/models/demo").status_code == 401         # the models themselves are not


def test_out_of_memory_is_503_logged_and_the_server_serves_on(client, monkeypatch, caplog):
    served = client.app.state.registry.get("default")
    real = type(served).infer
    calls = []

    def exhausted(self, *a, **k):
        calls.append(1)
        if len(calls) == 1:
            raise MemoryError()
        return real(self, *a, **k)
    monkeypatch.setattr(type(served), "infer", exhausted)
    body = json.dumps({"inputs": [_features()]})
    r = _post(client, body)
    assert r.status_code == 503 and "out of memory" in r.json()["error"] and r.headers["retry-after"] == "1"
    assert any("out of memory" in rec.message for rec in caplog.records)
    assert _post(client, body).status_code == 200
    assert client.app.state.memory_budget.used == client.app.state.upload_budget.used == 0   # all given back


def test_out_of_memory_while_a_body_arrives_is_503_too(client, monkeypatch, caplog):
    def exhausted(*a, **k):
        raise MemoryError()
    monkeypatch.setattr(infer_mod, "read_body", exhausted)
    r = _post(client, json.dumps({"inputs": [_features()]}))
    assert r.status_code == 503 and "out of memory" in r.json()["error"], r.text
    assert not any("Traceback" in (rec.exc_text or "") for rec in caplog.records)
    monkeypatch.undo()
    assert _post(client, json.dumps({"inputs": [_features()]})).status_code == 200


# --- the HTTP layer's own 400s -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def socket_server(bundle):
    app = create_app(ModelRegistry({"demo": bundle}), token=TOKEN,
                     limits=Limits(max_body_bytes=8 << 20),
                     upload=UploadPolicy(stall=5.0, deadline=4.0, min_rate=2048, grace=1.0))
    with threaded_server(app, http=guarded_protocol(10.0)) as port:
        yield f"http://127.0.0.1:{port}", app


def test_protocol_errors_have_the_json_error_body(socket_server):
    r = attack.protocol_error(socket_server[0])
    assert r["status"] == 400 and r["content_type"] == "application/json", r
    assert r["error"].startswith("invalid HTTP request"), r


def test_a_trickling_upload_is_cut_off_after_the_grace_period(socket_server):
    url, _ = socket_server
    for declared in (8 << 20, None):              # with a Content-Length, and chunked
        stop = threading.Event()
        t0 = time.monotonic()
        rows = []
        worker = threading.Thread(
            target=attack.slow_upload, args=(url, TOKEN, stop, declared, 0.2, 30, rows))
        worker.start()
        while not rows and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        stop.set()
        worker.join(10)
        # the rate rule ended it ("bytes/s"; the 4 s deadline says "not complete"), never within
        # the grace period; how soon after it is BENCHMARKS.md's, a busy machine delays it
        assert rows and rows[0]["status"] == 408 and "bytes/s" in rows[0]["error"], rows
        assert 1.0 <= rows[0]["held_s"] < 30.0, rows


def test_the_whole_body_deadline_holds_against_a_steady_dribble(socket_server):
    """Fast enough for the minimum rate, never finishing: the deadline ends it."""
    url, _ = socket_server
    host, port = url.removeprefix("http://").split(":")
    s = socket.create_connection((host, int(port)), timeout=10)
    t0 = time.monotonic()
    got = b""
    try:
        s.sendall(f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                  f"Content-Type: application/json\r\nContent-Length: {8 << 20}\r\n\r\n".encode())
        while time.monotonic() - t0 < 60 and not got:
            try:
                s.sendall(b"[" * 1024)                     # 10 KiB/s, over the 2 KiB/s floor
            except OSError:
                break
            s.settimeout(0.1)
            try:
                got = s.recv(4096)
            except TimeoutError:
                pass
        got += attack.wait_closed(s, time.monotonic() + 5)[1]
    finally:
        s.close()
    assert got.startswith(b"HTTP/1.1 408") and b"not complete after 4 s" in got, got[:300]
    assert time.monotonic() - t0 >= 4.0            # not before its deadline (load only delays the answer)


def test_slow_uploaders_hold_what_they_sent_not_what_they_declared(bundle):
    """The budget admits one request of the largest body; a client declaring that body and
    trickling it used to hold the whole budget (every other request: 503 after 30 s)."""
    limits = Limits(max_body_bytes=8 << 20)
    assert limits.memory_budget == request_cost(8 << 20)
    app = create_app(ModelRegistry({"demo": bundle}), token=TOKEN, limits=limits,
                     upload=UploadPolicy(stall=30.0, deadline=60.0, min_rate=None))
    import threading
    with threaded_server(app, http=guarded_protocol(10.0)) as port:
        url = f"http://127.0.0.1:{port}"
        stop = threading.Event()
        slow = [threading.Thread(target=attack.slow_upload, args=(url, TOKEN, stop, 8 << 20, 0.5, 60), daemon=True)
                for _ in range(4)]
        for t in slow:
            t.start()
        try:
            time.sleep(1.5)
            body, headers = make_request(blocks=2, size=32, binary=True)
            statuses = [attack.post(url, body, headers, TOKEN, timeout=60)[0] for _ in range(3)]
            held = app.state.upload_budget.used + app.state.memory_budget.used
        finally:
            stop.set()
            for t in slow:
                t.join(10)
    assert statuses == [200, 200, 200]
    assert held <= 4 * (1 << 20), held                  # one reservation step each, not 8 MiB x 16


@pytest.mark.slow
def test_normal_requests_are_served_beside_sixteen_slow_uploaders(bundle):
    """`noisestop serve` with its defaults except a short grace: 16 slow uploaders (half
    chunked, half declaring 64 MiB) reconnecting as they are cut off; every normal request
    is answered 200 (the latency figures are BENCHMARKS.md's, not asserted here)."""
    with LocalServer({"demo": bundle}, body_grace=2.0) as s:
        r = attack.normal_latency_under_slow_uploads(s.url, s.token, 16, requests=20, interval=0.5)
        assert s.process.poll() is None, s.log()
    assert r["ok"] == r["requests"], r
    assert set(r["slow_statuses"]) <= {"408", "None"} and "408" in r["slow_statuses"], r


# --- SIGHUP ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_sighup_drains_like_sigterm_and_says_so(bundle):
    with LocalServer({"demo": bundle}) as s:
        body, headers = make_request(blocks=2, size=32, binary=True)
        sock = socket.create_connection(("127.0.0.1", s.port), timeout=30)
        head = (f"POST /v2/models/default/infer HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {s.token}\r\n"
                + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
                + f"Content-Length: {len(body)}\r\n\r\n").encode()
        sock.sendall(head + body[:100])                  # a request in flight
        time.sleep(0.5)
        s.process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert s.process.poll() is None, s.log()           # not killed: draining
        sock.sendall(body[100:])
        answer = attack.wait_closed(sock, time.monotonic() + 30)[1]
        sock.close()
        s.process.wait(30)
        log = s.log()
    assert answer.startswith(b"HTTP/1.1 200"), answer[:200]
    assert "SIGHUP: draining requests in flight" in log and "Traceback" not in log, log
