"""What a stopping criterion is: the `Criterion` contract, the `Decision` it returns, and the
one factory (`make_criterion`). A criterion answers, per unit of a `UnitBatch`, +1 (converged)
or -1 (noisy) with its ratio to the target (> 1: above it; what a budget render spends by).
The live loop and the simulation call the same `decide`, so what is measured offline runs
online; a criterion is configuration only (the loop owns counters and timers). A unit with no
finite estimate (`UnitBatch.unestimated`) is never converged, whatever the criterion: else a
unit whose samples were all dropped would stop at once on its black, flat mean.
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from learning.stoprule import NOISY, dots_ratio, flat_blocks, flat_halves

from .batch import UnitBatch, UnitView
from .registry import Declared, criterion_class

if TYPE_CHECKING:
    from ..spec import RenderSpec

V = TypeVar("V")

# units_featured: units whose image went through the features or FLIP (here or on a server);
# feature_rows: 26-feature rows computed here; flat_units: settled by the flat test;
# nonfinite_units: held non-finite samples; dotted_units: held noisy by the dot guard;
# gated_tiles: tiles flip called converged that the model's block verdict held
COUNTER_NAMES = ("decide_calls", "units_asked", "units_featured", "feature_rows", "converged",
                 "flat_units", "nonfinite_units", "dotted_units", "gated_tiles")
#: a counter's name in report.json, a simulation's counters and checkpoints, where it differs:
#: those files keep the names given when every unit was a block (DESIGN fixes report.json)
EXTERNAL_COUNTER_NAMES = {"units_asked": "blocks_asked", "units_featured": "blocks_featured",
                          "flat_units": "flat_blocks", "nonfinite_units": "nonfinite_blocks",
                          "dotted_units": "dotted_blocks"}
_INTERNAL_COUNTER_NAMES = {v: k for k, v in EXTERNAL_COUNTER_NAMES.items()}


def external_counters(counters: Mapping[str, V]) -> dict[str, V]:
    """`counters` under their external names (`EXTERNAL_COUNTER_NAMES`), in the same order."""
    return {EXTERNAL_COUNTER_NAMES.get(k, k): v for k, v in counters.items()}


def internal_counters(counters: Mapping[str, V]) -> dict[str, V]:
    """`counters` read from a file under this code's names, in the same order."""
    return {_INTERNAL_COUNTER_NAMES.get(k, k): v for k, v in counters.items()}


TIMER_NAMES = ("features_s", "decisions_s")


@dataclass(frozen=True)
class Decision:
    """One `decide` call's answer: `verdict` int8 [k], `ratio` float64 [k] (0 flat, NaN no
    estimate yet), `evidence` float64 [k] (what it adds to each unit's history,
    `learning.inputs.history`; None: no history), and what the call cost, for the loop."""

    verdict: np.ndarray
    ratio: np.ndarray
    evidence: np.ndarray | None = None
    counts: Mapping[str, int] = field(default_factory=dict)
    timers: Mapping[str, float] = field(default_factory=dict)


