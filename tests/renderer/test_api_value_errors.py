"""`renderer.render` raises ValueError for every bad argument, as its docstring promises:
`tau=10**400` (not OverflowError), a missing model and an unreachable server, whose errors
are ValueError subclasses that are still FileNotFoundError and ConnectionError
(`renderer.errors`)."""
from __future__ import annotations

from pathlib import Path

import pytest

import renderer
from renderer.errors import InputNotFound, ServerUnavailable

pytestmark = pytest.mark.slow

TINY = {"resolution": 16, "block": 16, "max_spp": 16, "progress": False}


def test_a_huge_integer_setting_is_a_value_error() -> None:
    for name in ("tau", "exposure", "time_limit", "offset"):
        with pytest.raises(ValueError, match=f"{name} must be a finite number"):
            renderer.render("cornell", **{name: 10**400}, **TINY)
    with pytest.raises(ValueError, match="digit"):
        renderer.render("cornell", max_spp=10**5000, resolution=16)


def test_a_missing_model_is_a_value_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="nope") as err:
        renderer.render("cornell", model=str(tmp_path / "nope"), **TINY)
    assert isinstance(err.value, (InputNotFound, FileNotFoundError))


def test_a_missing_scene_file_is_a_value_error(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="missing.xml") as err:
        renderer.render(str(tmp_path / "missing.xml"), **TINY)
    assert isinstance(err.value, InputNotFound)


def test_an_unreachable_server_is_a_value_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("NOISESTOP_TOKEN", "t" * 24)
    monkeypatch.delenv("NOISESTOP_TOKEN_FILE", raising=False)
    with pytest.raises(ValueError, match="127.0.0.1:9") as err:
        renderer.render("cornell", server="http://127.0.0.1:9", **TINY)
    assert isinstance(err.value, ServerUnavailable) and isinstance(err.value, ConnectionError)


def test_an_object_that_is_no_criterion_is_refused_at_the_door(monkeypatch: pytest.MonkeyPatch) -> None:
    import renderer.scenes.catalog

    class Lookalike:            # decides and describes, but is no Criterion
        def decide(self, ids, batch):
            raise AssertionError("decided")

        def describe(self):
            return {"name": "lookalike"}

    def load_scene(*args, **kwargs):
        raise AssertionError("the scene loaded")
    monkeypatch.setattr(renderer.scenes.catalog, "load_scene", load_scene)
    with pytest.raises(ValueError, match="^criterion must be one of .* or a Criterion, got <") as err:
        renderer.render("cornell", criterion=Lookalike(), **TINY)
    assert "\n" not in str(err.value)
