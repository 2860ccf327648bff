"""RemoteModel against a tiny fake OIP v2 server that checks the request format."""
from __future__ import annotations

import json
import socket
from http.server import BaseHTTPRequestHandler

import numpy as np
import pytest

from renderer.client.remote import HEADER_LENGTH, RemoteModel
from renderer.criteria import UnitView, ModelCriterion
from tests.support.live_server import handler_server

TOKEN = "s3cret"


class FakeOIP(BaseHTTPRequestHandler):
    """Verdict = +1 iff the block's mean exceeds its quick block's mean; score = difference."""

    seen: list = []          # (path, headers, parsed request) of every infer call
    fail_with: tuple | None = None
    fail_once = False        # answer fail_with to the next request only

    def log_message(self, *args):  # keep test output clean
        pass

    def _send(self, status, obj, extra=b"", headers=None):
        body = json.dumps(obj).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.send_header("Content-Length", str(len(body) + len(extra)))
        self.end_headers()
        self.wfile.write(body + extra)

    def _authorised(self):
        if self.headers.get("Authorization") != f"Bearer {TOKEN}":
            self._send(401, {"error": "unauthorized"})
            return False
        return True

    def do_GET(self):
        if not self._authorised():
            return
        if self.path == "/v2/models/default/ready":
            self._send(200, {"name": "default", "ready": True})
        elif self.path == "/v2/models/loading/ready":
            self._send(503, {"error": "model is loading"})
        elif self.path == "/v2/models/default":
            self._send(200, {"name": "default", "versions": ["1"], "platform": "noisestop",
                             "inputs": [{"name": "blocks", "datatype": "FP32", "shape": [-1, -1, -1, 3]}],
                             "outputs": [{"name": "verdict", "datatype": "INT8", "shape": [-1]}]})
        else:
            self._send(404, {"error": f"no such model route {self.path}"})

    def do_POST(self):
        if not self._authorised():
            return
        if self.fail_with:
            self._send(*self.fail_with)
            if type(self).fail_once:
                type(self).fail_with = None
            return
        if self.path != "/v2/models/default/infer":
            self._send(404, {"error": "unknown model"})
            return
        body = self.rfile.read(int(self.headers["Content-Length"]))
        hlen = self.headers.get(HEADER_LENGTH)
        header = json.loads(body[: int(hlen)] if hlen else body)
        tail = body[int(hlen):] if hlen else b""
        arrays, offset = {}, 0
        for t in header["inputs"]:
            assert t["datatype"] == "FP32"
            count = int(np.prod(t["shape"]))
            if hlen:
                size = t["parameters"]["binary_data_size"]
                assert size == 4 * count and "data" not in t
                arrays[t["name"]] = np.frombuffer(tail, "<f4", count, offset).reshape(t["shape"])
                offset += size
            else:
                arrays[t["name"]] = np.asarray(t["data"], np.float32).reshape(t["shape"])
        assert offset == len(tail), "binary bytes left over"
        type(self).seen.append((self.path, dict(self.headers), header))
        score = arrays["blocks"].mean(axis=(1, 2, 3)) - arrays["quick"].mean(axis=(1, 2, 3))
        verdict = np.where(score > 0, 1, -1).astype(np.int8)
        want_binary = {o["name"]: o.get("parameters", {}).get("binary_data", False) for o in header["outputs"]}
        outs, raw = [], b""
        for name, arr, dt in (("verdict", verdict, "INT8"), ("score", score.astype("<f4"), "FP32")):
            o = {"name": name, "shape": [len(arr)], "datatype": dt}
            if want_binary.get(name):
                o["parameters"] = {"binary_data_size": arr.nbytes}
                raw += arr.tobytes()
            else:
                o["data"] = arr.tolist()
            outs.append(o)
        resp = {"model_name": "default", "outputs": outs}
        hdr = {HEADER_LENGTH: str(len(json.dumps(resp).encode()))} if raw else None
        self._send(200, resp, raw, hdr)


@pytest.fixture()
def server():
    FakeOIP.seen = []
    FakeOIP.fail_with = None
    FakeOIP.fail_once = False
    with handler_server(FakeOIP) as url:
        yield url


def blocks_and_quick(n=5, seed=0):
    rng = np.random.default_rng(seed)
    blocks = rng.random((n, 8, 6, 3)).astype(np.float32)
    quick = np.full_like(blocks, 0.5)
    return blocks, quick


@pytest.mark.parametrize("binary", [True, False])
def test_score_blocks_round_trip(server, binary):
    m = RemoteModel(server, token=TOKEN, binary=binary)
    blocks, quick = blocks_and_quick()
    verdict, score = m.score_blocks(blocks, quick)
    expected = blocks.mean(axis=(1, 2, 3)) - 0.5
    assert verdict.dtype == np.int8 and verdict.tolist() == np.where(expected > 0, 1, -1).tolist()
    np.testing.assert_allclose(score, expected, rtol=1e-6)
    path, headers, req = FakeOIP.seen[-1]
    assert [t["name"] for t in req["inputs"]] == ["blocks", "quick"]
    assert all(t["shape"] == [5, 8, 6, 3] for t in req["inputs"])
    assert [o["name"] for o in req["outputs"]] == ["verdict", "score"]
    assert all(o["parameters"]["binary_data"] is binary for o in req["outputs"])
    assert (HEADER_LENGTH in headers) is binary


