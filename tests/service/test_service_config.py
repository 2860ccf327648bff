"""Service settings: token sources, the loopback rule, limits from the environment, model specs."""
from __future__ import annotations

import logging

import pytest

from service import registry as registry_mod
from service.auth import check_bind, is_loopback, resolve_token
from service.limits import DEFAULT_MAX_BATCH, DEFAULT_MAX_BODY, Limits
from tests.support.demo import make_demo_bundle
from service.registry import ModelRegistry, parse_model_specs
from service.serve import build, run


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return str(make_demo_bundle(tmp_path_factory.mktemp("m") / "b", name="dsvm_x"))


def test_token_from_env_or_file(tmp_path):
    assert resolve_token(environ={}) is None
    assert resolve_token(environ={"NOISESTOP_TOKEN": "abc"}) == "abc"
    with pytest.raises(ValueError, match="visible ASCII"):         # docs/guide/serving.md: spaces are refused
        resolve_token(environ={"NOISESTOP_TOKEN": " abc \n"})
    f = tmp_path / "secret"
    f.write_text("from-file\n")
    assert resolve_token(environ={"NOISESTOP_TOKEN_FILE": str(f)}) == "from-file"
    assert resolve_token(token="explicit", environ={"NOISESTOP_TOKEN_FILE": str(f)}) == "explicit"


def test_token_problems_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        resolve_token(environ={"NOISESTOP_TOKEN_FILE": str(tmp_path / "nope.txt")})
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ValueError, match="empty"):
        resolve_token(environ={"NOISESTOP_TOKEN_FILE": str(tmp_path / "empty")})
    with pytest.raises(ValueError, match="not both"):
        resolve_token(environ={"NOISESTOP_TOKEN": "a", "NOISESTOP_TOKEN_FILE": str(tmp_path / "empty")})
    with pytest.raises(ValueError, match="empty"):
        resolve_token(token="  ")


@pytest.mark.parametrize("environ", [{"NOISESTOP_TOKEN": ""}, {"NOISESTOP_TOKEN": " \t\n"},
                                     {"NOISESTOP_TOKEN_FILE": ""}, {"NOISESTOP_TOKEN_FILE": "  "}])
def test_a_variable_set_but_empty_is_refused_not_taken_for_no_token(environ):
    """`NOISESTOP_TOKEN=` used to start a server with authentication off."""
    with pytest.raises(ValueError, match="set but empty"):
        resolve_token(environ=environ)
    with pytest.raises(ValueError, match="set but empty"):
        resolve_token(token_file="")


def test_no_token_needs_no_auth_and_loopback():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("example.org") and not is_loopback("10.0.0.1")
    check_bind("127.0.0.1", None, no_auth=True)
    check_bind("0.0.0.0", "token")
    with pytest.raises(ValueError, match="--no-auth"):
        check_bind("127.0.0.1", None)              # no token and no flag: refused, not a warning
    with pytest.raises(ValueError, match="drop one"):
        check_bind("127.0.0.1", "token", no_auth=True)
    for host in ("0.0.0.0", "::", "192.168.1.4"):
        for no_auth in (False, True):
            with pytest.raises(ValueError, match="without a token"):
                check_bind(host, None, no_auth=no_auth)


def test_serve_refuses_public_bind_without_token_before_loading(monkeypatch):
    monkeypatch.delenv("NOISESTOP_TOKEN", raising=False)
    monkeypatch.delenv("NOISESTOP_TOKEN_FILE", raising=False)
    with pytest.raises(ValueError, match="without a token"):
        run({"x": "/does/not/exist"}, host="0.0.0.0", port=0)


def test_unauthenticated_loopback_is_explicit_and_logged(monkeypatch, caplog, demo):
    monkeypatch.delenv("NOISESTOP_TOKEN", raising=False)
    monkeypatch.delenv("NOISESTOP_TOKEN_FILE", raising=False)
    with pytest.raises(ValueError, match="--no-auth"):
        build({"dsvm_x": demo}, "127.0.0.1")
    with caplog.at_level(logging.WARNING, logger="service.serve"):
        app = build({"dsvm_x": demo}, "127.0.0.1", no_auth=True)
    assert app.state.token is None
    assert any("UNAUTHENTICATED" in r.message and "loopback" in r.message for r in caplog.records)


def test_limits_from_arguments_env_and_defaults():
    assert Limits.from_env(environ={}) == Limits(DEFAULT_MAX_BODY, DEFAULT_MAX_BATCH)
    env = {"NOISESTOP_MAX_BODY_BYTES": "1000", "NOISESTOP_MAX_BATCH": "4"}
    assert Limits.from_env(environ=env) == Limits(1000, 4)
    assert Limits.from_env(max_batch=9, environ=env) == Limits(1000, 9)
    with pytest.raises(ValueError, match="NOISESTOP_MAX_BATCH"):
        Limits.from_env(environ={"NOISESTOP_MAX_BATCH": "lots"})
    with pytest.raises(ValueError, match="NOISESTOP_MAX_BODY_BYTES"):
        Limits.from_env(environ={"NOISESTOP_MAX_BODY_BYTES": "0"})
    with pytest.raises(ValueError, match="max_batch"):
        Limits(max_batch=0)


def test_model_specs(demo, tmp_path):
    assert parse_model_specs([demo]) == {"dsvm_x": demo}
    assert parse_model_specs([f"a={demo}", f"b={demo}"]) == {"a": demo, "b": demo}
    with pytest.raises(ValueError, match="two models"):
        parse_model_specs([demo, demo])
    with pytest.raises(ValueError, match="default"):
        parse_model_specs([f"default={demo}"])
    with pytest.raises(ValueError, match="model name"):
        parse_model_specs([f"bad/name={demo}"])
    with pytest.raises(FileNotFoundError, match="not a noisestop model bundle"):
        parse_model_specs([str(tmp_path)])


def test_missing_bundled_model_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setattr(registry_mod, "BUNDLED_DIR", tmp_path / "bundled")
    with pytest.raises(FileNotFoundError, match="--model"):
        parse_model_specs(None)
    reg = ModelRegistry({"x": None})
    with pytest.raises(FileNotFoundError, match="no model is bundled"):
        reg.load()


def test_registry_default_alias(demo):
    reg = ModelRegistry({"first": demo, "second": demo})
    reg.load()
    assert reg.ready and reg.get("default") is reg.get("first") is not reg.get("second")
    assert reg.names() == ["default", "first", "second"]


def test_client_and_server_read_the_token_by_one_rule(tmp_path, monkeypatch):
    """The client used to let NOISESTOP_TOKEN win where the server refused both: now both refuse."""
    from renderer.client.remote import default_token

    f = tmp_path / "token.txt"
    f.write_text("from-file\n")
    monkeypatch.setenv("NOISESTOP_TOKEN", "abc")
    monkeypatch.setenv("NOISESTOP_TOKEN_FILE", str(f))
    for read in (default_token, resolve_token):
        with pytest.raises(ValueError, match="not both"):
            read()
    monkeypatch.delenv("NOISESTOP_TOKEN")
    assert default_token() == resolve_token() == "from-file"
