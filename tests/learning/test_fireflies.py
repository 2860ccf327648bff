"""Sparse fireflies on a dark background: the failure the block mean hid.

A 64x64 block of dark grey where, rarely, a sample is very bright (a path that found a
small bright light), as in spot_stage's background. Its passes are drawn here, so the
test needs no renderer: each pass of 32 samples per pixel adds `bg` plus F/32 per bright
sample, and the reference is the exact expected value. At 32 spp a handful of white dots
lie on the grey; they fade as samples accumulate.

Under the first observer (the block mean) the block counts as converged from its first
level: a few dots hardly move the mean FLIP of 4096 pixels. Under DESIGN's observer (the
largest 16x16 tile mean) it does not. The `flip` criterion at the shipped c(tau) keeps
sampling until the dots are gone because it pools its half-buffer FLIP by 8x8 tiles
(`noisefeat.pooling.CRITERION_POOLING`); pooled by 16x16 tiles, as the observer, it
stopped these blocks at 96, 736 and 288 spp against thresholds of 640, 1312 and 1312
(docs/how-it-works.md, "The criteria": a dot saturates FLIP in both the halves' difference and the
observer's, so the halves' usual 1.5x margin over the observer, which c is calibrated
on, is missing for fireflies; finer tiles weigh a dot 4x more).
"""
from __future__ import annotations

import numpy as np
import pytest

from learning.data.block_terms import pooled_errors
from learning.data.observer import VirtualObserver
from learning.data.relabel import observed
from learning.data.stack_write import write_stack
from learning.inputs.halves import flip_c, load_flip_calibration
from renderer.criteria import FlipCriterion
from noisefeat.pooling import CRITERION_POOLING, POOLINGS
from renderer.simulation.simulate import simulate_stack

STEP, LEVELS, SIZE = 32, 64, 64
BG, P, F = 0.02, 2e-5, 12.0          # background, chance of a bright sample, its value
TAU = 0.02


def firefly_levels(seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    total = np.zeros((SIZE, SIZE, 3))
    levels = []
    for k in range(LEVELS):
        hits = rng.binomial(STEP, P, (SIZE, SIZE, 1)).astype(np.float64)
        total += (BG + hits * F / STEP) * STEP
        levels.append((total / ((k + 1) * STEP)).astype(np.float32))
    return np.full((SIZE, SIZE, 3), BG + P * F, np.float32), levels


@pytest.fixture(scope="module", params=[0, 1, 2])
def stack(request, tmp_path_factory):
    reference, levels = firefly_levels(request.param)
    obs = VirtualObserver(tau=TAU)
    spp = [STEP * (k + 1) for k in range(LEVELS)]
    return write_stack(tmp_path_factory.mktemp("fireflies") / "s", scene="fireflies", levels=levels, spp=spp,
                       reference=reference, quick=None, reference_spp=10 ** 6, renderer="synthetic fireflies",
                       grid=(1, 1), labeler=obs.labeler, thresholds=obs.thresholds(reference, levels, spp, (1, 1)))


def test_the_block_mean_calls_the_dotted_block_converged_the_tiles_do_not(stack):
    e = pooled_errors(stack.reference(), [stack.level(0)], (1, 1))[:, 0, 0]
    tile, mean = float(e[POOLINGS.index("tile16-max")]), float(e[POOLINGS.index("mean")])
    assert mean <= TAU < tile, (tile, mean)               # v1 would stop here; v2 sees the dots
    assert observed(stack, TAU, "mean").thresholds[0] == STEP
    assert stack.thresholds[0] is None or stack.thresholds[0] > STEP


def test_flip_keeps_sampling_until_the_fireflies_are_gone(stack):
    assert CRITERION_POOLING == "tile8-max"
    crit = FlipCriterion(exposure=0.0, tau=TAU)
    assert crit.c == pytest.approx(flip_c(load_flip_calibration(), TAU))
    V = simulate_stack(stack, crit, min_spp=STEP)
    stopped = np.flatnonzero(V[:, 0] > 0)
    if stopped.size == 0:
        return                                            # never stopped: no visible dot left behind
    stop, true = stack.spp[int(stopped[0])], stack.thresholds[0]
    assert stop > STEP                                    # not at min spp
    assert true is not None and stop >= true, (stop, true)   # not before the observer's threshold
