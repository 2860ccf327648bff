"""No JSON parse on the server's own thread that can stall it. A body just under
the pool's byte threshold (16.3 kB nested 11 deep) opens thousands of lists, and their
garbage collections stalled the server (p99 8x, health p95 26x): such a body goes to the
parse pool; a binary request's header and a flat JSON tensor stay inline. Speed goals live
in benchmarks (`benchmarks.hardening_bodies.bench_inline_json`); these tests check the
routing."""
from __future__ import annotations

import pytest

from benchmarks.attack import nested_json, valid_halves_json
from service.parsepool import INLINE_BYTES, INLINE_CONTAINERS, parse_inline
from tests.support.demo import make_request


def _header(body: bytes, headers: dict[str, str]) -> bytes:
    (n,) = [v for k, v in headers.items() if k.lower().endswith("header-content-length")]
    return body[:int(n)]


def test_a_nested_body_under_the_byte_threshold_is_not_parsed_inline():
    body, _ = nested_json(16_300)
    assert len(body) <= INLINE_BYTES                     # it passed the old byte test
    assert not parse_inline(body) and not parse_inline(memoryview(body))
    assert not parse_inline(nested_json(3_000)[0])       # 1,272 lists: already sets off collections


def test_cheap_headers_stay_inline():
    binary = _header(*make_request(blocks=16, size=128, binary=True))
    flat, _ = valid_halves_json(16_000)                  # flat tensors: numbers are not containers
    assert parse_inline(binary) and parse_inline(memoryview(binary)) and parse_inline(flat)
    assert flat.count(b"[") + flat.count(b"{") < INLINE_CONTAINERS
    assert not parse_inline(flat + b" " * INLINE_BYTES)  # the byte threshold still holds


@pytest.fixture(scope="module")
def demo_bundle(tmp_path_factory):
    from tests.support.demo import make_demo_bundle

    return str(make_demo_bundle(tmp_path_factory.mktemp("inline") / "demo", name="demo"))


@pytest.mark.parametrize("case", ["nested JSON body", "nested binary header"])
def test_the_server_sends_a_costly_body_to_the_pool(demo_bundle, monkeypatch, case):
    """Through the app: the nested body (all JSON, or as a binary request's header) reaches
    the parse pool and is refused as before; a binary request's ordinary header does not."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.oip import HEADER_LENGTH
    from service.registry import ModelRegistry

    app = create_app(ModelRegistry({"demo": demo_bundle}))
    body, headers = nested_json(16_300)
    if case == "nested binary header":
        headers = {"Content-Type": "application/octet-stream", HEADER_LENGTH: str(len(body))}
    normal, normal_headers = make_request(blocks=2, size=32, binary=True)
    with TestClient(app) as c:
        pool = app.state.parse_pool
        seen: list[int] = []
        real = pool.parse

        async def spy(head):
            seen.append(len(head))
            return await real(head)

        monkeypatch.setattr(pool, "parse", spy)
        r = c.post("/v2/models/default/infer", content=body, headers=headers)
        assert r.status_code in (400, 413) and seen == [len(body)], (r.status_code, seen)
        assert c.post("/v2/models/default/infer", content=normal, headers=normal_headers).status_code == 200
        assert seen == [len(body)]                       # the binary header was parsed inline