def test_batches_are_split(server):
    m = RemoteModel(server, token=TOKEN, batch_size=2)
    blocks, quick = blocks_and_quick(5)
    verdict, _ = m.score_blocks(blocks, quick)
    assert len(verdict) == 5 and len(FakeOIP.seen) == 3
    assert [req["inputs"][0]["shape"][0] for _, _, req in FakeOIP.seen] == [2, 2, 1]


def test_ready_metadata_and_token_from_env(server, monkeypatch):
    monkeypatch.setenv("NOISESTOP_TOKEN", TOKEN)
    m = RemoteModel(server)
    assert m.ready() is True
    assert m.metadata()["inputs"][0]["name"] == "blocks"
    assert RemoteModel(server, model="loading").ready() is False
    assert m.quick == "albedo" and m.needs_quick   # a server that does not say wants albedo
    monkeypatch.delenv("NOISESTOP_TOKEN")
    with pytest.raises(ValueError, match="401.*unauthorized"):
        RemoteModel(server).metadata()


def test_token_file(server, monkeypatch, tmp_path):
    monkeypatch.delenv("NOISESTOP_TOKEN", raising=False)
    (tmp_path / "tok").write_text(TOKEN + "\n")
    monkeypatch.setenv("NOISESTOP_TOKEN_FILE", str(tmp_path / "tok"))
    assert RemoteModel(server).ready() is True


def test_server_errors_carry_the_server_message(server):
    m = RemoteModel(server, token=TOKEN)
    blocks, quick = blocks_and_quick(2)
    FakeOIP.fail_with = (400, {"error": "input 'blocks' must be at least 8x8"})
    with pytest.raises(ValueError, match="HTTP 400: input 'blocks' must be at least 8x8"):
        m.score_blocks(blocks, quick)
    FakeOIP.fail_with = (500, {"error": "model crashed"})
    with pytest.raises(ConnectionError, match="HTTP 500: model crashed"):
        m.score_blocks(blocks, quick)
    assert m.requests == 2                   # HTTP errors are not retried
    with pytest.raises(ValueError, match="404"):
        RemoteModel(server, model="nope", token=TOKEN).metadata()


def test_busy_server_503_with_retry_after_is_retried(server):
    """A server at its in-flight or memory limit answers 503 + Retry-After."""
    m = RemoteModel(server, token=TOKEN, retries=2, backoff=0.0)
    blocks, quick = blocks_and_quick(2)
    FakeOIP.fail_with, FakeOIP.fail_once = (503, {"error": "server busy"}, b"", {"Retry-After": "0"}), True
    verdict, _ = m.score_blocks(blocks, quick)
    assert len(verdict) == 2 and m.requests == 2
    FakeOIP.fail_with, FakeOIP.fail_once = (503, {"error": "server busy"}, b"", {"Retry-After": "0"}), False
    with pytest.raises(ConnectionError, match="HTTP 503: server busy"):
        m.score_blocks(blocks, quick)
    assert m.requests == 2 + 3               # retried at most `retries` times


def test_unreachable_server_retries_a_bounded_number_of_times():
    with socket.socket() as s:               # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    m = RemoteModel(f"http://127.0.0.1:{port}", token="x", retries=2, backoff=0.01)
    with pytest.raises(ConnectionError, match="unreachable after 3 attempt"):
        m.ready()
    assert m.requests == 3


def test_bad_arguments():
    with pytest.raises(ValueError, match="http://host:port"):
        RemoteModel("localhost:8000")
    m = RemoteModel("http://127.0.0.1:9", token="x")
    with pytest.raises(ValueError, match=r"\[N, H, W, 3\]"):
        m.score_blocks(np.zeros((2, 8, 8)), None)
    with pytest.raises(ValueError, match="do not match"):
        m.score_blocks(np.zeros((2, 8, 8, 3)), np.zeros((1, 8, 8, 3)))


def test_model_criterion_over_http(server):
    crit = ModelCriterion(RemoteModel(server, token=TOKEN))
    assert crit.needs_quick
    rng = np.random.default_rng(1)
    views = [UnitView(mean=0.1 + 0.05 * rng.random((8, 8, 3)), spp=16, quick=np.full((8, 8, 3), 0.5)),
             UnitView(mean=0.8 + 0.05 * rng.random((8, 8, 3)), spp=16, quick=np.full((8, 8, 3), 0.5))]
    d = crit.decide([2, 9], views)
    assert d.verdict.tolist() == [-1, 1]
    assert d.counts["units_featured"] == 2 and d.counts.get("feature_rows", 0) == 0
    assert crit.describe()["model"]["remote"] == server
