"""One decision route: evaluate, the simulation, the live loop and the HTTP service stop the
same blocks at the same spp, for the same model, offset and stack (a flat block included);
and the flip criterion's stored-stack route agrees with the simulation and the live loop."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from learning import read_stack, write_stack
from learning.models.bundle import load_model, save_model
from learning.evaluation.evaluate import evaluate_model, stops_by_scene
from learning.data.accumulator import UnitAccumulator
from learning.inputs.halves import flip_offset, guarded_flip_scores, recover_passes, stack_flip_errors
from learning.evaluation.metrics import stop_thresholds
from learning.stoprule import StopRule, decide_active
from learning.inputs.halves import stack_flat
from learning.inputs.table import load_table
from learning.training.train import train_model
from renderer.client.remote import RemoteModel
from renderer.criteria import FlipCriterion, ModelCriterion
from renderer.simulation.simulate import evaluate_criterion, simulate_loop, simulate_stack
from tests.support.local_server import LocalServer
from tests.support.stack_renderer import live
from tests.support import FIXTURE_DATASET as FIXTURE

MIN_SPP = 96
FLAT_BLOCK = 5


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The fixture dataset, with block 5 of 'cornell' made flat (a constant grey) in every
    level: the model's score for it means nothing, the rule must stop it at once."""
    root = tmp_path_factory.mktemp("route") / "data"
    for s in ("checker", "cornell_dark", "sky"):
        shutil.copytree(FIXTURE / s, root / s, ignore=shutil.ignore_patterns(".cache"))
    st = read_stack(FIXTURE / "cornell")
    (r0, r1), (c0, c1) = [(i * n, (i + 1) * n) for i, n in zip(divmod(FLAT_BLOCK, st.grid[1]), st.block)]

    def flatten(img):
        img = img.copy()
        img[r0:r1, c0:c1] = 0.35
        return img
    write_stack(root / "cornell", scene="cornell", levels=[flatten(st.level(k)) for k in range(st.n_levels)],
                spp=st.spp, reference=flatten(st.reference()), quick=st.quick(), reference_spp=st.reference_spp,
                quick_description=st.quick_description, grid=st.grid, labeler=st.labeler,
                thresholds=st.thresholds)
    return root


@pytest.fixture(scope="module", params=["none", "halves"])
def model(data, tmp_path_factory, request):
    """A feature model on the current block alone (the paper's input with quick 'none') and
    one on the half buffers (`halves`): both must decide the same way on every route."""
    table = load_table(data, progress=False, quick=request.param)
    est, summary = train_model("dsvm", str(data), table=table, test_scenes=["cornell"], cv=False,
                               quick=request.param, progress=False)
    path = save_model(est, tmp_path_factory.mktemp("m") / "m", kind="dsvm", input="features",
                      training=summary, extra={"quick": request.param})
    return load_model(path)


@pytest.fixture(scope="module")
def server(model):
    """`noisestop serve` with that model, in its own process on loopback."""
    with LocalServer({"m": str(model.path)}) as s:
        yield s


def offset_that_splits(model, table) -> float:
    """An offset (not the model's own) at which some non-flat cornell blocks stop and some do
    not: otherwise agreement would prove little."""
    scores = model.decision_function(table.X)
    for off in np.quantile(scores[~table.flat], [0.6, 0.5, 0.7, 0.4, 0.8]):
        V = stops_by_scene(table, scores, model.rule(float(off), MIN_SPP))["cornell"][0]
        stopped = (V[-1] > 0)
        stopped[FLAT_BLOCK] = False
        if 2 <= stopped.sum() <= 13:
            return float(off)
    raise AssertionError("no informative offset on the fixture")


def spp_from_report(report) -> list[int]:
    return [b["spp"] if b["converged"] else -1 for b in report["blocks"]]


def stop_spp(V, spp) -> list[int]:
    t = stop_thresholds(V, spp)
    return [int(x) if x <= spp[-1] else -1 for x in t]


