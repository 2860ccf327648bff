"""A model's decision offset at the user's noise target tau.

A model is trained on labels of one tau (the observer's), and its offset is calibrated
out of fold on the training scenes (`learning.evaluation.calibrate`). The same
out-of-fold scores, judged against the labels of other taus, give an offset per tau:
the bundle keeps them as `offsets_by_tau` ([{"tau", "offset"}], increasing tau), so
`--tau` moves a model as c(tau) moves the `flip` criterion. A bundle without that curve
answers only at the tau it was calibrated at.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..names import DEFAULT_TAU

_EPS = 1e-9


def _training(manifest: Mapping[str, Any]) -> Mapping[str, Any]:
    t = manifest.get("training")
    return t if isinstance(t, Mapping) else {}


def offset_curve(manifest: Mapping[str, Any]) -> list[tuple[float, float]]:
    """(tau, offset) pairs of a bundle (its training record's calibration), checked:
    increasing positive finite tau, finite offsets."""
    cal = _training(manifest).get("calibration")
    rows = (cal.get("offsets_by_tau") if isinstance(cal, Mapping) else None) or []
    if not isinstance(rows, Sequence):
        raise ValueError(f"offsets_by_tau must be a list, got {type(rows).__name__}")
    try:
        pts = [(float(r["tau"]), float(r["offset"])) for r in rows]
    except (KeyError, TypeError, ValueError):
        raise ValueError("offsets_by_tau must hold objects with numeric 'tau' and 'offset'") from None
    taus = [t for t, _ in pts]
    if not all(np.isfinite([v for p in pts for v in p])) or any(t <= 0 for t in taus) \
            or any(b <= a for a, b in zip(taus, taus[1:])):
        raise ValueError(f"offsets_by_tau must be finite with increasing positive tau, got {pts[:4]}")
    return pts


def calibrated_tau(manifest: Mapping[str, Any]) -> float:
    """The tau of the labels the model's own offset was calibrated on."""
    return float(_training(manifest).get("tau", DEFAULT_TAU))


def tau_range(manifest: Mapping[str, Any]) -> tuple[float, float]:
    """The noise targets a bundle answers at: its curve's range, or its one calibrated tau."""
    pts = offset_curve(manifest)
    if pts:
        return pts[0][0], pts[-1][0]
    t = calibrated_tau(manifest)
    return t, t


def offset_at(manifest: Mapping[str, Any], offset: float, tau: float | None) -> float:
    """The offset at `tau` (None: the calibrated `offset`): interpolated linearly in log tau
    on the bundle's curve; a tau outside what the bundle was calibrated for is refused,
    naming the range."""
    if tau is None:
        return float(offset)
    t = float(tau)
    lo, hi = tau_range(manifest)
    if not (np.isfinite(t) and lo * (1 - _EPS) <= t <= hi * (1 + _EPS)):
        what = f"the calibrated range [{lo:g}, {hi:g}]" if hi > lo else f"tau {lo:g}, the only one it was calibrated at"
        raise ValueError(f"tau {tau!r} is outside what this model answers at: {what} "
                         "(retrain it to get offsets for other noise targets)")
    pts = offset_curve(manifest)
    if not pts:
        return float(offset)
    return float(np.interp(np.log(t), np.log([p[0] for p in pts]), [p[1] for p in pts]))