class Tally(dict):
    """The counts of one `decide` call."""

    def add(self, name: str, n: int | float) -> None:
        self[name] = self.get(name, 0) + n

    @contextmanager
    def timing(self, name: str = "features_s") -> Iterator[None]:
        """Add the block's seconds to `name`."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)


class Criterion(Declared, ABC):
    """Base class: validates inputs, enforces int8 +-1 verdicts, times and counts a call.
    Its declaration (`renderer.criteria.registry.Declared`): `name`, `grain`, `settings`,
    `needs_thresholds`, `summary`, and `from_spec`."""

    #: what the batches must carry (the quick image, 'albedo' or 'direct', and the half
    #: buffers are made only when a criterion reads them)
    needs_quick: bool = False
    quick_kind: str = "albedo"
    needs_halves: bool = False
    #: its ratio falls as 1/sqrt(spp), as Monte Carlo noise does, so the loop may skip the
    #: decisions before a unit's predicted stop
    noise_ratio: bool = False
    #: it may call a unit converged; one that never does is asked only at a unit's last pass,
    #: so the loop traces the passes before in as few launches as it can
    stops: bool = True

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
        """The criterion of a resolved spec (`thresholds`: a labelled reference's, per unit);
        by default the class called with its declared settings."""
        return cls(**{name: getattr(spec, name) for name in cls.settings})

    @classmethod
    def checked(cls, **given: Any) -> dict[str, Any]:
        """A constructor's render settings (None: not given), checked and defaulted by this
        criterion's declaration: the one check the render spec makes too."""
        from ..settings import declared_values

        return declared_values(cls, given)

    def describe(self) -> dict[str, Any]:
        """Name and parameters, for reports."""
        return {"name": self.name}

    def prepare(self, quick: np.ndarray) -> tuple[np.ndarray, Tally]:
        """What the batches' `quick` holds, made once per render from the quick blocks
        [n, bh, bw, 3] (by default the blocks themselves), and what making it cost."""
        return quick, Tally()

    def decide(self, ids: Sequence[int], batch: UnitBatch | Sequence[UnitView]) -> Decision:
        """The `Decision` on the listed units: a `UnitBatch`, or one `UnitView` per unit."""
        t0 = time.perf_counter()       # before the views are batched: that may time features too
        ids = np.asarray(ids, np.int64).reshape(-1).tolist()
        tally = Tally()
        if not isinstance(batch, UnitBatch):
            batch = self._batch_of_views(ids, list(batch), tally)
        if len(ids) != len(batch):
            raise ValueError(f"{len(ids)} block ids but a batch of {len(batch)} blocks")
        if not ids:
            return Decision(np.zeros(0, np.int8), np.zeros(0))
        if self.needs_quick and batch.quick is None:
            raise ValueError(f"{self.name} criterion needs the quick image, the batch has none")
        if self.needs_halves and batch.half_spp is None:
            raise ValueError(f"{self.name} criterion needs half buffers, the batch has none")
        verdict, ratio, *rest = self.assess(ids, batch, tally)
        verdict, ratio = np.asarray(verdict), np.asarray(ratio, np.float64)
        evidence = np.asarray(rest[0], np.float64).reshape(-1) if rest and rest[0] is not None else None
        if evidence is not None and evidence.shape != (len(ids),):
            raise RuntimeError(f"{self.name} criterion returned {evidence.shape} evidence for {len(ids)} blocks")
        if verdict.shape != (len(ids),) or ratio.shape != (len(ids),):
            raise RuntimeError(f"{self.name} criterion returned shapes {verdict.shape}, {ratio.shape} "
                               f"for {len(ids)} blocks")
        if not np.isin(verdict, (-1, 1)).all():
            raise RuntimeError(f"{self.name} criterion returned values other than -1/+1: "
                               f"{np.unique(verdict)[:5].tolist()}")
        verdict = verdict.astype(np.int8)
        blind = batch.unestimated > 0          # no finite estimate: never converged (module docstring)
        verdict, ratio = np.where(blind, NOISY, verdict).astype(np.int8), np.where(blind, np.nan, ratio)
        features_s = float(tally.pop("features_s", 0.0))
        counts = {"decide_calls": 1, "units_asked": len(ids), "converged": int((verdict > 0).sum()),
                  "nonfinite_units": int((batch.nonfinite > 0).sum()), **tally}
        timers = {"features_s": features_s, "decisions_s": max(0.0, time.perf_counter() - t0 - features_s)}
        return Decision(verdict, ratio, evidence, counts, timers)

    def _batch_of_views(self, ids: list[int], views: list[UnitView], tally: Tally) -> UnitBatch:
        if len(ids) != len(views):
            raise ValueError(f"{len(ids)} block ids but {len(views)} views")
        for b, v in zip(ids, views):
            if not isinstance(v, UnitView):
                raise ValueError(f"block {b}: expected a UnitView, got {type(v).__name__}")
            if np.ndim(v.mean) != 3 or np.shape(v.mean)[-1] != 3:
                raise ValueError(f"block {b}: mean must be [bh, bw, 3], got shape {np.shape(v.mean)}")
            if self.needs_quick and v.quick is None:
                raise ValueError(f"{self.name} criterion needs the quick image, block {b} has none")
            if self.needs_halves and (v.halves is None or v.half_spp is None):
                raise ValueError(f"{self.name} criterion needs half buffers, block {b} has none")
        batch = UnitBatch.from_views(views) if views else UnitBatch(np.zeros(0, np.int64))
        if batch.quick is not None and len(batch):
            batch.quick, made = self.prepare(batch.quick)
            for k, v in made.items():
                tally.add(k, v)
        return batch

    def assess(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, ...]:
        """`_decide`'s answer, before `decide` checks and wraps it: what a criterion made of
        others combines (`renderer.criteria.gated`)."""
        return self._decide(ids, batch, tally)

    @abstractmethod
    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, ...]:
        """(verdict [k], ratio [k]) for a validated, non-empty batch, and a criterion with a
        history the decision's evidence [k]; counts go into `tally`."""

    @staticmethod
    def _flat(batch: UnitBatch, exposure: float, tally: Tally) -> np.ndarray:
        """bool [n]: units with no visible variation (the stop rule's flat test). Once both
        halves hold a pass they must agree within one 8-bit level too (the served route's
        rule): a mean can be flat over halves that differ."""
        flat = flat_blocks(batch.mean, exposure)
        if batch.half_spp is not None and batch.has_halves:
            check = np.flatnonzero(flat & (batch.half_spp.min(axis=1) > 0))
            if check.size:
                flat[check] = flat_halves(*batch.halves_of(check), exposure)
        tally.add("flat_units", int(flat.sum()))
        return flat

    @staticmethod
    def _dots(batch: UnitBatch, ask: np.ndarray, exposure: float, tau: float, tally: Tally) -> np.ndarray:
        """float64 [len(batch)]: the asked units' dot term relative to tau (0 for the others);
        above 1 a unit holds more isolated outliers than the observer lets through."""
        out = np.zeros(len(batch.spp))
        if ask.size:
            out[ask] = dots_ratio(*batch.halves_of(ask), exposure, tau)
            tally.add("dotted_units", int((out[ask] > 1).sum()))
        return out

    @staticmethod
    def _ready(batch: UnitBatch, flat: np.ndarray) -> np.ndarray:
        """The units to judge: not flat, and both halves hold a pass (else they cannot disagree)."""
        return np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0))   # type: ignore[union-attr]


def make_criterion(spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
    """The one criterion factory: the criterion `spec` names, built by its declared class (or
    `spec.criterion` when it is one); `thresholds`: a labelled reference stack's true ones."""
    if isinstance(spec.criterion, Criterion):
        return spec.criterion
    return criterion_class(spec.criterion).from_spec(spec, thresholds)
