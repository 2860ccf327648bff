"""The server's guards on real sockets: idle floods, slow clients, the in-flight limit, the memory
ceiling, schemathesis stateful runs. The scenarios are benchmarks.attack's, the same ones
`noisestop bench reliability` reports; here they assert."""
from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (content_type_conformance, negative_data_rejection,
                                               response_headers_conformance, response_schema_conformance,
                                               status_code_conformance)

from benchmarks import attack
from service.app import create_app
from tests.support.demo import make_demo_bundle, make_request
from tests.support.local_server import LocalServer
from service.registry import ModelRegistry

HEADER_TIMEOUT = 1.0


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return str(make_demo_bundle(tmp_path_factory.mktemp("guards") / "demo", name="demo"))


@pytest.fixture(scope="module")
def server(bundle):
    with LocalServer({"demo": bundle}, header_timeout=HEADER_TIMEOUT, body_timeout=2.0, keep_alive=1,
                     limit_concurrency=4) as s:
        yield s


def _infer(server) -> int | str:
    body, headers = make_request(blocks=2, size=32, binary=True)
    return attack.post(server.url, body, headers, server.token)[0]


def test_health_answers_under_64_idle_connections_which_are_then_closed(server):
    r = attack.idle_flood(server.url, n=64, probes=10, wait=HEADER_TIMEOUT + 15, infer=lambda: _infer(server))
    assert r["health_ok"] == r["probes"] == 10, r            # never a 503 (an idle flood must not deny service)
    assert r["infer_status"] == 200, r
    assert r["closed_by_server"] == 64, r                      # the header timeout hung up on every one
    assert set(r["answers_before_close"]) <= {"none", "408"}, r


def test_slow_header_client_is_cut_off(server):
    r = attack.slow_headers(server.url, interval=0.05, limit_s=30)
    assert r["cut_off"] and r["bytes_sent"] < r["header_bytes"], r
    assert r["status"] in (None, "408"), r


def test_stalled_body_is_answered_408(server):
    r = attack.stalled_body(server.url, server.token, limit_s=30)
    assert r["status"] == "408", r


def test_requests_over_the_in_flight_limit_get_503_and_probes_still_200(server):
    r = attack.over_the_limit(server.url, server.token, limit=4)
    assert r["extra_status"] == 503 and r["retry_after"] == "1" and "--limit-concurrency" in r["error"], r
    assert r["health_status"] == 200, r
    assert _infer(server) == 200          # the held requests are gone: the server serves again


@pytest.mark.slow
def test_memory_ceiling_under_the_worst_shapes(bundle):
    """The server in a subprocess under RLIMIT_AS = 3 GiB with the default limits: the worst
    shapes (a block side past the limit, the widest and thinnest blocks, 64 MiB of nested JSON, three of the
    largest at once) are answered or refused, never a 5xx, and its peak RSS stays under 2 GiB.
    The nested JSON is refused unparsed (its decoding would take ~2.5 GiB: over the memory
    budget), as is the 62 MiB request (20 lists around every value); after them
    the server still answers."""
    with LocalServer({"demo": bundle}, address_space=3 << 30) as s:
        rows = attack.run_worst_shapes(s.url, s.token, 64 << 20, concurrent=3, memory=s.memory)
        nested = attack.nested_over_budget(s.url, s.token)
        assert s.process.poll() is None, s.log()
        assert attack.timed_get("127.0.0.1", s.port, "/v2/health/ready")[0] == 200
        peak = s.memory()["peak_rss"]
    statuses = [st for r in rows for st in r.get("statuses", [r["status"]])]
    assert all(st in (200, 413) for st in statuses), rows
    # the long block, the pixel budget, the nested JSON, the declared body
    assert sum(st == 413 for st in statuses) == 4, rows
    assert nested["status"] == 413 and "working memory" in nested["error"], nested
    assert peak < 2 << 30, (peak, rows)


# --- schemathesis, stateful -------------------------------------------------------------------

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance,
          response_headers_conformance, response_schema_conformance, negative_data_rejection]
TOKEN = "stateful-token-0123456789"


def test_schemathesis_stateful_runs_find_no_server_error(bundle):
    """Scenarios through the links schemathesis infers (repository index -> model name ->
    metadata, readiness, infer), every answer checked against the OpenAPI document."""
    app = create_app(ModelRegistry({"demo": bundle}), token=TOKEN)
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    calls = []

    class Workflow(schema.as_state_machine()):
        def get_call_kwargs(self, case):
            return {"headers": {"Authorization": f"Bearer {TOKEN}"}}

        def after_call(self, response, case):
            calls.append((case.method, case.path, response.status_code))

        def validate_response(self, response, case, additional_checks=None, **kwargs):
            case.validate_response(response, checks=CHECKS)

    Workflow.run(settings=settings(max_examples=40, stateful_step_count=6, deadline=None, database=None,
                                   suppress_health_check=list(HealthCheck)))
    assert len(calls) >= 40 and not [c for c in calls if c[2] >= 500]
    assert any(c[1].endswith("/infer") and c[2] in (200, 400) for c in calls)   # reached the decoder
