"""A unit's noise estimate from its whole decision history, not from one level.

Monte Carlo noise falls as 1/sqrt(spp), so each decision's score e_j (the halves' FLIP at
spp_j) times spp_j^ALPHA estimates one constant per unit. One level's score is noisy; the
mean of those estimates over the unit's decisions so far, brought back to the current spp,
is not: `e_hist(k) = sum_{j <= k}(w_j e_j spp_j^ALPHA) / sum_{j <= k} w_j / spp_k^ALPHA`.
The criterion stops on it (the stop rule with score -e_hist) where it decides from the
history.

Each estimate weighs the samples it stands for, w_j = spp_j minus the spp of the unit's
decision before it: decided after every pass of a constant step, every w_j is
the step and this is the plain mean the tile curve of c(tau) was calibrated on; decided at
geometric spp steps (`renderer.live.passloop.decision_passes`), it is the same mean sampled more
sparsely, not one tilted towards the early, noisier levels. So one curve holds for every
decision schedule.

Two forms of one formula: `running` over a whole score matrix (the calibration on stored
stacks), and `Evidence`, the sums the live loop keeps per unit between decisions
(`renderer.live.passloop.PassLoop`, checkpointed with it) and adds each decision's estimate to.
A decision without a finite score adds nothing (but is the decision the next weight counts
from); a unit without any finite score has no estimate (NaN: no decision).
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
    """e_hist [K, n] from per-level scores e [K, n] at spp [K], every level a decision: at
    each level, the weighted mean of the finite estimates so far brought to that level's
    spp; NaN where the level's own score is NaN (no decision there) or no estimate exists
    yet."""
    e = np.asarray(scores, np.float64)
    s = np.asarray(spp, np.float64).reshape(-1, *([1] * (e.ndim - 1)))
    w = np.diff(s, axis=0, prepend=0.0)
    x = estimates(e, s)
    ok = np.isfinite(x)
    total, weight = np.cumsum(np.where(ok, w * x, 0.0), axis=0), np.cumsum(np.where(ok, w, 0.0), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, total / weight / s ** ALPHA, np.nan)


def combine(prior: np.ndarray | None, scores: np.ndarray, spp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e_hist [k], estimates [k]) of one decision: the units' earlier decisions `prior`
    [k, 3] (weighted sum of estimates, sum of weights, spp of the last decision;
    `Evidence.rows`; None: none) with this decision's `scores` [k] at `spp` [k]. Pure: the
    caller keeps the sums (`Evidence.add` the estimates)."""
    s = np.asarray(spp, np.float64).reshape(-1)
    x = estimates(np.asarray(scores, np.float64).reshape(-1), s)
    ok = np.isfinite(x)
    prior = np.zeros((len(x), 3)) if prior is None else np.asarray(prior, np.float64).reshape(len(x), 3)
    w = s - prior[:, 2]
    total, weight = prior[:, 0] + np.where(ok, w * x, 0.0), prior[:, 1] + np.where(ok, w, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok, total / weight / s ** ALPHA, np.nan), x


def last_decided_spp(verdicts: np.ndarray, unit_spp: np.ndarray) -> np.ndarray:
    """int64 [n]: each unit's spp at its last decision (0: none yet), from the verdict
    history [K, n] (nonzero where a unit was judged) and every unit's spp after each row
    [K, n]: what its next weight counts from, and what its weights may sum to at most."""
    asked = np.asarray(verdicts) != 0
    n = asked.shape[1]
    if not asked.size:
        return np.zeros(n, np.int64)
    last = len(asked) - 1 - np.argmax(asked[::-1], axis=0)
    return np.where(asked.any(axis=0), np.asarray(unit_spp, np.int64)[last, np.arange(n)], 0).astype(np.int64)


class Evidence:
    """Per unit, the weighted sum of its decisions' estimates and the sum of their weights
    (float64 [n, 2], what a live render checkpoints), and the spp of its last decision
    (int64 [n], what the next weight counts from; restored from the verdict history)."""

    def __init__(self, n: int) -> None:
        self.sums = np.zeros((int(n), 2), np.float64)
        self.last = np.zeros(int(n), np.int64)

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """float64 [k, 3]: the units' sums and last decided spp, as `combine` reads them."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        return np.concatenate([self.sums[idx], self.last[idx, None].astype(np.float64)], axis=1)

    def add(self, ids: np.ndarray, x: np.ndarray, spp: np.ndarray) -> None:
        """Add one decision's estimates `x` [k] (NaN: none) of units `ids` at their `spp` [k]."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        x = np.asarray(x, np.float64).reshape(-1)
        s = np.asarray(spp, np.int64).reshape(-1)
        ok = np.isfinite(x)
        w = (s - self.last[idx]).astype(np.float64)
        self.sums[idx[ok], 0] += w[ok] * x[ok]
        self.sums[idx[ok], 1] += w[ok]
        self.last[idx] = s

    def restore(self, sums: np.ndarray, last: np.ndarray) -> None:
        """Continue from checkpointed sums (validated by `renderer.live.checkpoint`) and each
        unit's last decided spp (from the verdict history)."""
        self.sums = np.array(sums, np.float64, copy=True).reshape(self.sums.shape)
        self.last = np.array(last, np.int64, copy=True).reshape(self.last.shape)
