"""A unit's noise estimate from its whole decision history, not from one level (issue 49).

Monte Carlo noise falls as 1/sqrt(spp), so each decision's score e_j (the halves' FLIP at
spp_j) times spp_j^ALPHA estimates one constant per unit. One level's score is noisy; the
mean of those estimates over the unit's decisions so far, brought back to the current spp,
is not: `e_hist(k) = mean_{j <= k}(e_j spp_j^ALPHA) / spp_k^ALPHA`. The criterion stops
on it (the stop rule with score -e_hist) where it decides from the history.

Two forms of one formula: `running` over a whole score matrix (the calibration on stored
stacks), and `Evidence`, the sums the live loop keeps per unit between decisions
(`renderer.passloop.PassLoop`, checkpointed with it) and adds each decision's estimate to.
A decision without a finite score adds nothing; a unit without any finite score has no
estimate (NaN: no decision).
"""
from __future__ import annotations

import numpy as np

#: the decay exponent of the halves' score with spp: Monte Carlo's 1/sqrt(spp)
ALPHA = 0.5
#: what a unit's statistic is named in reports and in the calibration record: the
#: history's, and one level's alone (block grain)
STATISTIC = "history-mean"
LAST = "last"


def estimates(scores: np.ndarray, spp: np.ndarray) -> np.ndarray:
    """Each decision's estimate of the unit's constant: e * spp^ALPHA (NaN stays NaN)."""
    return np.asarray(scores, np.float64) * np.asarray(spp, np.float64) ** ALPHA


def running(scores: np.ndarray, spp: np.ndarray) -> np.ndarray:
    """e_hist [K, n] from per-level scores e [K, n] at spp [K]: at each level, the mean of
    the finite estimates so far brought to that level's spp; NaN where the level's own score
    is NaN (no decision there) or no estimate exists yet."""
    e = np.asarray(scores, np.float64)
    s = np.asarray(spp, np.float64).reshape(-1, *([1] * (e.ndim - 1)))
    x = estimates(e, s)
    ok = np.isfinite(x)
    total, count = np.cumsum(np.where(ok, x, 0.0), axis=0), np.cumsum(ok, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, total / count / s ** ALPHA, np.nan)


def combine(sums: np.ndarray | None, scores: np.ndarray, spp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e_hist [k], estimates [k]) of one decision: the units' earlier `sums` [k, 2] (sum of
    estimates, count; None: no earlier decision) with this decision's `scores` [k] at `spp`
    [k]. Pure: the caller keeps the sums (`Evidence.add` the estimates)."""
    s = np.asarray(spp, np.float64).reshape(-1)
    x = estimates(np.asarray(scores, np.float64).reshape(-1), s)
    ok = np.isfinite(x)
    prior = np.zeros((len(x), 2)) if sums is None else np.asarray(sums, np.float64).reshape(len(x), 2)
    total, count = prior[:, 0] + np.where(ok, x, 0.0), prior[:, 1] + ok
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, total / count / s ** ALPHA, np.nan), x


class Evidence:
    """Per unit, the sum of its decisions' estimates and how many there were: float64 [n, 2],
    the state a live render carries between decisions (and checkpoints)."""

    def __init__(self, n: int) -> None:
        self.sums = np.zeros((int(n), 2), np.float64)

    def add(self, ids: np.ndarray, x: np.ndarray) -> None:
        """Add one decision's estimates `x` [k] (NaN: none) of units `ids`."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        x = np.asarray(x, np.float64).reshape(-1)
        ok = np.isfinite(x)
        self.sums[idx[ok], 0] += x[ok]
        self.sums[idx[ok], 1] += 1.0

    def restore(self, sums: np.ndarray) -> None:
        """Continue from checkpointed sums (validated by `renderer.checkpoint`)."""
        self.sums = np.array(sums, np.float64, copy=True).reshape(self.sums.shape)
