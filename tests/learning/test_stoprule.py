"""The one stop rule (DESIGN "The stop rule"): offset, min spp, held stops, flat blocks, extremes."""
from __future__ import annotations

import numpy as np
import pytest

from learning.evaluation.metrics import stop_thresholds
from learning.stoprule import FLAT_TOLERANCE, StopRule, decide_active, flat_blocks

SPP = [16, 32, 48, 64, 80]


def test_verdict_is_score_above_offset_or_flat():
    rule = StopRule(offset=0.5)
    score = np.array([0.4, 0.5, 0.6, np.nan, -np.inf, np.inf])
    assert rule.verdict(score).tolist() == [-1, -1, 1, -1, -1, 1]      # strictly above; NaN is no decision
    flat = np.array([True, False, False, True, False, False])
    assert rule.verdict(score, flat).tolist() == [1, -1, 1, 1, -1, 1]  # flat stops whatever the score
    assert rule.verdict(np.zeros(0)).shape == (0,)
    with pytest.raises(ValueError, match="differ in shape"):
        rule.verdict(score, flat[:2])


def test_stops_are_first_level_above_offset_and_held():
    # block 0 crosses at level 1 then falls back: still stopped (held); block 1 never;
    # block 2 crosses at level 3; block 3 is flat from level 2 with a hopeless score
    s = np.array([[0.0, 2.0, -5.0, -5.0, -5.0],
                  [0.0, 0.0, 0.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0, 2.0, 2.0],
                  [-9.0, -9.0, -9.0, -9.0, -9.0]]).T
    flat = np.zeros_like(s, bool)
    flat[2:, 3] = True
    V = StopRule(1.0).stops(s, SPP, flat)
    assert V.dtype == np.int8
    assert V[:, 0].tolist() == [-1, 1, 1, 1, 1]
    assert V[:, 1].tolist() == [-1] * 5
    assert V[:, 2].tolist() == [-1, -1, -1, 1, 1]
    assert V[:, 3].tolist() == [-1, -1, 1, 1, 1]


def test_no_decision_before_min_spp():
    s = np.full((5, 2), 3.0)
    flat = np.ones((5, 2), bool)
    V = StopRule(0.0, min_spp=48).stops(s, SPP, flat)
    assert V[:, 0].tolist() == [-1, -1, 1, 1, 1]           # neither score nor flatness counts before 48
    assert (StopRule(0.0, min_spp=10_000).stops(s, SPP, flat) == -1).all()


def test_a_larger_offset_never_stops_earlier():
    rng = np.random.default_rng(0)
    s = np.cumsum(rng.normal(0.1, 1.0, (5, 40)), axis=0)
    stops = [stop_thresholds(StopRule(float(off)).stops(s, SPP), SPP) for off in np.linspace(-3, 3, 25)]
    assert all((b >= a).all() for a, b in zip(stops, stops[1:]))
    assert stops[0].sum() < stops[-1].sum()


def test_decide_active_asks_only_active_blocks_and_holds():
    active = np.array([True, False, True, True])
    asked = []

    def decide(ids):
        asked.append(list(ids))
        return np.array([1, -1, 1][:len(ids)])
    row = decide_active(active, 32, 16, decide)
    assert asked == [[0, 2, 3]] and row.tolist() == [1, 0, -1, 1]
    assert active.tolist() == [False, False, True, False]
    assert decide_active(active, 8, 16, decide).tolist() == [0, 0, 0, 0] and len(asked) == 1
    with pytest.raises(RuntimeError, match="verdicts returned"):
        decide_active(np.ones(3, bool), 32, None, lambda ids: np.ones(2))


def test_bad_rules_are_refused():
    for off in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="finite"):
            StopRule(off)
    for m in (0, -4, True, 2.5):
        with pytest.raises(ValueError, match="min_spp"):
            StopRule(0.0, min_spp=m)
    with pytest.raises(ValueError, match="levels"):
        StopRule().stops(np.zeros((3, 2)), SPP)


def test_scores_at_the_extremes_give_defined_stops():
    s = np.array([[1e300, -1e300, 1e-300, -1e-300, np.nan, np.inf, -np.inf]] * 5)
    V = StopRule(0.0).stops(s, SPP)
    assert V[0].tolist() == [1, -1, 1, -1, -1, 1, -1] and set(np.unique(V)) <= {-1, 1}
    assert StopRule(1e308).verdict(np.array([1e300])).tolist() == [-1]


def block(value, noise=0.0, seed=0, size=16):
    rng = np.random.default_rng(seed)
    return (np.full((size, size, 3), value) + noise * rng.standard_normal((size, size, 3))).astype(np.float32)


def two_levels(codes: float) -> np.ndarray:
    """A block of two linear values whose display images lie `codes` 8-bit levels apart."""
    import torch

    from noisefeat.display import srgb_decode, srgb_encode
    lo = 0.2
    hi = float(srgb_decode(srgb_encode(torch.tensor(lo)) + codes / 255))
    b = block(lo)
    b[: b.shape[0] // 2] = hi
    return b


def test_flat_blocks_at_the_extremes():
    fireflies = block(0.2)
    fireflies[3, 3] = 1e6
    nan = block(0.0)
    nan[1, 1] = [np.nan, np.inf, -np.inf]            # +Inf reads as white: not flat
    black_nan = block(0.0)
    black_nan[1, 1] = np.nan                         # NaN reads as black: still flat
    cases = {"black": (block(0.0), True), "constant": (block(0.3), True),
             "noisy": (block(0.3, 0.05), False), "fireflies": (fireflies, False),
             "nan/inf": (nan, False), "black with NaN": (black_nan, True),
             "tiny 1e-30": (block(1e-30, 1e-31), True), "huge 1e30": (block(1e30, 1e29), True),
             "half an 8-bit level apart": (two_levels(0.5), True), "two 8-bit levels apart": (two_levels(2), False)}
    got = flat_blocks(np.stack([b for b, _ in cases.values()]))
    assert dict(zip(cases, got.tolist())) == {k: v for k, (_, v) in cases.items()}
    # the tolerance is one 8-bit code value of the display image, exposure included
    ramp = block(0.2)
    ramp[0, 0] += 0.2
    assert not flat_blocks(ramp[None])[0] and flat_blocks(ramp[None], exposure=-40)[0]
    assert FLAT_TOLERANCE == pytest.approx(1 / 255)
    assert flat_blocks(np.zeros((0, 16, 16, 3), np.float32)).shape == (0,)
