"""A budget that binds reorders the work, never the render: at tile grain, with decisions
skipped as the unbudgeted render skips them, every block goes through the unbudgeted
render's states, so a time limit that is never reached gives the unbudgeted render and a
resume after one gives the uninterrupted image."""
from __future__ import annotations

import numpy as np
import pytest

from learning.data.exr import read_exr
from learning.data.npz import read_npz
from renderer.live.adaptive import adaptive_render
from renderer.live.budget import Budget
from renderer.live.passloop import PassLoop
from tests.support.forgery import killed_at

pytestmark = pytest.mark.slow

#: four 32 px blocks of four 16 px tiles each, flip at tile grain, decisions skipped (defaults)
TILED = {"resolution": 64, "block": 32, "tile": 16, "step": 8, "min_spp": 8, "max_spp": 256, "seed": 3,
         "tau": 0.05, "progress": False}


def _units(report: dict) -> list[tuple]:
    """Each block's and each tile's spp and stop, and each tile's decisions."""
    return [(b["id"], b["spp"], b["converged"], b.get("stop_spp"), b["history"])
            for b in report["blocks"] + report["tiles"]]


def _assert_same_render(a, b, ra: dict, rb: dict) -> None:
    np.testing.assert_array_equal(read_exr(a / "final.exr"), read_exr(b / "final.exr"))
    assert _units(ra) == _units(rb)


def _binding(monkeypatch) -> None:
    """Every round's budget left is nothing: a time limit that binds from the first round on
    (the render still runs to its end: the limit itself is never reached)."""
    monkeypatch.setattr(Budget, "left", lambda self, spp, elapsed: 0.0)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    out = tmp_path_factory.mktemp("plain")
    return out, adaptive_render("cornell", out, **TILED)


def test_a_time_limit_that_binds_but_is_not_reached_gives_the_unbudgeted_render(plain, tmp_path,
                                                                                monkeypatch) -> None:
    _binding(monkeypatch)
    rep = adaptive_render("cornell", tmp_path / "t", time_limit=1e6, **TILED)
    assert rep["budget"]["prioritised_rounds"] > 0                 # it did pick blocks
    assert rep["budget"]["judges_every_unit"] is False
    assert any(t["converged"] for t in rep["tiles"]) and rep["passes"] > plain[1]["passes"]
    _assert_same_render(tmp_path / "t", plain[0], rep, plain[1])


def test_a_binding_time_limit_traces_what_the_time_left_pays_for_in_one_launch(plain, tmp_path,
                                                                                 monkeypatch) -> None:
    """A prioritised round of a time limit gets several passes in one launch, as many as the
    time left pays for (a launch of a few blocks costs more per lane than a full one), and
    still goes through the unbudgeted render's states. Control: with no time left to speak of
    (`_binding`), one pass a launch."""
    from renderer.live.blocks import BlockRenderer

    def launches(left: float, out) -> tuple[dict, list[tuple[int, int]]]:
        per_launch: list[tuple[int, int]] = []
        real = BlockRenderer.submit_passes

        def counting(self, jobs, spp, seed):
            units = [u for u, _ in jobs]
            per_launch.append((len(set(units)), max(units.count(u) for u in set(units))))   # units, passes
            return real(self, jobs, spp, seed)

        with monkeypatch.context() as m:
            m.setattr(Budget, "left", lambda self, spp, elapsed: left)
            m.setattr(BlockRenderer, "submit_passes", counting)
            return adaptive_render("cornell", out, time_limit=1e6, **TILED), per_launch

    # 100 unit-spp left: below the ~4000 that all 16 tiles need (it binds); a launch of n tiles'
    # 8-spp passes holds at most 100 // (8 n) of them (three for a block's 4 tiles)
    rep, per_launch = launches(100.0, tmp_path / "g")
    assert rep["budget"]["prioritised_rounds"] > 0 and (4, 3) in per_launch
    assert all(k <= max(1, 100 // (8 * n)) for n, k in per_launch)
    assert len(per_launch) < rep["passes"] * 0.75
    _assert_same_render(tmp_path / "g", plain[0], rep, plain[1])
    _, one = launches(0.0, tmp_path / "z")
    assert max(k for _, k in one) == 1


def test_a_resume_after_a_binding_time_limit_is_the_uninterrupted_render(plain, tmp_path, monkeypatch) -> None:
    with monkeypatch.context() as m:
        _binding(m)
        m.setattr(PassLoop, "judge", killed_at(12))
        with pytest.raises(RuntimeError, match="simulated kill"):
            adaptive_render("cornell", tmp_path / "r", time_limit=1e6, checkpoint_every=0.0, **TILED)
    saved = read_npz(tmp_path / "r" / "checkpoint.npz")
    assert int(saved["budget_prioritised_rounds"]) > 0
    assert len(set(saved["acc_passes"][saved["active"]].tolist())) > 1     # units at different passes
    rep = adaptive_render("cornell", tmp_path / "r", resume=True, checkpoint_every=0.0, **TILED)
    _assert_same_render(tmp_path / "r", plain[0], rep, plain[1])


def test_a_tight_spp_budget_stops_units_where_the_unbudgeted_render_does(tmp_path) -> None:
    """An spp budget below max spp judges every unit it renders (it says so), and a unit it
    lets stop stops where the render that judges every unit without a budget stops it."""
    every = adaptive_render("cornell", tmp_path / "p", decide_skip=0.0, decide_growth=0.0, **TILED)
    rep = adaptive_render("cornell", tmp_path / "b", spp_budget=96, **TILED)
    again = adaptive_render("cornell", tmp_path / "b2", spp_budget=96, **TILED)
    assert rep["budget"]["ended"] and rep["budget"]["prioritised_rounds"] > 0
    assert rep["budget"]["judges_every_unit"] is True
    _assert_same_render(tmp_path / "b", tmp_path / "b2", rep, again)          # deterministic
    stops = {t["id"]: t["stop_spp"] for t in every["tiles"] if t["converged"]}
    stopped = [t for t in rep["tiles"] if t["converged"]]
    assert stopped and all(t["stop_spp"] == stops.get(t["id"]) for t in stopped)
    per_block = np.array([t["spp"] for t in rep["tiles"]]).reshape(4, 4)
    active = np.array([not t["converged"] for t in rep["tiles"]]).reshape(4, 4)
    for spp, act in zip(per_block, active):          # a block's pending tiles move together
        assert len(set(spp[act].tolist())) <= 1
