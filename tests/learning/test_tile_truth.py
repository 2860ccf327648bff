"""The truth at tile grain: a tile is converged at a level when its FLIP mean is at
most tau and at most one pixel exceeds the dot level, at that level and every later one."""
from __future__ import annotations

import json

import numpy as np
import pytest

from learning import write_stack
from learning.data.observer import VirtualObserver, thresholds_from_errors
from learning.data.relabel import relabel_if_stale, with_tile_truth
from learning.data.stack import read_stack
from learning.data.stack_validate import validate_meta
from learning.data.stack_write import update_labels
from learning.data.tile_terms import tile_errors, tile_terms

SPP = [8, 16, 24, 32]
#: tile t of the 4x4 tiles of a 64x64 block is noisy up to level CONV[t]: its truth is SPP[CONV[t]]
CONV = np.array([0, 1, 2, 3] * 4)


def _levels(amplitude: float = 0.04, dots_in: int | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    rng = np.random.default_rng(0)
    ref = np.full((64, 64, 3), 0.4, np.float32)
    levels = []
    for k in range(len(SPP)):
        img = ref.copy()
        for t in np.flatnonzero(k < CONV):
            r, c = divmod(int(t), 4)
            img[r * 16:(r + 1) * 16, c * 16:(c + 1) * 16] += amplitude * rng.standard_normal((16, 16, 3))
        if dots_in is not None:                       # two outlier pixels in one tile, at every level
            r, c = divmod(dots_in, 4)
            img[r * 16 + 3, c * 16 + 3] = img[r * 16 + 9, c * 16 + 11] = 0.9
        levels.append(img)
    return ref, levels


def test_tile_thresholds_are_the_construction() -> None:
    ref, levels = _levels()
    e = tile_errors(tile_terms(ref, levels, (1, 1), 16))
    assert thresholds_from_errors(e, SPP, 0.02) == [SPP[c] for c in CONV]
    # control: the block, judged whole, waits for its slowest tile
    assert VirtualObserver().thresholds(ref, levels, SPP, (1, 1)) == [32]


def test_two_outlier_pixels_keep_a_tile_noisy_and_one_does_not() -> None:
    """The dot guard at tile grain: one pixel in 256 may exceed the dot level."""
    ref, levels = _levels(amplitude=0.0, dots_in=6)
    e = tile_errors(tile_terms(ref, levels, (1, 1), 16))
    th = thresholds_from_errors(e, SPP, 0.02)
    assert th[6] is None and all(t == 8 for i, t in enumerate(th) if i != 6)
    one = [lev.copy() for lev in levels]
    for lev in one:
        lev[16 + 9, 32 + 11] = 0.4                    # tile 6 (row 1, column 2) keeps one dot only
    assert thresholds_from_errors(tile_errors(tile_terms(ref, one, (1, 1), 16)), SPP, 0.02)[6] == 8


def _written(tmp_path):
    """The stack of `_levels`, labelled by the block observer only (no tile truth stored)."""
    ref, levels = _levels()
    obs = VirtualObserver()
    return obs, write_stack(tmp_path / "s", scene="s", levels=levels, spp=SPP, reference=ref, quick=None,
                            reference_spp=256, grid=(1, 1), labeler=obs.labeler,
                            thresholds=obs.thresholds(ref, levels, SPP, (1, 1)))


def test_relabel_writes_block_and_tile_truth(tmp_path) -> None:
    obs, st = _written(tmp_path)
    assert st.tile_thresholds is None
    assert with_tile_truth(st).tile_thresholds == [SPP[c] for c in CONV]      # in memory
    after, changed = relabel_if_stale(read_stack(st.path))
    assert changed and after.tile == 16 and after.tile_thresholds == [SPP[c] for c in CONV]
    meta = json.loads((st.path / "meta.json").read_text())
    assert meta["thresholds"] == [32] and meta["tile"] == 16 and len(meta["tile_thresholds"]) == 16
    assert read_stack(st.path).tile_labels().shape == (4, 16)
    assert relabel_if_stale(read_stack(st.path)) == (read_stack(st.path), False)     # now current
    # relabelled at another tau: both truths go with the labels
    other, changed = relabel_if_stale(read_stack(st.path), tau=0.05)
    assert changed and other.labeler["tau"] == 0.05 and other.tile_thresholds is not None
    # a tile truth of the wrong length, or without its tile size, is refused
    bad = {**meta, "tile_thresholds": meta["tile_thresholds"][:5]}
    assert any("tile_thresholds has 5 entries" in e for e in validate_meta(bad))
    assert any("go together" in e for e in validate_meta({**meta, "tile": None}))
    with pytest.raises(ValueError, match="no tile thresholds"):
        update_labels(st.path, [32], obs.labeler).tile_labels()


def test_the_simulation_decides_tiles_and_reports_both_grains(tmp_path) -> None:
    """`evaluate --tile`: the oracle per tile against the tile truth makes no early stop and
    spends the tile oracle's samples: 20 of 32 spp a block here by construction (0.625x the
    block oracle, which waits for the slowest tile). Control: at block grain the same oracle
    saves nothing on this block."""
    from renderer.simulation.simulate import criterion_factory, evaluate_criterion, simulate_loop

    ref, levels = _levels()
    obs = VirtualObserver()
    st = write_stack(tmp_path / "s", scene="s", levels=levels, spp=SPP, reference=ref, quick=None,
                     reference_spp=256, grid=(1, 1), labeler=obs.labeler,
                     thresholds=obs.thresholds(ref, levels, SPP, (1, 1)))
    tiles = evaluate_criterion([st], criterion_factory("oracle", tile=16), tile=16)
    assert tiles["tile"] == 16 and tiles["early_stop_rate"] == 0.0 and tiles["spp_ratio_vs_oracle"] == 1.0
    assert tiles["blocks"]["tile_oracle_vs_block_oracle"] == pytest.approx(20 / 32)
    assert tiles["blocks"]["spp_ratio_vs_block_oracle"] == pytest.approx(20 / 32)
    assert tiles["blocks"]["per_scene"]["s"]["tile_oracle_vs_block_oracle"] == pytest.approx(20 / 32)
    blocks = evaluate_criterion([st], criterion_factory("oracle"))
    assert blocks["saved_vs_uniform"] == 0.0 and "blocks" not in blocks
    # tile = block is the block loop, verdict for verdict
    from renderer.criteria import VarianceCriterion

    whole, _ = simulate_loop(st, VarianceCriterion(0.2), tile=64)
    np.testing.assert_array_equal(whole, simulate_loop(st, VarianceCriterion(0.2))[0])


def test_the_end_of_a_simulated_render_is_judged_by_the_block_observer(tmp_path) -> None:
    """`end_of_render` puts each unit at the level it stopped at (the last if never) into
    the frame and judges it with the version-3 block observer: tiles stopped at their truth
    leave a clean block; the same stops one level early leave it above tau. Control: the
    composed frame is the one built here by hand."""
    from learning.data.block_terms import block_errors
    from renderer.simulation.simulate import end_of_render

    ref, levels = _levels()
    obs = VirtualObserver()
    st = write_stack(tmp_path / "s", scene="s", levels=levels, spp=SPP, reference=ref, quick=None,
                     reference_spp=256, grid=(1, 1), labeler=obs.labeler,
                     thresholds=obs.thresholds(ref, levels, SPP, (1, 1)))
    at_truth = np.where(np.arange(len(SPP))[:, None] >= CONV[None], 1, -1).astype(np.int8)
    assert end_of_render(st, at_truth, 16, 0.02)["above_tau"] == 0
    early = np.where(np.arange(len(SPP))[:, None] >= np.maximum(CONV - 1, 0)[None], 1, -1).astype(np.int8)
    got = end_of_render(st, early, 16, 0.02)
    by_hand = levels[-1].copy()
    for t, k in enumerate(np.maximum(CONV - 1, 0)):
        r, c = divmod(t, 4)
        by_hand[r * 16:(r + 1) * 16, c * 16:(c + 1) * 16] = levels[k][r * 16:(r + 1) * 16, c * 16:(c + 1) * 16]
    assert got["above_tau"] == 1 and got["worst"] == pytest.approx(float(block_errors(ref, by_hand[None], (1, 1))[0, 0]))
    never = end_of_render(st, np.full((len(SPP), 1), -1, np.int8), None, 0.02)   # whole block, last level
    assert never == {"above_tau": 0, "early": 0, "converging": 1, "blocks": 1,
                     "worst": pytest.approx(float(block_errors(ref, levels[-1][None], (1, 1))[0, 0]))}
    assert got["early"] == 1 and got["converging"] == 1       # the block above tau could be clean


def _noisy_stack(path, scene: str, seed: int, amplitude: tuple[float, float] = (0.02, 0.3)):
    """A virtual-observer stack whose levels are true cumulative means of noisy passes (8 spp
    each), its 16 tiles noisy to different degrees (uniform in `amplitude`): the halves the
    live loop would keep."""
    rng = np.random.default_rng(seed)
    ref = np.full((64, 64, 3), 0.35, np.float32)
    amp = np.repeat(np.repeat(rng.uniform(*amplitude, (4, 4)), 16, 0), 16, 1)[..., None]
    total, levels, spp = np.zeros_like(ref, np.float64), [], []
    for k in range(12):
        total += (ref + amp * rng.standard_normal(ref.shape)) * 8
        spp.append(8 * (k + 1))
        levels.append((total / spp[-1]).astype(np.float32))
    obs = VirtualObserver()
    return write_stack(path, scene=scene, levels=levels, spp=spp, reference=ref, quick=None, reference_spp=4096,
                       grid=(1, 1), labeler=obs.labeler, thresholds=obs.thresholds(ref, levels, spp, (1, 1)))


def test_c_is_calibrated_per_tile_against_the_tile_truth(tmp_path) -> None:
    """`noisestop calibrate` makes the tile curve too: chosen out of fold against the final
    frame's early blocks, on the history's statistic, and recorded with its unit;
    the flip criterion at tile grain reads it, a file without it falls back to the block
    curve, and a tile curve of another statistic is refused."""
    from learning.evaluation.calibrate import calibrate_flip_curve
    from learning.inputs.halves import unit_calibration

    stacks = [_noisy_stack(tmp_path / f"s{i}", f"s{i}", i) for i in range(3)]
    tiles = calibrate_flip_curve(stacks, 0.05, taus=(0.02,), progress=False, tile=16)
    assert tiles["unit"] == "tile16" and len(tiles["curve"]) == 1
    point = tiles["curve"][0]
    assert point["c"] > 0 and point["chosen"]["end_early_rate"] <= 0.05
    assert tiles["statistic"] == "history-mean" and tiles["rate"] == "end_early_rate"
    assert tiles["tile_truth"] == "final-frame"
    blocks = calibrate_flip_curve(stacks, 0.05, taus=(0.02,), progress=False)
    assert blocks["unit"] == "block" and "end_early_rate" not in blocks["curve"][0]["chosen"]
    part = {k: tiles[k] for k in ("unit", "curve", "c", "target_early_stop_rate", "statistic")}
    cal = {**blocks, "tiles": {"16": part}}
    assert unit_calibration(cal, 16)["curve"] == tiles["curve"] and unit_calibration(cal, 16)["unit"] == "tile16"
    assert unit_calibration(blocks, 16)["curve"] == blocks["curve"]          # no tile curve: the block one
    older = {**blocks, "tiles": {"16": {k: v for k, v in part.items() if k != "statistic"}}}   # no statistic named
    with pytest.raises(ValueError, match="recalibrate"):
        unit_calibration(older, 16)


def test_the_shipped_calibration_holds_a_checked_tile_curve(tmp_path) -> None:
    """learning/flip.json carries c(tau) per 16-px tile beside the block curve; a damaged tile
    curve is refused in one line like a damaged block curve."""
    from learning.inputs.halves import FLIP_CALIBRATION, flip_c, load_flip_calibration, unit_calibration

    cal = load_flip_calibration()
    tiles = unit_calibration(cal, 16)
    assert tiles["unit"] == "tile16" and 0 < flip_c(tiles, 0.02) < flip_c(cal, 0.02)
    bad = json.loads(FLIP_CALIBRATION.read_text())
    bad["tiles"]["16"]["curve"][1]["tau"] = bad["tiles"]["16"]["curve"][0]["tau"]     # not increasing
    (tmp_path / "flip.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="unreadable flip calibration .taus must be finite and increasing"):
        load_flip_calibration(tmp_path / "flip.json")


# ----------------------------------------------------------------------------- on the final frame

def _leaky(residual: float = 0.01) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """A checkerboard of early and late tiles whose residual noise halves every level after
    their stop: a tile stopped early keeps more noise than the same-samples frame shows its
    late neighbour, and FLIP's filters carry it across."""
    from learning.data.tile_truth import unit_windows

    spp = [8, 16, 24, 32, 40, 48]
    conv = np.array([0, 3, 0, 3, 3, 0, 3, 0] * 2)
    rng = np.random.default_rng(0)
    ref = np.full((64, 64, 3), 0.3, np.float32)
    levels = []
    for k in range(len(spp)):
        img = ref.copy()
        for t, (x, y, w, h) in enumerate(unit_windows(64, 64, (1, 1), 16)):
            a = 0.1 if k < conv[t] else residual * 0.5 ** (k - conv[t])
            img[y:y + h, x:x + w] += a * rng.standard_normal((h, w, 3)).astype(np.float32)
        levels.append(img)
    return ref, np.stack(levels), spp


def test_the_final_frame_truth_holds_where_the_same_samples_truth_leaks() -> None:
    from learning.data.tile_truth import compose_levels, fixed_point, unit_windows

    ref, levels, spp = _leaky()
    th = thresholds_from_errors(tile_errors(tile_terms(ref, levels, (1, 1), 16)), spp, 0.02)
    start = np.array([spp.index(t) if t is not None else len(spp) for t in th])
    win = unit_windows(64, 64, (1, 1), 16)
    obs = VirtualObserver()
    before, _ = obs.frame_errors(ref, compose_levels(levels, start, win), (1, 1), 16)
    assert before[0] > 0.02                       # control: every tile at its same-samples truth leaks
    at, rounds = fixed_point(levels, ref, start, (1, 1), 16, obs)
    after, _ = obs.frame_errors(ref, compose_levels(levels, at, win), (1, 1), 16)
    assert after[0] <= 0.02 and rounds > 1
    assert (at >= start).all() and (at > start).sum() >= 1        # only ever later, and only where needed


def test_a_tile_noisy_at_the_last_level_is_censored_and_holds_no_neighbour() -> None:
    from learning.data.tile_truth import fixed_point

    ref, levels, spp = _leaky()
    levels[:, 20:28, 20:28] += 0.5                 # tile 5 never converges, at any level
    th = thresholds_from_errors(tile_errors(tile_terms(ref, levels, (1, 1), 16)), spp, 0.02)
    start = np.array([spp.index(t) if t is not None else len(spp) for t in th])
    assert start[5] == len(spp)
    at, _ = fixed_point(levels, ref, start, (1, 1), 16, VirtualObserver())
    assert at[5] == len(spp)                       # no threshold
    assert (at[[0, 2, 7, 8, 10, 13, 15]] <= start[[0, 2, 7, 8, 10, 13, 15]] + 1).all()   # not driven to the cap


def test_stored_tile_truth_of_the_first_version_is_recomputed(tmp_path) -> None:
    obs, st = _written(tmp_path)
    old = {k: v for k, v in obs.labeler.items() if k != "tile_truth"}   # as a same-samples relabel wrote it
    update_labels(st.path, st.thresholds, old, 16, [8] * 16)
    assert relabel_if_stale(read_stack(st.path))[1]                 # stale: rewritten
    again = read_stack(st.path)
    assert again.labeler["tile_truth"] == "final-frame" and again.tile_thresholds == [SPP[c] for c in CONV]
    assert with_tile_truth(read_stack(st.path)) is not None and not relabel_if_stale(again)[1]


@pytest.mark.parametrize("case", ["black", "constant", "firefly", "nan", "tiny"])
def test_the_fixed_point_ends_on_extreme_frames(case: str) -> None:
    """Black, constant, fireflies of 1e30, NaN pixels and tiny values: the fixed point ends,
    tiles only move later, and a block it cannot bring under tau is censored, never a
    traceback or a stop inside noise."""
    from learning.data.tile_truth import fixed_point

    spp = [8, 16, 24]
    value = {"black": 0.0, "constant": 0.4, "firefly": 0.4, "nan": 0.4, "tiny": 1e-30}[case]
    ref = np.full((32, 32, 3), value, np.float32)
    levels = np.repeat(ref[None], len(spp), axis=0)
    if case == "firefly":                     # more outliers than a tile lets through
        levels[:, 3:6, 3:6] = 1e30
    if case == "nan":
        levels[:, 4:8, 20:24] = np.nan
    start = np.zeros(4, np.int64)
    at, rounds = fixed_point(levels, ref, start, (1, 1), 16, VirtualObserver())
    assert (at >= start).all() and rounds <= len(start) * len(spp) + 1     # every round moves a tile
    if case in ("black", "constant", "tiny"):
        assert at.tolist() == [0, 0, 0, 0] and rounds == 1          # nothing to see: nothing moves
    else:                                                           # what never clears is censored
        assert at[0 if case == "firefly" else 1] == len(spp)
