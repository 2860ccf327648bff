"""Several passes per launch, and the budget render (spend passes where the noise is)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from learning.data.exr import read_exr
from renderer.live.adaptive import adaptive_render, run_adaptive
from renderer.live.blocks import BlockRenderer
from renderer.live.budget import Budget
from renderer.criteria import OracleCriterion, UniformCriterion, VarianceCriterion
from renderer.live.passloop import PassLoop, schedule
from renderer.settings import MAX_SPP
from tests.support.errors import assert_one_line_error, run
from tests.renderer.test_renderer_blocks import _scene

SCHEDULE = schedule(4, 64)

pytestmark = pytest.mark.slow

TINY = {"resolution": 32, "grid": (4, 4), "step": 4, "min_spp": 4, "max_spp": 24, "progress": False}
THRESHOLDS = [4, 8, 24, 12, None, 4, 16, 8, 20, 4, 8, 12, 24, 16, 8, None]


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_passes_in_one_launch_are_the_passes_traced_apart(rfilter) -> None:
    r = BlockRenderer(_scene("cornell", 32, rfilter), grid=(4, 4))
    jobs = [(5, 0), (5, 1), (5, 2), (6, 3), (9, 1)]        # passes of one block, other blocks at other passes
    together = r.render_passes(jobs, 4, seed=7)
    launches = r.ledger.get("kernel_launches")
    for (b, p), img in zip(jobs, together):
        apart = r.render_units([b], 4, seed=7, pass_index=p)[0]
        if rfilter == "box":
            np.testing.assert_array_equal(img, apart)
        else:                           # the same samples; splats summed in another order
            np.testing.assert_allclose(img, apart, rtol=1e-5, atol=1e-7)
    assert launches == 1                         # every pass index in one launch, whatever the filter
    assert r.ledger.get("kernel_lanes") == r.ledger.get("samples_traced") and r.ledger.get("kernel_lanes") > 0
    sizes = r.render_passes([(5, 0), (6, 1)], [4, 2], seed=7)   # a short last pass: its own launch
    short = r.render_units([6], 2, seed=7, pass_index=1)[0]
    if rfilter == "box":
        np.testing.assert_array_equal(sizes[1], short)
    else:                               # splats summed in an order that varies run to run
        np.testing.assert_allclose(sizes[1], short, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="duplicate"):
        r.render_passes([(5, 0), (5, 0)], 4, seed=7)


def test_a_budget_round_is_the_plain_pass_when_every_block_is_at_the_same_pass() -> None:
    """One round, two callers: a plain pass (one size for all) and a budget round (a size per
    block) over the same blocks give the same verdicts, state and sums."""
    rng = np.random.default_rng(0)
    loops = [PassLoop(VarianceCriterion(0.5), (2, 2), (4, 4), SCHEDULE, 8) for _ in range(2)]
    for k in range(4):
        ids = np.flatnonzero(loops[0].active).tolist()
        noise = np.array([0.0, 0.002, 0.5, 0.5])[ids, None, None, None]   # a flat, a quiet and two noisy blocks
        images = 0.5 + noise * rng.standard_normal((len(ids), 4, 4, 3))
        row0 = loops[0].run_round(ids, [(images, 4)])
        row1 = loops[1].run_round(ids, [(images, np.full(len(ids), 4))])
        np.testing.assert_array_equal(row0, row1)
    assert loops[0].active.tolist() == [False, False, True, True]
    for key in ("active", "stop_spp", "history", "history_spp", "rendered"):
        np.testing.assert_array_equal(getattr(loops[0].state(), key), getattr(loops[1].state(), key))
    assert loops[0].events == loops[1].events
    np.testing.assert_array_equal(loops[0].acc.state()["sum"], loops[1].acc.state()["sum"])


def test_several_passes_in_one_round_are_history_rows_judged_once() -> None:
    """A round of several passes: each pass is a history row (the checkpoint's invariant), the verdicts
    go in the last one, and the sums are those of the passes added one by one."""
    rng = np.random.default_rng(1)
    images = [0.5 + 0.1 * rng.standard_normal((4, 4, 4, 3)) for _ in range(3)]
    # a criterion that can stop and judges every pass (no decide_skip); these blocks stay noisy
    one = PassLoop(VarianceCriterion(1e-6), (2, 2), (4, 4), SCHEDULE, None)
    for img in images:
        one.run_round([0, 1, 2, 3], [(img, 4)])
    grown = PassLoop(VarianceCriterion(1e-6), (2, 2), (4, 4), SCHEDULE, None)
    row = grown.run_round([0, 1, 2, 3], [(img, 4) for img in images])
    assert row.tolist() == [-1] * 4
    assert grown.history.tolist() == [[0] * 4, [0] * 4, [-1] * 4]
    assert grown.history_spp.tolist() == [4, 8, 12] == one.history_spp.tolist()
    assert grown.ledger.counters["decide_calls"] == 1 and one.ledger.counters["decide_calls"] == 3
    np.testing.assert_array_equal(grown.acc.state()["sum"], one.acc.state()["sum"])
    with pytest.raises(ValueError, match="stopped"):
        stopped = PassLoop(OracleCriterion([4, None, None, None]), (2, 2), (4, 4), SCHEDULE, None)
        stopped.run_round([0, 1, 2, 3], [(images[0], 4)])
        stopped.run_round([0, 1], [(images[1][:2], 4)])


def _same(a, b, ra, rb) -> None:
    np.testing.assert_array_equal(read_exr(a / "final.exr"), read_exr(b / "final.exr"))
    assert ra["blocks"] == rb["blocks"] and ra["passes"] == rb["passes"]


def test_a_roomy_budget_renders_what_the_unbudgeted_loop_renders(tmp_path) -> None:
    # a budget that cannot bind (max spp) or is never reached decides as the plain render
    # does, decisions skipped and spaced (the defaults): the same render
    plain = adaptive_render("cornell", tmp_path / "plain", VarianceCriterion(0.3), **TINY)
    assert "budget" not in plain
    spp = adaptive_render("cornell", tmp_path / "spp", VarianceCriterion(0.3), spp_budget=24, **TINY)
    secs = adaptive_render("cornell", tmp_path / "secs", VarianceCriterion(0.3), time_limit=1e6, **TINY)
    for name, rep in (("spp", spp), ("secs", secs)):
        _same(tmp_path / "plain", tmp_path / name, plain, rep)
        assert rep["budget"]["ended"] is False and rep["budget"]["above_target"] == []
        assert rep["budget"]["prioritised_rounds"] == 0 and rep["budget"]["judges_every_unit"] is False


def test_a_tight_budget_goes_to_the_blocks_farthest_from_target(tmp_path) -> None:
    plain = adaptive_render("cornell", tmp_path / "plain", OracleCriterion(THRESHOLDS), **TINY)
    rep = adaptive_render("cornell", tmp_path / "b", OracleCriterion(THRESHOLDS), spp_budget=12, **TINY)
    spp = np.array([b["spp"] for b in rep["blocks"]])
    assert spp.mean() <= 12 and spp.mean() > 12 - 4                 # spent, within one pass
    assert rep["budget"]["ended"] and rep["budget"]["prioritised_rounds"] > 0
    # the oracle's ratio is T_b / spp: censored and late blocks got the samples
    assert spp[4] == spp.max() and spp[15] == spp.max() and spp[4] > 12
    left = rep["budget"]["above_target"]
    assert {x["id"] for x in left} == {b["id"] for b in rep["blocks"] if not b["converged"]}
    ratios = [np.inf if x["ratio"] is None else x["ratio"] for x in left]
    assert ratios == sorted(ratios, reverse=True)
    # a block that stops, stops where it stops without a budget; its history is its own
    for b, p in zip(rep["blocks"], plain["blocks"]):
        if b["converged"]:
            assert b["stop_spp"] == p["stop_spp"]
            assert b["history"] == p["history"][:len(b["history"])]
    saved = json.loads((tmp_path / "b" / "report.json").read_text())
    assert saved["budget"]["above_target"] == left
    assert (tmp_path / "b" / "spp_map.png").stat().st_size > 0


def test_a_budget_is_spent_to_the_last_pass_it_pays_for(tmp_path) -> None:
    rep = adaptive_render("cornell", tmp_path / "u", UniformCriterion(), spp_budget=10, **TINY)
    spp = [b["spp"] for b in rep["blocks"]]
    assert set(spp) == {8, 12} and np.mean(spp) == 10                 # half the blocks get the last pass
    assert rep["budget"]["ended"] and len(rep["budget"]["above_target"]) == 16


@pytest.mark.parametrize("bad", [-1, 0, float("nan"), float("inf"), "12", True, MAX_SPP * 2])
def test_bad_budgets_are_refused_at_each_door_by_one_check(bad) -> None:
    """One check, one message (the render spec's row), at the door: the live render refuses
    the budgets the row does, MAX_SPP included; the simulation behind it checks nothing
    again."""
    from renderer.settings import ROW

    with pytest.raises(ValueError, match="spp_budget must be a finite number in") as one:
        ROW["spp_budget"].check(bad)
    with pytest.raises(ValueError) as live:
        run_adaptive("cornell", UniformCriterion(), spp_budget=bad, **TINY)
    assert str(live.value) == str(one.value)


@pytest.mark.parametrize("value", ["-5", "0", "nan", "abc", "inf"])
def test_bad_spp_budget_is_a_one_line_usage_error(value, tmp_path, capsys) -> None:
    rc, err = run(capsys, "render", "--scene", "cornell", "--out", str(tmp_path / "o"), "--spp-budget", value)
    assert_one_line_error(rc, err, "--spp-budget")


RENDER = ["render", "--scene", "cornell", "--resolution", "32", "--grid", "4", "4", "--step", "4", "--min-spp", "4",
          "--max-spp", "24", "--criterion", "variance", "--threshold", "0.05"]


def test_render_command_takes_a_budget(tmp_path, capsys) -> None:
    """--spp-budget reaches the loop: the command's files are adaptive_render's with the same
    budget, spent to within one pass; control: without it the same render spends more."""
    from learning.data.exr import read_exr_channels
    from service import cli

    out = tmp_path / "o"
    rc = cli.main([*RENDER, "--spp-budget", "8", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert report["budget"]["spp_budget"] == 8.0 and 8 - 4 < report["mean_spp"] <= 8
    assert "budget ended with" in text and report["budget"]["ended"]
    assert read_exr_channels(out / "final.exr")["spp"].mean() == pytest.approx(report["mean_spp"])
    api = adaptive_render("cornell", tmp_path / "api", VarianceCriterion(0.05), spp_budget=8, **TINY)
    _same(out, tmp_path / "api", report, api)
    assert report["budget"]["above_target"] == api["budget"]["above_target"]
    assert cli.main([*RENDER, "--out", str(tmp_path / "free")]) == 0
    free = json.loads((tmp_path / "free" / "report.json").read_text())
    assert "budget" not in free and free["mean_spp"] > 8


def rendered_jobs(monkeypatch, run) -> tuple[dict, list[tuple[int, int]]]:
    """What `run()` returns, and the (block, pass index) jobs it rendered, in order."""
    jobs: list[tuple[int, int]] = []
    real = BlockRenderer.submit_passes

    def counting(self, js, spp, seed):
        jobs.extend((int(b), int(p)) for b, p in js)
        return real(self, js, spp, seed)
    with monkeypatch.context() as m:
        m.setattr(BlockRenderer, "submit_passes", counting)
        return run(), jobs


def assert_resumed(jobs: list[tuple[int, int]], whole: list[tuple[int, int]], passes_saved) -> None:
    """A resume renders no pass its checkpoint holds (block b's first `passes_saved[b]`),
    and with those it renders exactly the uninterrupted run's passes."""
    saved = {(b, p) for b, n in enumerate(passes_saved) for p in range(int(n))}
    assert saved, "the checkpoint holds no pass"
    again = [j for j in jobs if j in saved]
    assert again == [], f"passes rendered again: {again[:5]}"
    assert sorted(saved | set(jobs)) == sorted(whole) and len(jobs) == len(set(jobs))


class CrashingVariance(VarianceCriterion):
    """Dies at its `at`-th decision: a kill in the middle of a budget render."""

    def __init__(self, at: int) -> None:
        super().__init__(0.05)
        self.at = at

    def _decide(self, ids, batch, tally):
        self.calls = getattr(self, "calls", 0) + 1       # the test's own count: a criterion keeps none
        if self.calls == self.at:
            raise RuntimeError("simulated kill")
        return super()._decide(ids, batch, tally)


def test_a_budget_render_resumes_to_the_same_image(tmp_path, monkeypatch) -> None:
    """Killed while it prioritises (blocks at different pass counts), a budget render resumes from its
    last round's checkpoint: the fresh run's image and report, and only the passes the
    checkpoint lacks are rendered. Controls: the checkpoint was written during prioritised
    rounds (the old loop stopped writing them there), and a 'resume' that restarts gives
    the same image but fails the pass count."""
    import shutil

    from learning.data.npz import read_npz

    opts = {**TINY, "checkpoint_every": 0.0, "spp_budget": 12}
    whole, whole_jobs = rendered_jobs(monkeypatch, lambda: adaptive_render(
        "cornell", tmp_path / "b", VarianceCriterion(0.05), **opts))
    assert whole["budget"]["prioritised_rounds"] > 1
    late = whole["counters"]["decide_calls"] - 1                       # the kill: near the end
    with pytest.raises(RuntimeError, match="simulated kill"):
        adaptive_render("cornell", tmp_path / "a", CrashingVariance(late), **opts)
    saved = read_npz(tmp_path / "a" / "checkpoint.npz")
    assert int(saved["budget_prioritised_rounds"]) > 0 and not bool(saved["done"])
    passes_saved = saved["acc_passes"]
    assert 0 < passes_saved.sum() < len(whole_jobs)
    shutil.copytree(tmp_path / "a", tmp_path / "c")
    again, jobs = rendered_jobs(monkeypatch, lambda: adaptive_render(
        "cornell", tmp_path / "a", VarianceCriterion(0.05), resume=True, **opts))
    _same(tmp_path / "a", tmp_path / "b", again, whole)
    assert again["budget"] == whole["budget"]
    assert_resumed(jobs, whole_jobs, passes_saved)
    assert len(jobs) <= 2 * 16                      # what was left: the last rounds, not the render
    restarted, restart_jobs = rendered_jobs(monkeypatch, lambda: adaptive_render(
        "cornell", tmp_path / "c", VarianceCriterion(0.05), resume=False, **opts))
    _same(tmp_path / "c", tmp_path / "b", restarted, whole)           # the image cannot tell
    with pytest.raises(AssertionError, match="passes rendered again"):
        assert_resumed(restart_jobs, whole_jobs, passes_saved)


def test_the_budget_simulated_on_a_stack(tmp_path) -> None:
    from learning import make_synthetic_stack
    from renderer.simulation.simulate import simulate_budget
    from renderer.simulation.simulate import simulate_stack

    spp = [32 * (k + 1) for k in range(12)]
    st = make_synthetic_stack(tmp_path / "s", size=64, spp=spp, seed=1, label=False)
    plain = simulate_stack(st, VarianceCriterion(0.2), min_spp=32)
    roomy = simulate_budget(st, VarianceCriterion(0.2), spp_budget=spp[-1], min_spp=32)
    stops = [spp[int(np.argmax(plain[:, b] > 0))] if (plain[:, b] > 0).any() else spp[-1] for b in range(16)]
    assert roomy["spp"] == stops and not roomy["budget"]["ended"]
    late = [64, 96, 128, 384, None, 64, 256, 96, 320, 64, 96, 128, 384, 256, 96, None]
    tight = simulate_budget(st, OracleCriterion(late), spp_budget=160, min_spp=32)
    assert 160 - 32 < np.mean(tight["spp"]) <= 160 and tight["budget"]["ended"]
    assert tight["spp"][4] == tight["spp"][15] == max(tight["spp"]) > 160     # the censored blocks got most
    assert all(s == t for s, t, c in zip(tight["spp"], late, tight["converged"]) if c)


def test_a_time_budget_prioritises_once_the_time_left_will_not_cover_every_block() -> None:
    loop = PassLoop(OracleCriterion([8, 64, None, 16]), (2, 2), (4, 4), schedule(4, 64), 4)   # 16 passes
    loop.run_round([0, 1, 2, 3], [(np.full((4, 4, 4, 3), 0.5), [4] * 4)])       # ratios T/spp: 2, 16, inf, 4
    budget = Budget(time_limit=100.0)
    assert budget.select(loop, elapsed=90.0) == [0, 1, 2, 3]         # no rate known yet
    budget.record(1.0, 16)                                                  # 1/16 s per block-spp
    assert budget.select(loop, elapsed=50.0) == [0, 1, 2, 3]         # 800 block-spp left >= 240 needed
    assert budget.select(loop, elapsed=90.0) == [2]                  # 160 left: the censored block first
    assert budget.prioritised_rounds == 1 and not budget.ended
    loop.ratios.put([2], [1.5], 4)                                          # now finite: the band decides
    assert budget.select(loop, elapsed=90.0) == [1]                  # 16/2 = 8 > 0.8 x others
