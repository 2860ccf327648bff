"""One Open Inference Protocol binary codec (renderer/client/oip_codec.py) for client and server:
what the client encodes the server decodes, what the server encodes the client decodes,
and neither end packs or unpacks tensor bytes on its own."""
from __future__ import annotations

import ast
import json

import numpy as np
import pytest

from renderer.client import oip_codec
from renderer.client.remote import RemoteModel
from renderer.client.oip_codec import WireError, join_body, read_tensor, split_body, tensor_bytes
from tests.support import ROOT



def test_client_request_decodes_on_the_server_and_back(monkeypatch: pytest.MonkeyPatch) -> None:
    from service.oip import InferenceResponse, decode_tensors, encode_response, parse_request

    blocks = np.random.default_rng(0).random((3, 4, 5, 3)).astype(np.float32)
    sent: dict[str, object] = {}

    def fake_request(self, method, url, body=None, headers=None):   # what the client puts on the wire
        sent.update(body=body, headers=headers)
        header, tail = split_body(body, int(headers[oip_codec.HEADER_LENGTH]))
        got = decode_tensors(parse_request(bytes(header)), tail, max_batch=16)
        np.testing.assert_array_equal(got["blocks"], blocks)
        resp = InferenceResponse(model_name="m", outputs=[
            {"name": "verdict", "shape": [3], "datatype": "INT8"},
            {"name": "score", "shape": [3], "datatype": "FP64"}])
        out, hlen = encode_response(resp, {"verdict": np.array([1, -1, 1], np.int8),
                                           "score": np.array([0.5, -2.0, 3.25])}, {"verdict", "score"})
        return 200, {oip_codec.HEADER_LENGTH.lower(): str(hlen)}, out

    monkeypatch.setattr(RemoteModel, "_request", fake_request)
    res = RemoteModel("http://127.0.0.1:1", retries=0).infer({"blocks": blocks})
    assert res["verdict"].tolist() == [1, -1, 1] and res["score"].tolist() == [0.5, -2.0, 3.25]
    assert json.loads(split_body(sent["body"], int(sent["headers"][oip_codec.HEADER_LENGTH]))[0])


def test_codec_checks_sizes_and_lengths() -> None:
    raw = tensor_bytes(np.arange(6, dtype=np.float32).reshape(2, 3))
    body, n = join_body(b'{"h":1}', [raw])
    header, tail = split_body(body, n)
    assert header == b'{"h":1}'
    np.testing.assert_array_equal(read_tensor(tail, "FP32", [2, 3], 24, 0, "x"), np.arange(6).reshape(2, 3))
    assert join_body(b"{}", []) == (b"{}", None)
    with pytest.raises(WireError, match="does not match shape"):
        read_tensor(tail, "FP32", [2, 3], 20, 0, "input 'x'")
    with pytest.raises(WireError, match="truncated"):
        read_tensor(tail[:-4], "FP32", [2, 3], 24, 0, "input 'x'")
    with pytest.raises(WireError, match="is 99 but the body holds"):
        split_body(body, 99)


def test_neither_end_has_its_own_codec() -> None:
    """No np.frombuffer / .tobytes() in the client or the server's protocol module."""
    for rel in ("renderer/client/remote.py", "service/oip.py"):
        tree = ast.parse((ROOT / rel).read_text())
        own = [n.lineno for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr in ("frombuffer", "tobytes")]
        assert own == [], f"{rel}: tensor bytes packed by hand at lines {own}"
