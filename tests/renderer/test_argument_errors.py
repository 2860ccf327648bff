"""Every argument error of run_adaptive names its argument, one line, ValueError; a budget
below one pass, a non-finite reference, the output-folder lock."""
from __future__ import annotations

import multiprocessing
import os

import numpy as np
import pytest

from renderer.spec import resolve
from renderer.live.outlock import LOCK_NAME, OutputLocked, locked_output


@pytest.mark.parametrize("kwargs, name", [
    ({"max_spp": -1}, "max_spp"), ({"min_spp": "16"}, "min_spp"), ({"max_spp": "16"}, "max_spp"),
    ({"step": 1.5}, "step"), ({"quick_spp": 0}, "quick_spp"), ({"quick_spp": -1}, "quick_spp"),
    ({"quick_spp": 1.5}, "quick_spp"), ({"quick_spp": "16"}, "quick_spp"),
    ({"time_limit": 10**48}, "time_limit"), ({"spp_budget": 10**48}, "spp_budget"),
    ({"time_limit": "5"}, "time_limit"), ({"spp_budget": float("nan")}, "spp_budget"),
])
def test_each_bad_argument_is_named(kwargs, name):
    with pytest.raises(ValueError) as exc:
        resolve(kwargs)
    message = str(exc.value)
    assert f"({name})" in message or message.startswith(name), message
    assert "\n" not in message
    if kwargs.get("time_limit") == 10**48:
        assert "49-digit number" in message


def test_run_adaptive_names_max_spp_not_min_spp():
    from renderer.live.adaptive import run_adaptive
    with pytest.raises(ValueError, match="^max_spp must"):
        run_adaptive("cornell", "uniform", max_spp=-1, progress=False)


def test_a_budget_below_one_pass_is_refused():
    with pytest.raises(ValueError, match="cannot buy one pass of 16"):
        resolve({"spp_budget": 8, "step": 16})
    assert resolve({"spp_budget": 16, "step": 16}).spp_budget == 16.0


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_a_non_finite_reference_is_refused(value):
    img = np.full((4, 4, 3), value, np.float32)
    from renderer.live.plan import load_reference

    with pytest.raises(ValueError, match="non-finite"):
        load_reference(img, "scene")


def _hold(out: str, ready, release) -> None:
    with locked_output(out):
        ready.set()
        release.wait(30)


def test_a_second_render_into_a_locked_folder_is_refused(tmp_path):
    ctx = multiprocessing.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    p = ctx.Process(target=_hold, args=(str(tmp_path), ready, release))
    p.start()
    try:
        assert ready.wait(30)
        with pytest.raises(OutputLocked, match="another render is writing into this folder"):
            with locked_output(tmp_path):
                pass
    finally:
        release.set()
        p.join(30)
    with locked_output(tmp_path):         # free again once the first has ended
        pass
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_stale_lock_of_a_killed_run_is_taken_over_and_said(tmp_path, caplog):
    (tmp_path / LOCK_NAME).write_text("pid 999999 on elsewhere, since yesterday\n")
    with caplog.at_level("WARNING"), locked_output(tmp_path):
        pass
    assert "taking over the lock" in caplog.text and "pid 999999" in caplog.text
    assert not os.path.exists(tmp_path / LOCK_NAME)
