"""A token must be one line of visible ASCII characters, and no error ever shows it: a
two-line token file must not reach the HTTP layer (whose error would print ``Invalid
header value b'Bearer <the token>\\nsecond line'``), nor `serve` take it and answer every
request 401. Client and server refuse it in one line naming the file; the secret appears
in no output and no exception text."""
from __future__ import annotations

import pytest

from renderer.client.token import resolve_token
from tests.support.errors import assert_one_line_error, run

SECRET = "s3cr3t-TOKEN-value"
#: token file contents that are not one line of visible ASCII
BAD_FILES = {"two lines": f"{SECRET}\nsecond line\n", "a control character": f"{SECRET}\x07x\n",
             "a blank line after": f"{SECRET}\n\n", "a space inside": f"{SECRET} x\n",
             "not ASCII": f"{SECRET}\u00e9\n"}


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    """No token in the environment, and a server that would start returns at once instead
    of serving (so a token taken by mistake fails the test rather than hanging it)."""
    import service.serve

    monkeypatch.delenv("NOISESTOP_TOKEN", raising=False)
    monkeypatch.delenv("NOISESTOP_TOKEN_FILE", raising=False)
    monkeypatch.setattr(service.serve._DrainingServer, "run", lambda self, *a, **k: None)
    return monkeypatch


def _no_secret(*texts: str) -> None:
    for text in texts:
        assert SECRET not in text, text


def test_a_token_file_is_one_visible_line_with_an_optional_newline(tmp_path, clean_env) -> None:
    for content, want in ((f"{SECRET}\n", SECRET), (SECRET, SECRET), (f"{SECRET}\r\n", SECRET)):
        (tmp_path / "tok").write_bytes(content.encode())
        assert resolve_token(token_file=tmp_path / "tok") == want
    for name, content in BAD_FILES.items():
        (tmp_path / "tok").write_bytes(content.encode())
        with pytest.raises(ValueError) as err:
            resolve_token(token_file=tmp_path / "tok")
        assert str(tmp_path / "tok") in str(err.value) and "\n" not in str(err.value), name
        _no_secret(str(err.value))


def test_the_client_refuses_a_two_line_token_file_without_showing_it(capsys, tmp_path, clean_env) -> None:
    (tmp_path / "tok").write_text(BAD_FILES["two lines"])
    clean_env.setenv("NOISESTOP_TOKEN_FILE", str(tmp_path / "tok"))
    rc, err = run(capsys, "render", "--scene", "cornell", "--resolution", "16", "--server", "http://127.0.0.1:9",
                  "--out", str(tmp_path / "out"))
    out = capsys.readouterr().out
    assert_one_line_error(rc, err, str(tmp_path / "tok"), "one line")
    _no_secret(err, out)


def test_the_server_refuses_a_two_line_token_file_without_showing_it(capsys, tmp_path, clean_env) -> None:
    from service.registry import ModelRegistry

    (tmp_path / "tok").write_text(BAD_FILES["two lines"])
    loaded: list[int] = []
    clean_env.setattr(ModelRegistry, "load", lambda self: loaded.append(1))
    rc, err = run(capsys, "serve", "--token-file", str(tmp_path / "tok"), "--port", "1")
    assert_one_line_error(rc, err, str(tmp_path / "tok"), "one line")
    _no_secret(err, capsys.readouterr().out)
    assert loaded == []


@pytest.mark.parametrize("command", ["serve", "render"])
def test_a_token_with_control_characters_is_refused_without_showing_it(capsys, tmp_path, clean_env,
                                                                       command: str) -> None:
    from service.registry import ModelRegistry

    clean_env.setenv("NOISESTOP_TOKEN", f"{SECRET}\x1b[2J\x07")
    clean_env.setattr(ModelRegistry, "load", lambda self: None)
    argv = ["serve", "--port", "1"] if command == "serve" else [
        "render", "--scene", "cornell", "--resolution", "16", "--server", "http://127.0.0.1:9",
        "--out", str(tmp_path / "out")]
    rc, err = run(capsys, *argv)
    assert_one_line_error(rc, err, "NOISESTOP_TOKEN", "one line")
    _no_secret(err, capsys.readouterr().out)


def test_the_client_never_shows_a_token_in_its_exceptions(clean_env) -> None:
    from renderer.client.remote import RemoteModel

    with pytest.raises(ValueError) as err:              # an explicit token: checked as the file's is
        RemoteModel("http://127.0.0.1:9", token=f"{SECRET}\nx")
    _no_secret(str(err.value))
    m = RemoteModel("http://127.0.0.1:9", token=SECRET, retries=0)
    m.token = f"{SECRET}\r\nX-Evil: 1"                 # past every check: the HTTP layer refuses the header
    with pytest.raises(ValueError) as err:
        m.ready()
    _no_secret(str(err.value), repr(err.value.__cause__), repr(err.value.__context__))
    m.token = SECRET                                    # unreachable: a ConnectionError, no header in it
    with pytest.raises(ConnectionError) as conn:
        m.ready()
    _no_secret(str(conn.value))
