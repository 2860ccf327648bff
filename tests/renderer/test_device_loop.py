"""The device-resident loop: the same stops and image as the host loop it replaced,
grown passes that change nothing but the launches, FLIP where the half buffers live, and no
state leaking from one render into the next."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from renderer.live.adaptive import run_adaptive
from renderer.criteria import UnitBatch, FlipCriterion, OracleCriterion
from renderer.live.launches import grown_passes
from tests.support import passloop_golden as golden

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "fixtures" / "passloop_golden.npz"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def variant() -> str:
    from learning.data.variant import select_variant

    return select_variant()


def golden_failures(name: str, r, log: golden.DecisionLog) -> list[str]:
    """What keeps render `r` of case `name` from the recorded one, [] if nothing: stops
    equal, the image within `golden.IMAGE_RTOL`, every decision at least `golden.MARGIN`
    from its threshold (else equal stops here say nothing about another CPU)."""
    with np.load(GOLDEN) as g:
        spp, image = g[f"{name}/block_spp"], g[f"{name}/image"]
    out = []
    got = [b["spp"] for b in r.report["blocks"]]
    if got != spp.tolist():
        out.append(f"{name}: stops {got} != recorded {spp.tolist()}")
    bad, rel = golden.image_mismatch(r.image, image)
    if bad:
        out.append(f"{name}: {bad} pixels beyond the float32 bound (largest relative difference {rel:.2e} > "
                   f"{golden.IMAGE_RTOL:.2e})")
    if log.margin < golden.MARGIN:
        out.append(f"{name}: a decision sat {log.margin:.2e} from its threshold (relative), under the bound "
                   f"{golden.MARGIN:.2e}: its stop could flip on another CPU; choose the case's threshold anew")
    return out


@pytest.mark.parametrize("case", [c[0] for c in golden.CASES])
@pytest.mark.parametrize("grow", [True, False])
def test_the_device_loop_gives_the_host_loops_stops_and_image(variant, case, grow) -> None:
    """tests/fixtures/passloop_golden.npz holds what the host loop (numpy accumulators, one
    pass per launch) gave on llvm_ad_rgb on an Intel Xeon; the device loop must give the
    same stops and the same image to float32 rounding on any x86-64 CPU
    (`tests.support.passloop_golden`: the bound, and why it holds)."""
    if variant != "llvm_ad_rgb":
        pytest.skip(f"recorded on llvm_ad_rgb; {variant} traces other samples")
    log = golden.DecisionLog()
    r = golden.render_case(case, grow, log)
    with np.load(GOLDEN) as g:
        spp = g[f"{case}/block_spp"]
    assert len(set(spp.tolist())) > 1 or case == "cornell_budget"     # the cases do stop blocks apart
    assert not golden_failures(case, r, log)


@pytest.mark.parametrize("fault", ["twice", "dropped"])
def test_a_loop_that_adds_a_pass_twice_or_drops_one_fails_the_golden_check(variant, fault, monkeypatch) -> None:
    """The control of the tolerance: the accumulator's fifth pass added twice (counted as
    two passes, so it stands in for the next), or dropped (counted, its samples lost), and
    the image leaves the float32 bound (the stops change too)."""
    if variant != "llvm_ad_rgb":
        pytest.skip(f"recorded on llvm_ad_rgb; {variant} traces other samples")
    from learning.data.accumulator import UnitAccumulator

    add, calls = UnitAccumulator.add_batch, []

    def faulty(self, ids, images, spp):
        calls.append(1)
        if len(calls) == 5:
            if fault == "dropped":
                self._pass_counts[np.asarray(ids, np.int64)] += 1   # the loop moves on without them
                return torch.zeros(len(ids), dtype=torch.int64)
            add(self, ids, images, spp)
        return add(self, ids, images, spp)

    monkeypatch.setattr(UnitAccumulator, "add_batch", faulty)
    log = golden.DecisionLog()
    r = golden.render_case("cornell_flip", False, log)
    failures = golden_failures("cornell_flip", r, log)
    assert any("beyond the float32 bound" in f for f in failures), failures
    monkeypatch.undo()
    bad, _ = golden.image_mismatch(golden.render_case("cornell_flip", False).image,
                                   np.load(GOLDEN)["cornell_flip/image"])
    assert bad == 0                                     # and without the fault it passes


def test_the_margin_check_names_a_case_that_sits_on_its_threshold() -> None:
    """A decision within rounding of its threshold is reported with the case's name (the
    check cannot pass vacuously: a log with such a value fails it)."""
    log = golden.DecisionLog([np.array([0.5, 1.0 + golden.MARGIN / 2, np.nan])])
    assert log.margin == pytest.approx(golden.MARGIN / 2)
    r = type("R", (), {"report": {"blocks": []}, "image": np.zeros((1, 1, 3), np.float32)})()
    assert any("cornell_flip: a decision sat" in f for f in golden_failures("cornell_flip", r, log))


def test_grown_passes_keep_the_result_and_save_launches(variant) -> None:
    """Once few blocks are active, a launch traces several passes, and the next launch is
    queued while this one is judged (`RenderSession.advance`): fewer launches, the same stops,
    history and image; the passes queued for blocks that then stopped are traced and
    dropped, and counted. A control: without growth the launches are one per pass, and
    nothing is traced that is not kept."""
    kw = {"resolution": 64, "block": 16, "step": 4, "min_spp": 8, "max_spp": 96, "progress": False}
    runs = {g: run_adaptive("cornell", "flip", tau=golden.NO_DOTS, threshold=0.2, grow=g, **kw)
            for g in (True, False)}
    grown, fixed = runs[True].report, runs[False].report
    assert [b["spp"] for b in grown["blocks"]] == [b["spp"] for b in fixed["blocks"]]
    assert [b["history"] for b in grown["blocks"]] == [b["history"] for b in fixed["blocks"]]
    np.testing.assert_array_equal(runs[True].image, runs[False].image)
    assert fixed["render_calls"]["kernel_launches"] == fixed["passes"]
    assert grown["render_calls"]["kernel_launches"] < fixed["render_calls"]["kernel_launches"]
    assert grown["passes"] == fixed["passes"]
    spent = fixed["samples_spent"]
    assert fixed["render_calls"]["samples_traced"] == spent == grown["samples_spent"]
    assert grown["render_calls"]["samples_traced"] > spent        # queued for blocks that stopped


def test_the_growth_rule() -> None:
    assert grown_passes(256, 256, 60) == 1                   # every block active: one pass
    assert grown_passes(256, 100, 60) == 2                   # fewer than half: two, even
    assert grown_passes(256, 60, 60) == 4                    # 256 // 60 = 4
    assert grown_passes(256, 50, 60) == 4                    # 5 made even
    assert grown_passes(256, 1, 3) == 3                      # capped by the passes left
    assert grown_passes(256, 1, 60, grow=False) == 1
    # while no unit can be judged, the passes up to the first that judges one, within the lane cap
    assert grown_passes(256, 256, 60, undecided=9, lane_cap=8) == 8
    assert grown_passes(256, 256, 60, undecided=5, lane_cap=8) == 5
    assert grown_passes(256, 256, 3, undecided=5, lane_cap=8) == 3   # the passes left
    assert grown_passes(256, 60, 60, undecided=2, lane_cap=8) == 4   # growth by stops still holds
    assert grown_passes(256, 256, 60, grow=False, undecided=9, lane_cap=8) == 1


def test_passes_ahead_of_decisions_that_may_stop_units_waste_little() -> None:
    """`ahead_passes`: with no unit that may stop, the cap; a unit judged at the first pass of a
    256-unit launch costs at most its k - 1 later passes, within 1/16 of the launch; many such
    units hold the launch to one pass."""
    from renderer.live.launches import WASTE_SHARE, ahead_passes

    assert ahead_passes(np.array([], np.int64), 256, 8) == 8
    assert ahead_passes(np.zeros(10, np.int64), 256, 8) == 8          # 10 x 7 <= 256 x 8 / 16
    assert ahead_passes(np.zeros(100, np.int64), 256, 8) == 1         # 100 (k - 1) > 16 k for every k > 1
    assert ahead_passes(np.full(100, 3), 256, 8) == 4                 # judged at the 4th pass: 4 waste nothing
    k = ahead_passes(np.zeros(20, np.int64), 256, 64)
    assert 20 * (k - 1) <= WASTE_SHARE * 256 * k < 20 * k             # the largest k within the share


def test_passes_before_a_due_decision_share_a_launch(variant) -> None:
    """No decision can stop a unit before it is due (`PassLoop.due_pass`), so the passes up to
    it go in one launch from the first pass on, every unit still active: fewer launches, the
    same stops, history and image as one launch per pass. The uniform baseline, which never
    stops, is asked once per unit at its last pass and traces its passes in one launch. A
    control: judging every pass (decide_skip 0), each decision one that may stop a unit
    (`NEAR` infinite), gives one launch per pass while all are active."""
    kw = {"resolution": 64, "block": 16, "step": 4, "min_spp": 8, "max_spp": 96, "progress": False}
    runs = {g: run_adaptive("cornell", "flip", tau=0.02, grow=g, **kw) for g in (True, False)}
    grown, fixed = runs[True].report, runs[False].report
    assert [b["spp"] for b in grown["blocks"]] == [b["spp"] for b in fixed["blocks"]]
    assert [b["history"] for b in grown["blocks"]] == [b["history"] for b in fixed["blocks"]]
    np.testing.assert_array_equal(runs[True].image, runs[False].image)
    assert fixed["render_calls"]["kernel_launches"] == fixed["passes"] == 24
    assert grown["render_calls"]["kernel_launches"] <= 0.6 * fixed["passes"]
    # far from their target (ratio above NEAR) units are judged within a launch; were every
    # decision one that may stop a unit, each pass judged would end its launch
    import renderer.live.session as session_module
    with pytest.MonkeyPatch.context() as m:
        m.setattr(session_module, "NEAR", math.inf)
        every = run_adaptive("cornell", "flip", tau=0.02, decide_skip=0.0, decide_growth=0.0, **kw).report
    first_stop = min([b["spp"] for b in every["blocks"] if b["converged"]], default=96)
    assert every["render_calls"]["kernel_launches"] >= first_stop // 4 - 1
    uni = {g: run_adaptive("cornell", "uniform", grow=g, **kw) for g in (True, False)}
    assert uni[True].report["render_calls"]["kernel_launches"] == 1
    assert uni[False].report["render_calls"]["kernel_launches"] == 24
    assert uni[True].report["counters"]["decisions"] == 16 == len(uni[True].report["blocks"])   # once a block
    np.testing.assert_array_equal(uni[True].image, uni[False].image)


def test_flip_on_the_accumulators_device_matches_flip_evaluator() -> None:
    """The flip criterion's FLIP runs on the half buffers' device (`flip_halves_tensor`);
    on the fixture dataset's stacks it is within 1e-3 of flip-evaluator (to float32
    rounding in fact), and it returns a tensor where its inputs live."""
    from learning.data.dataset_dir import read_stacks
    from learning.inputs.halves import halves_flip_evaluator, iter_stack_halves
    from noisefeat.flip import flip_halves_tensor

    worst, n = 0.0, 0
    for st in read_stacks(ROOT / "tests" / "fixtures" / "dataset"):
        for k, even, odd in iter_stack_halves(st):
            if k % 3:
                continue
            got = flip_halves_tensor(torch.from_numpy(even), torch.from_numpy(odd))
            assert isinstance(got, torch.Tensor) and got.dtype == torch.float64
            worst = max(worst, float(np.abs(got.numpy() - halves_flip_evaluator(even, odd)).max()))
            n += len(even)
    assert n > 100 and worst < 1e-3


def test_the_flip_criterion_judges_a_batch_without_host_blocks() -> None:
    """A batch read lazily from an accumulator: the criterion asks for the half buffers
    only; verdicts and ratios come back per block."""
    from learning.data.accumulator import UnitAccumulator

    rng = np.random.default_rng(0)
    acc = UnitAccumulator((1, 3), (16, 16))
    for _ in range(2):
        acc.add_batch([0, 1, 2], np.stack([np.full((16, 16, 3), 0.5),                 # flat
                                           0.5 + 0.01 * rng.standard_normal((16, 16, 3)),    # quiet
                                           0.5 + 0.4 * rng.standard_normal((16, 16, 3))]), 8)
    batch = UnitBatch.from_accumulator(acc, [0, 1, 2])
    crit = FlipCriterion(c=0.05)
    d = crit.decide([0, 1, 2], batch)
    assert d.verdict.tolist() == [1, 1, -1]
    assert d.ratio[0] == 0.0 and d.ratio[2] > 1.0
    assert d.counts["flat_units"] == 1 and d.counts["units_featured"] == 2


def test_a_reused_criterion_carries_nothing_into_the_next_render() -> None:
    """simulate_budget twice with one criterion object: the second render is the first
    (ratios of the first render used to reorder the second's rounds)."""
    from learning import make_synthetic_stack
    from renderer.simulation.simulate import simulate_budget

    st = make_synthetic_stack(Path(__import__("tempfile").mkdtemp()) / "s", size=32, spp=tuple(range(8, 200, 8)))
    late = [None if b % 5 == 0 else 8 * (1 + b % 7) for b in range(st.n_blocks)]
    crit = OracleCriterion(late)
    first = simulate_budget(st, crit, spp_budget=40, min_spp=8)
    second = simulate_budget(st, crit, spp_budget=40, min_spp=8)
    assert first == second and first["budget"]["prioritised_rounds"] > 0


def test_block_renderer_puts_the_kernel_history_flag_back(variant) -> None:
    if not variant.startswith(("llvm", "cuda")):
        pytest.skip("the flag exists on JIT variants only")
    import drjit as dr

    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene

    dr.set_flag(dr.JitFlag.KernelHistory, False)
    with BlockRenderer(load_scene("cornell", 32), grid=(2, 2)) as br:
        assert dr.flag(dr.JitFlag.KernelHistory)          # on while it counts compilations
        br.render_units([0, 3], 4, seed=0)
    assert not dr.flag(dr.JitFlag.KernelHistory)
    run_adaptive("cornell", "uniform", resolution=32, grid=(2, 2), step=4, min_spp=4, max_spp=8, progress=False)
    assert not dr.flag(dr.JitFlag.KernelHistory)          # and after a whole render


def test_render_honours_the_scenes_own_plugin_properties(variant) -> None:
    """renderer.render on an mi.Scene whose integrator is the noisestop plugin renders with
    the plugin's properties; arguments given to render win. A control: the same scene
    with a plain integrator renders with render's defaults."""
    import mitsuba as mi

    import renderer

    renderer.register()
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 64
    plain = mi.load_dict(d)
    d["integrator"] = {"type": "noisestop", "block": 32, "max_spp": 48, "step": 8, "min_spp": 8,
                       "criterion": "uniform", "integrator": d["integrator"]}
    scene = mi.load_dict(d)
    r = renderer.render(scene, progress=False)
    assert (r.report["block"], r.report["max_spp"], r.report["step"]) == ([32, 32], 48, 8)
    assert r.report["criterion"]["name"] == "uniform" and int(r.spp.min()) == 48
    mine = renderer.render(scene, progress=False, max_spp=16, step=8)
    assert mine.report["max_spp"] == 16 and mine.report["block"] == [32, 32]
    control = renderer.render(plain, progress=False, max_spp=16, step=8)
    assert control.report["block"] == [64, 64] and control.report["criterion"]["name"] == "flip"


def test_a_min_spp_below_the_step_takes_effect_at_the_first_pass() -> None:
    """Documented (renderer.render): min_spp is not changed, decisions come at pass ends,
    so min_spp 7 with step 8 decides at 8, and min_spp 9 first at 16 (a control)."""
    for min_spp, first in ((7, 8), (9, 16)):
        r = run_adaptive("cornell", "flip", tau=0.02, threshold=0.5, resolution=32, block=16,
                         step=8, min_spp=min_spp, max_spp=32, progress=False)
        assert r.report["min_spp"] == min_spp
        assert min(h[0][0] for h in (b["history"] for b in r.report["blocks"]) if h) == first


def test_the_portability_check_compiles_for_the_target_it_names(variant) -> None:
    """`make test-portability`'s switch (NOISESTOP_TEST_LLVM_TARGET): in a fresh process the
    LLVM backend reports the target asked for, and a render still runs on it; a malformed
    target is refused in one line. (A subprocess: the switch holds for the whole process.)"""
    import subprocess
    import sys

    if not variant.startswith("llvm"):
        pytest.skip("the target is the LLVM backend's")
    with pytest.raises(ValueError, match="power of two"):
        golden.set_llvm_target("haswell,6")
    code = ("from tests.support import passloop_golden as g; print(g.apply_target_from_env()); "
            "r = g.render_case('cornell_flip', True); print(r.report['passes'])")
    env = {**__import__("os").environ, golden.LLVM_TARGET_ENV: "haswell,8",
           "DRJIT_CACHE_DIR": str(Path(__import__("tempfile").mkdtemp()))}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.split()
    assert lines[0] == "haswell,8" and int(lines[1]) > 0
