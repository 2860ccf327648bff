"""Tokens as docs/guide/serving.md documents them: a token with surrounding spaces is refused (serve
used to strip `NOISESTOP_TOKEN=" abc"` and accept a 3-character token); an error about a
token file names where the file came from (`--token-file`, or the variable only when the
variable named it); and the HTTP layer's 400 never echoes a header line (a NUL in the
Authorization line came back in the body, token and all)."""
from __future__ import annotations

import socket
import time

import pytest

from renderer.client.token import ENV_TOKEN, ENV_TOKEN_FILE, resolve_token
from benchmarks.attack.wire import wait_closed
from tests.support.errors import assert_one_line_error, run

SECRET = "s3cret-token-0123456789"


@pytest.fixture
def clean_env(monkeypatch):
    """No token in the environment, and a server that would start returns at once."""
    monkeypatch.delenv(ENV_TOKEN, raising=False)
    monkeypatch.delenv(ENV_TOKEN_FILE, raising=False)
    import service.serve
    monkeypatch.setattr(service.serve._DrainingServer, "run", lambda self, *a, **k: None)


@pytest.mark.parametrize("token", [" abc", "abc ", "\tabc"])
def test_a_token_with_surrounding_spaces_is_refused_without_showing_it(capsys, monkeypatch, clean_env,
                                                                        token) -> None:
    monkeypatch.setenv(ENV_TOKEN, token)
    with pytest.raises(ValueError, match=ENV_TOKEN):
        resolve_token()
    rc, err = run(capsys, "serve", "--port", "1")
    assert_one_line_error(rc, err, ENV_TOKEN, "visible ASCII")
    assert "abc" not in err


def test_a_token_file_error_names_the_flag_when_the_flag_gave_it(capsys, tmp_path, clean_env) -> None:
    (tmp_path / "tok").write_text("")
    rc, err = run(capsys, "serve", "--token-file", str(tmp_path / "tok"), "--port", "1")
    assert_one_line_error(rc, err, "--token-file", "empty")
    assert ENV_TOKEN_FILE not in err
    rc, err = run(capsys, "serve", "--token-file", str(tmp_path / "none"), "--port", "1")
    assert_one_line_error(rc, err, "--token-file", "does not exist")
    assert ENV_TOKEN_FILE not in err


def test_a_token_file_error_names_the_variable_when_the_variable_gave_it(capsys, tmp_path, monkeypatch,
                                                                          clean_env) -> None:
    (tmp_path / "tok").write_text("")
    monkeypatch.setenv(ENV_TOKEN_FILE, str(tmp_path / "tok"))
    rc, err = run(capsys, "serve", "--port", "1")
    assert_one_line_error(rc, err, ENV_TOKEN_FILE, "empty")
    assert "--token-file" not in err


@pytest.fixture(scope="module")
def socket_server(tmp_path_factory):
    from service.app import create_app
    from service.connections import guarded_protocol
    from service.registry import ModelRegistry
    from tests.support.demo import make_demo_bundle
    from tests.support.live_server import threaded_server

    bundle = str(make_demo_bundle(tmp_path_factory.mktemp("tok") / "demo", name="demo"))
    with threaded_server(create_app(ModelRegistry({"demo": bundle}), token=SECRET),
                         http=guarded_protocol(10.0)) as port:
        yield port


@pytest.mark.parametrize("line", [f"Authorization: Bearer {SECRET}\x00x", f"Author\x00ization: Bearer {SECRET}",
                                  f"X-Secret {SECRET}"], ids=["NUL in the value", "NUL in the name",
                                                               "no colon"])
def test_the_http_layers_400_never_echoes_a_header_line(socket_server, line) -> None:
    s = socket.create_connection(("127.0.0.1", socket_server), timeout=30)
    try:
        s.sendall(f"GET /v2/health/live HTTP/1.1\r\nHost: x\r\n{line}\r\n\r\n".encode("latin-1"))
        _, got = wait_closed(s, time.monotonic() + 30)
    finally:
        s.close()
    assert got.startswith(b"HTTP/1.1 400") and b'"error": "invalid HTTP request' in got, got
    assert SECRET.encode() not in got and b"Bearer" not in got and b"X-Secret" not in got, got
