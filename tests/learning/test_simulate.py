"""Simulation on stacks: exact pass / half-buffer recovery, live-loop agreement, metrics."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from learning import make_synthetic_stack, write_stack
from learning.models.bundle import load_model, save_model
from learning.models.estimators import DSVM
from learning.inputs.table import stack_features
from noisefeat import split_blocks
from learning.data.accumulator import UnitAccumulator
from renderer.criteria import ModelCriterion, OracleCriterion, UniformCriterion, VarianceCriterion
from learning.inputs.halves import recover_passes
from learning.data.dataset_dir import find_stack
from renderer.simulation.simulate import criterion_factory, evaluate_criterion, evaluate_criterion_cli, simulate_loop, simulate_stack
from tests.support.stack_renderer import live

GRID = (4, 4)
STEP = 8
SPP = [STEP * (k + 1) for k in range(12)]  # constant step, like rendered stacks


class MemStack:
    """The parts of `learning.Stack` the simulation reads, held in memory in float64."""

    def __init__(self, levels, spp, grid=GRID, quick=None, scene="mem"):
        self.levels_, self.spp, self.grid, self.scene = levels, list(spp), tuple(grid), scene
        self.height, self.width = levels.shape[1:3]
        self.block = (self.height // grid[0], self.width // grid[1])
        self.quick_ = quick if quick is not None else np.full(levels.shape[1:], 0.5)
        self.path = Path("/mem") / scene
        self.thresholds = None

    n_levels = property(lambda self: len(self.spp))
    n_blocks = property(lambda self: self.grid[0] * self.grid[1])

    def level(self, k):
        return self.levels_[k]

    def quick(self):
        return self.quick_

    def split(self, img):
        return split_blocks(img, self.grid)


def random_passes(n_passes=7, size=16, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.gamma(2.0, 0.2, (size, size, 3)) for _ in range(n_passes)]


def feed(acc, passes, step=STEP):
    """Feed full-frame passes, block by block, and return the cumulative means after each."""
    levels = []
    for p in passes:
        blocks = split_blocks(p, acc.grid)
        for b in range(acc.n_units):
            acc.add(b, blocks[b], step)
        levels.append(acc.image())
    return np.stack(levels)


def test_half_buffers_recovered_exactly_from_float64_levels():
    passes = random_passes()
    truth = UnitAccumulator(GRID, (4, 4))
    levels = feed(truth, passes)
    stack = MemStack(levels, SPP[:len(passes)])
    got = [p for _, _, n, p in recover_passes(stack)]
    assert all(n == STEP for _, _, n, _ in recover_passes(stack))
    for p, q in zip(got, passes):
        np.testing.assert_allclose(p, q, rtol=0, atol=1e-13)
    replay = UnitAccumulator(GRID, (4, 4))
    feed(replay, got)
    for b in range(16):
        for h_true, h_got in zip(truth.half_buffer(b), replay.half_buffer(b)):
            np.testing.assert_allclose(h_got, h_true, rtol=0, atol=1e-13)
        assert replay.half_spp(b) == truth.half_spp(b) == (32, 24)


def test_half_buffers_from_a_float32_stack_on_disk(tmp_path):
    passes = random_passes(5, seed=1)
    truth = UnitAccumulator(GRID, (4, 4))
    levels = feed(truth, passes)
    st = write_stack(tmp_path / "s", scene="s", levels=list(levels.astype(np.float32)), spp=SPP[:5],
                     reference=levels[-1].astype(np.float32), quick=None, reference_spp=400)
    replay = UnitAccumulator(GRID, (4, 4))
    feed(replay, [p for _, _, _, p in recover_passes(st)])
    for b in range(16):
        a_true, b_true = truth.half_buffer(b)
        a_got, b_got = replay.half_buffer(b)
        np.testing.assert_allclose(a_got, a_true, rtol=1e-5, atol=1e-6)  # float32 storage only
        np.testing.assert_allclose(b_got, b_true, rtol=1e-5, atol=1e-6)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return make_synthetic_stack(tmp_path_factory.mktemp("synth") / "synthetic", size=64, spp=SPP, seed=5)


def test_oracle_simulation_reproduces_the_labels(synth):
    V = simulate_stack(synth, OracleCriterion(synth.thresholds))
    np.testing.assert_array_equal(V, synth.labels())
    V16 = simulate_stack(synth, OracleCriterion(synth.thresholds), min_spp=32)
    assert (V16[:3] == -1).all()                       # no decision below min_spp (8, 16, 24)
    np.testing.assert_array_equal(V16[3:], synth.labels()[3:])


def test_converged_blocks_stay_converged_and_are_not_asked_again(synth):
    crit = VarianceCriterion(0.08)
    V, loop = simulate_loop(synth, crit, min_spp=16, decide_skip=0.0, decide_growth=0.0)   # every pass judged
    assert V.dtype == np.int8 and set(np.unique(V)) <= {-1, 1}
    assert (np.diff(V, axis=0) >= 0).all()              # monotone per block
    active_before = [(V[k - 1] < 0).sum() if k else 16 for k in range(len(SPP))]
    asked = sum(a for k, a in enumerate(active_before) if SPP[k] >= 16)
    assert loop.ledger.counters["units_asked"] == asked
    assert 0 < (V[-1] > 0).sum() < 16                   # the test is informative on this stack


def train(tmp_path):
    st = make_synthetic_stack(tmp_path / "train", size=64, seed=11)
    x = stack_features(st)
    est = DSVM(C=10.0).fit(x.reshape(-1, x.shape[-1]), st.labels().reshape(-1))
    return load_model(save_model(est, tmp_path / "model", kind="dsvm", input="features"))


@pytest.mark.parametrize("kind", ["oracle", "variance", "model"])
def test_simulation_and_live_loop_agree(monkeypatch, tmp_path, synth, kind):
    model = train(tmp_path) if kind == "model" else None

    def make():
        if kind == "oracle":
            return OracleCriterion(synth.thresholds)
        if kind == "variance":
            return VarianceCriterion(0.08)
        return ModelCriterion(model)

    V, sim = simulate_loop(synth, make(), min_spp=16)
    report, renderer = live(monkeypatch, tmp_path, synth, make(), min_spp=16)
    # same stops, block by block
    for b, blk in enumerate(report["blocks"]):
        first = np.flatnonzero(V[:, b] > 0)
        assert blk["converged"] == bool(first.size), b
        assert blk["spp"] == (SPP[first[0]] if first.size else SPP[-1]), b
    # the live loop rendered exactly the blocks the simulation still had active
    active = [np.flatnonzero(V[k - 1] < 0).tolist() if k else list(range(16)) for k in range(len(SPP))]
    assert renderer.calls == active[:len(renderer.calls)]
    assert report["counters"]["blocks_rendered_per_pass"] == [len(c) for c in renderer.calls]
    assert report["counters"]["decisions"] == sim.ledger.counters["units_asked"]
    if kind == "model":
        assert report["counters"]["blocks_featured"] == sim.ledger.counters["units_featured"] > 0


def test_evaluate_criterion_metrics(tmp_path, synth):
    oracle = evaluate_criterion([synth], lambda st: OracleCriterion(st.thresholds))
    assert oracle["precision"] == 1.0 and oracle["early_stop_rate"] == 0.0
    assert oracle["spp_ratio_vs_oracle"] == pytest.approx(1.0)
    assert oracle["criterion"] == {"name": "oracle"}
    uniform = evaluate_criterion(synth.path.parent, lambda st: UniformCriterion())
    assert uniform["saved_vs_uniform"] == 0.0 and uniform["early_stop_rate"] == 0.0
    assert set(uniform["per_scene"]) == {"synthetic"}
    # a criterion that never stops is asked once per block, at its last pass (Criterion.stops)
    assert uniform["counters"]["blocks_asked"] == 16
    var = evaluate_criterion(synth, lambda st: VarianceCriterion(0.08))
    assert 0.0 < var["saved_vs_uniform"] < 1.0
    assert var["spp_ratio_vs_oracle"] > 0


def test_nonfinite_levels_give_defined_verdicts(tmp_path):
    passes = random_passes(6, seed=2)
    acc = UnitAccumulator(GRID, (4, 4))
    levels = feed(acc, passes).astype(np.float32)
    levels[2, 0, 0] = [np.nan, np.inf, 1.0]                 # one broken pixel in level 2
    st = write_stack(tmp_path / "nan", scene="nan", levels=list(levels), spp=SPP[:6],
                     reference=levels[-1], quick=None, reference_spp=400)
    V, loop = simulate_loop(st, VarianceCriterion(0.5))
    assert set(np.unique(V)) <= {-1, 1}
    assert loop.ledger.counters["nonfinite_units"] >= 1


def test_find_stack(tmp_path, synth):
    assert find_stack(synth.path.parent, "synthetic").scene == "synthetic"
    assert find_stack(synth, "any") is synth
    with pytest.raises(ValueError, match="not 'cornell'"):
        find_stack(synth.path.parent, "cornell")


def test_criterion_factory_for_the_evaluate_command(synth):
    by_name = evaluate_criterion(synth, criterion_factory("oracle"))
    assert by_name["precision"] == 1.0 and by_name["spp_ratio_vs_oracle"] == pytest.approx(1.0)
    var = evaluate_criterion(synth, criterion_factory("variance", threshold=0.08))
    assert var["criterion"]["threshold"] == 0.08
    with pytest.raises(ValueError, match="criterion must be one of"):
        criterion_factory("bogus")
    cli = evaluate_criterion_cli(synth.path.parent, "variance", ["synthetic"], threshold=0.08,
                                 progress=False)
    assert cli["precision"] == var["precision"] and set(cli["per_scene"]) == {"synthetic"}
    with pytest.raises(ValueError, match="no stack of scene.*kitchen"):
        evaluate_criterion_cli(synth.path.parent, "uniform", ["kitchen"])


@pytest.mark.parametrize("bad,message", [({"min_spp": 0}, "min_spp must be a whole number"),
                                         ({"decide_skip": 1.5}, "decide_skip must be a finite number"),
                                         ({"decide_growth": -0.1}, "decide_growth must be a finite number")])
def test_the_simulation_door_refuses_bad_settings_before_reading_a_stack(tmp_path, bad, message):
    """The simulation's door checks its settings by their rows (the loop behind it does
    not check them again): a bad one fails before any stack is read (here: none exists)."""
    with pytest.raises(ValueError, match=message):
        evaluate_criterion_cli(tmp_path / "nowhere", "uniform", **bad)
