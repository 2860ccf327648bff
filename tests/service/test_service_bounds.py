"""Request bounds over HTTP: named in the 413, parameters in their ranges (400), no 5xx."""
from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.limits import Limits
from tests.support.demo import make_demo_bundle
from service.registry import ModelRegistry

TOKEN = "bounds-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SIDE, PIXELS = 64, 4 * 64 * 64


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    bundle = make_demo_bundle(tmp_path_factory.mktemp("b") / "demo", name="demo")
    app = create_app(ModelRegistry({"demo": str(bundle)}), token=TOKEN,
                     limits=Limits(max_body_bytes=2_000_000, max_batch=64, max_block_side=SIDE, max_pixels=PIXELS))
    with TestClient(app) as c:
        yield c


def _tensor(name, shape, data=None, binary=False):
    t = {"name": name, "shape": list(shape), "datatype": "FP32"}
    if binary:
        t["parameters"] = {"binary_data_size": 4 * int(np.prod(shape))}
    else:
        t["data"] = data if data is not None else [0.5] * int(np.prod(shape))
    return t


def _post(client, body):
    content = body if isinstance(body, (bytes, str)) else json.dumps(body)
    return client.post("/v2/models/default/infer", content=content, headers=AUTH)


def _pair(n, h, w):
    return {"inputs": [_tensor("blocks", (n, h, w, 3)), _tensor("quick", (n, h, w, 3))]}


def test_the_issue_shape_is_refused_before_any_data_is_read(client):
    """[1, 8, 40000, 3] took the server to 23.7 GB; its header alone is now answered 413."""
    head = json.dumps({"inputs": [_tensor("blocks", (1, 8, 40000, 3), binary=True),
                                  _tensor("quick", (1, 8, 40000, 3), binary=True)]}).encode()
    r = client.post("/v2/models/default/infer", content=head + b"\0" * 16,   # data missing: never read
                    headers={**AUTH, "Inference-Header-Content-Length": str(len(head))})
    assert r.status_code == 413 and f"max_block_side = {SIDE}" in r.json()["error"]


def test_pixel_budget_and_block_side_are_named(client):
    assert _post(client, _pair(4, SIDE, SIDE)).status_code == 200                 # exactly the budget
    r = _post(client, _pair(5, SIDE, SIDE))
    assert r.status_code == 413 and f"max_pixels = {PIXELS}" in r.json()["error"]
    r = _post(client, _pair(1, 8, SIDE + 1))
    assert r.status_code == 413 and "max_block_side" in r.json()["error"]


def _with(body: dict, parameters: str) -> str:
    """The body with a raw JSON `parameters` object (numbers json.dumps cannot write)."""
    return json.dumps(body)[:-1] + ', "parameters": ' + parameters + "}"


BAD = {
    "exposure 2000": _with(_pair(1, 16, 16), '{"exposure": 2000}'),
    "exposure of 400 digits": _with(_pair(1, 16, 16), '{"exposure": ' + "9" * 400 + "}"),
    "exposure 1e308": _with(_pair(1, 16, 16), '{"exposure": 1e308}'),
    "exposure -Infinity": _with(_pair(1, 16, 16), '{"exposure": -Infinity}'),
    "exposure true": _with(_pair(1, 16, 16), '{"exposure": true}'),
    "offset NaN": _with(_pair(1, 16, 16), '{"offset": NaN}'),
    "offset of 400 digits": _with(_pair(1, 16, 16), '{"offset": -' + "9" * 400 + "}"),
    "offset 1e7": _with(_pair(1, 16, 16), '{"offset": 1e7}'),
    "JSON true as FP32 data": {"inputs": [_tensor("features", (1, 26), [True] * 26)]},
    "true among numbers": {"inputs": [_tensor("features", (1, 26), [0.5] * 25 + [True])]},
    "false nested among numbers": {"inputs": [_tensor("features", (1, 26), [[0.5] * 25 + [False]])]},
    "rank 100": {"inputs": [_tensor("features", [1] * 100, [0.5])]},
    "dimension 2**40 of an empty tensor": {"inputs": [_tensor("features", (0, 2**40), [])]},
    "dimension of 400 digits": '{"inputs": [{"name": "features", "datatype": "FP32", "data": [], '
                                '"shape": [0, ' + "9" * 400 + "]}]}",
}


@pytest.mark.parametrize("case", list(BAD))
def test_out_of_range_requests_are_400(client, case):
    r = _post(client, BAD[case])
    assert r.status_code == 400, (case, r.status_code, r.text)
    assert set(r.json()) == {"error"} and r.json()["error"]


def test_in_range_parameters_and_null_are_accepted(client):
    for params in ('{"exposure": 64, "offset": -1e6}', '{"exposure": null, "offset": null}', '{"exposure": -3}'):
        r = _post(client, _with(_pair(1, 16, 16), params))
        assert r.status_code == 200, (params, r.text)