def test_model_stops_agree_on_every_route(data, model, server, monkeypatch, tmp_path):
    table = load_table(data, progress=False, quick=model.quick, scenes=["cornell"])
    stack = table.stacks["cornell"]
    assert table.flat.reshape(stack.n_levels, -1)[:, FLAT_BLOCK].all()
    off = offset_that_splits(model, table)

    # 1. evaluate --criterion model: the rule on the stored scores
    V_eval = stops_by_scene(table, model.decision_function(table.X), model.rule(off, MIN_SPP))["cornell"][0]
    truth = stop_spp(V_eval, stack.spp)
    assert truth[FLAT_BLOCK] == MIN_SPP                              # flat: at the first decision
    # 2. the simulation on the stack (the criterion code the live loop runs)
    V_sim, sim = simulate_loop(stack, ModelCriterion(model, offset=off), min_spp=MIN_SPP)
    assert stop_spp(V_sim, stack.spp) == truth
    assert sim.ledger.counters["flat_units"] >= 1
    # 3. the live loop, fed the stack's passes
    report, _ = live(monkeypatch, tmp_path, stack, ModelCriterion(model, offset=off), MIN_SPP)
    assert spp_from_report(report) == truth and report["offset"] == off
    # 4. the HTTP service, asked about every active block (flat ones too) as a Triton client
    #    would, the stops held on the client side
    remote = RemoteModel(server.url, model="m", token=server.token)
    assert remote.needs_halves == model.needs_halves
    active, stops = np.ones(stack.n_blocks, bool), [-1] * stack.n_blocks
    acc = UnitAccumulator(stack.grid, stack.block)
    for k, _, n, pass_img in recover_passes(stack):
        s, means = stack.spp[k], stack.blocks(k)
        acc.add_many(list(range(stack.n_blocks)), stack.split(pass_img), n)

        def ask(ids: list[int]) -> np.ndarray:
            if not model.needs_halves:
                return remote.score_blocks(means[ids], offset=off)[0]
            halves = [acc.half_buffer(b) for b in ids]
            return remote.score_halves(np.stack([h[0] for h in halves]).astype(np.float32),
                                       np.stack([h[1] for h in halves]).astype(np.float32), offset=off)[0]
        row = decide_active(active, s, MIN_SPP, ask)
        for b in np.flatnonzero(row > 0):
            stops[b] = s
    assert stops == truth
    # 5. the live loop asking that server (`render --server URL --offset X`)
    report, _ = live(monkeypatch, tmp_path, stack, ModelCriterion(remote, offset=off), MIN_SPP, "remote")
    assert spp_from_report(report) == truth
    # and the metrics of the evaluate command equal the simulation's
    m_eval = evaluate_model(model, table, offset=off, min_spp=MIN_SPP)
    m_sim = evaluate_criterion([stack], lambda st: ModelCriterion(model, offset=off), min_spp=MIN_SPP)
    for k in ("precision", "early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform"):
        assert m_eval[k] == m_sim[k], k


@pytest.mark.slow
def test_the_evaluate_command_reports_the_same_stops(data, model):
    """`noisestop evaluate --criterion model --offset X` (the command itself) against the rule."""
    table = load_table(data, progress=False, quick=model.quick, scenes=["cornell"])
    off = offset_that_splits(model, table)
    out = subprocess.run([sys.executable, "-m", "service.cli", "evaluate", "--data", str(data), "--model",
                          str(model.path), "--scenes", "cornell", "--offset", str(off), "--min-spp",
                          str(MIN_SPP), "--json"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    want = evaluate_model(model, table, offset=off, min_spp=MIN_SPP)
    assert got["offset"] == off
    for k in ("precision", "early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform"):
        assert got[k] == pytest.approx(want[k], abs=1e-12), k
    assert got["per_scene"]["cornell"]["early_stop_rate"] == pytest.approx(want["early_stop_rate"])


def test_flip_stops_agree_on_every_route(data, monkeypatch, tmp_path):
    stack = read_stack(data / "cornell")
    e = stack_flip_errors(stack)
    assert np.isnan(e[0]).all() and np.isnan(e[:, FLAT_BLOCK]).all()      # one pass; flat: FLIP not run
    measured = np.delete(e[1:], FLAT_BLOCK, axis=1)
    assert np.isfinite(measured).all() and (measured >= 0).all()
    # half the blocks end below c, taken midway between two scores: a c equal to a score
    # would let the routes' FLIP (batched differently; equal to 1e-6, test_flip) and
    # another CPU's matmul rounding decide that block's stop
    last = np.sort(e[-1][np.isfinite(e[-1])])
    c = float(last[len(last) // 2 - 1] + last[len(last) // 2]) / 2
    assert np.abs(measured - c).min() > 1e-6                # no decision within rounding of c
    rule = StopRule(flip_offset(c))
    # the criterion's scores as the live loop makes them: -e, held by the dot guard
    truth = stop_spp(rule.stops(guarded_flip_scores(stack), stack.spp, stack_flat(stack)), stack.spp)
    assert truth[FLAT_BLOCK] == stack.spp[0]             # flat: at the first level, halves or not
    assert 2 <= sum(t > 0 for t in truth) <= 14
    V_sim, sim = simulate_loop(stack, FlipCriterion(c))
    assert stop_spp(V_sim, stack.spp) == truth
    assert sim.ledger.timers["decisions_s"] > 0 and sim.ledger.counters["units_featured"] > 0
    report, renderer = live(monkeypatch, tmp_path, stack, FlipCriterion(c), int(stack.spp[0]))
    assert spp_from_report(report) == truth and report["threshold"] == c
    # converged blocks were never rendered again
    for k, ids in enumerate(renderer.calls[1:], 1):
        assert all(truth[b] < 0 or truth[b] >= stack.spp[k] for b in ids)
