"""What a stopping criterion is: the `Criterion` contract, its declaration, and the
`Decision` it returns for the `UnitBatch` it reads (`renderer.criteria.batch`).

A criterion declares itself on its class, in its own file (`renderer.criteria.registry`):
its name, grain, the render settings it takes and how it is built from a resolved
`renderer.spec.RenderSpec` (`from_spec`). Its constructor checks and defaults what it is
given by that declaration (`checked`), the rows of the render spec and its own `settings`,
the one check `renderer.spec.resolve` makes too: no criterion checks a setting its own way.

A criterion sees all the units it is asked about at once, as a `UnitBatch` (cumulative
means and the two half buffers as tensors on the accumulator's device, spp, quick blocks;
`UnitView`s, one per unit, for callers outside the loop) and answers, per unit, +1
(converged: stop sampling it) or -1 (noisy: keep sampling) with its ratio to the target
(> 1: above it; what a budget render spends by). The live loop and the simulation on
stored stacks build the same batches and call the same `decide`
(`renderer.live.passloop.PassLoop.judge`), so what is measured offline is what runs online.

A criterion is configuration only, as a scikit-learn estimator's parameters are: one
object may judge any number of renders, in any order, in any process. What a render
accumulates (its counters, timers and ratios) is the loop's (`renderer.live.passloop`); a
`Decision` carries one call's share of it.

The model and flip criteria decide by the one stop rule (`learning.stoprule`): a block is
converged when its score exceeds the offset, or at once when it is flat (its display image
within one 8-bit level: no noise to see). The loop adds the rest of the rule: no decision
before min spp, and a stop is held.

Non-finite samples: a unit with no finite estimate is never converged, whatever
the criterion (`Criterion.decide` holds it noisy, ratio NaN, after the criterion's own
verdict; uniform never stops anyway), so it renders to max spp. "No finite estimate"
(`UnitBatch.unestimated`): some pixel of the unit has no finite value in a half buffer
that holds a pass, that is, every (pixel, pass) value the accumulator put there was
dropped as non-finite (`learning.data.accumulator`); from views, a non-finite pixel in the
mean or in a half that holds a pass. A pixel with some finite passes has an estimate (the
mean of those) and is judged as usual: one NaN pass among many does not hold a unit. This
is the served halves route's rule (`learning.stoprule.flat_halves`: non-finite halves are
never flat, and the service answers -1), seen through the accumulator, which drops what
the route would receive as NaN: without it a unit whose samples were all dropped had a
black, flat mean and stopped at once.
"""
from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import numpy as np

from learning.stoprule import NOISY, dots_ratio, flat_blocks, flat_halves

from .batch import UnitBatch, UnitView
from .registry import TILE, Setting

if TYPE_CHECKING:
    from ..spec import RenderSpec

V = TypeVar("V")

# decide_calls: calls to decide; units_asked: verdicts given; units_featured: units whose
# current image went through the feature extractor or FLIP (here or on a server);
# feature_rows: 26-feature rows computed in this process (current and quick units);
# converged: +1 verdicts; flat_units: units settled by the flat test; nonfinite_units:
# verdicts on units that held non-finite samples; dotted_units: units held noisy by the
# dot guard; gated_tiles: tiles flip called converged that the model's block verdict held
# (the model at tile grain, `renderer.criteria.gated`).
COUNTER_NAMES = ("decide_calls", "units_asked", "units_featured", "feature_rows", "converged",
                 "flat_units", "nonfinite_units", "dotted_units", "gated_tiles")
#: the one mapping from a counter's name here to its name outside (report.json "counters",
#: a simulation's "counters", the checkpoint's counter_names) where the two differ: the
#: counters were named when every unit was a block, and those files keep their names
#: (DESIGN fixes report.json; a checkpoint written before still loads)
EXTERNAL_COUNTER_NAMES = {"units_asked": "blocks_asked", "units_featured": "blocks_featured",
                          "flat_units": "flat_blocks", "nonfinite_units": "nonfinite_blocks",
                          "dotted_units": "dotted_blocks"}
_INTERNAL_COUNTER_NAMES = {v: k for k, v in EXTERNAL_COUNTER_NAMES.items()}


def external_counters(counters: Mapping[str, V]) -> dict[str, V]:
    """`counters` under their external names (`EXTERNAL_COUNTER_NAMES`), in the same order."""
    return {EXTERNAL_COUNTER_NAMES.get(k, k): v for k, v in counters.items()}


def internal_counters(counters: Mapping[str, V]) -> dict[str, V]:
    """`counters` read from a file (external names) under this code's names, in the same order."""
    return {_INTERNAL_COUNTER_NAMES.get(k, k): v for k, v in counters.items()}


TIMER_NAMES = ("features_s", "decisions_s")


@dataclass(frozen=True)
class Decision:
    """One `decide` call's answer: `verdict` int8 [k] (+1 converged, -1 noisy), `ratio`
    float64 [k] (each unit's distance to the target as a ratio, > 1 above it, 0 flat, NaN
    no estimate yet), `evidence` float64 [k] (what this decision adds to each unit's
    history, `learning.inputs.history`; None for a criterion without one), and what the
    call cost (`counts` over COUNTER_NAMES, `timers` over TIMER_NAMES), for the loop to add up."""

    verdict: np.ndarray
    ratio: np.ndarray
    evidence: np.ndarray | None = None
    counts: Mapping[str, int] = field(default_factory=dict)
    timers: Mapping[str, float] = field(default_factory=dict)


class Tally(dict):
    """The counts one `decide` call makes (a fresh one per call; helpers add to it)."""

    def add(self, name: str, n: int | float) -> None:
        self[name] = self.get(name, 0) + n

    @contextmanager
    def timing(self, name: str = "features_s") -> Iterator[None]:
        """Add the seconds of the block to `name` (features_s: making a model's input)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - t0)


class Criterion(ABC):
    """Base class: validates inputs, enforces int8 +-1 verdicts, times and counts a call.

    `needs_quick` / `needs_halves` tell the caller what the batches must carry, so the
    quick image is rendered (and half buffers recovered) only when some criterion uses
    them; `quick_kind` says which quick image ('albedo' or 'direct'). `noise_ratio`: whether
    the loop may skip decisions from its ratio (below).

    The declaration (`renderer.criteria.registry`, read by the render spec, the command
    line, the plugin and the factory once the class is `declare`d): `name`, `grain`,
    `settings`, `needs_thresholds`, `summary` and `from_spec`.
    """

    name: str = "criterion"
    #: what it judges (DESIGN "Decision grain"): TILE (the tiles of blocks), BLOCK (whole
    #: blocks unless a tile is given) or BLOCK_ONLY (whole blocks always)
    grain: str = TILE
    #: the render spec's rows it takes beyond tau and exposure, with its own defaults and
    #: ranges where the row's do not do (a row no criterion names is every render's)
    settings: ClassVar[dict[str, Setting]] = {}
    #: it needs a labelled reference's true thresholds (the render spec refuses it without)
    needs_thresholds: bool = False
    #: one line for the help: what it stops on
    summary: str = ""
    needs_quick: bool = False
    quick_kind: str = "albedo"
    needs_halves: bool = False
    #: its ratio is a noise level over the target, falling as 1/sqrt(spp) as Monte Carlo
    #: noise does, so the loop may predict when a unit can stop and skip its decisions
    #: before then (`renderer.live.passloop.next_decision`); else every pass is judged
    noise_ratio: bool = False
    #: it may call a unit converged; one that never does (the uniform baseline) is asked only
    #: at a unit's last pass (`renderer.live.passloop.PassLoop.run_round`), so the loop traces
    #: the passes before it in as few launches as it can
    #: (`renderer.live.launches.grown_passes`): no decision where none can succeed
    stops: bool = True

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
        """The criterion of a resolved render spec (`thresholds`: a labelled reference's true
        ones, per unit). By default the class called with its declared settings by name."""
        return cls(**{name: getattr(spec, name) for name in cls.settings})

    @classmethod
    def checked(cls, **given: Any) -> dict[str, Any]:
        """`given` (render settings by row name; None: not given) checked and defaulted by
        this criterion's declaration (`renderer.settings.declared_values`): what a constructor
        keeps of its arguments, by the one check the render spec makes."""
        from ..settings import declared_values

        return declared_values(cls, given)

    def describe(self) -> dict[str, Any]:
        """Name and parameters, for reports."""
        return {"name": self.name}

    def prepare(self, quick: np.ndarray) -> tuple[np.ndarray, Tally]:
        """What the batches' `quick` holds, from every block's quick image [n, bh, bw, 3]
        (the blocks themselves unless a criterion reads something computed from them once
        per render), and what making it cost."""
        return quick, Tally()

    def decide(self, ids: Sequence[int], batch: UnitBatch | Sequence[UnitView]) -> Decision:
        """The `Decision` on the listed units: a `UnitBatch` (the loop's), or one
        `UnitView` per unit."""
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
        if blind.any():
            verdict, ratio = np.where(blind, NOISY, verdict).astype(np.int8), np.where(blind, np.nan, ratio)
        features_s = float(tally.pop("features_s", 0.0))
        counts = {"decide_calls": 1, "units_asked": len(ids), "converged": int((verdict > 0).sum()),
                  "nonfinite_units": int((batch.nonfinite > 0).sum()), **tally}
        timers = {"features_s": features_s,
                  "decisions_s": max(0.0, time.perf_counter() - t0 - features_s)}
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
        """The criterion's own answer on a validated, non-empty batch, before `decide` checks
        it and wraps it into a `Decision`: what a criterion made of others combines (the
        model at tile grain, `renderer.criteria.gated`). See `_decide`."""
        return self._decide(ids, batch, tally)

    @abstractmethod
    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, ...]:
        """(verdict [k], ratio [k]) for validated, non-empty input, and for a criterion that
        decides from the history a third, the decision's evidence [k] (`Decision`); counts
        go into `tally`."""

    @staticmethod
    def _flat(batch: UnitBatch, exposure: float, tally: Tally) -> np.ndarray:
        """bool [n]: units with no visible variation at all (the stop rule's flat test),
        computed where the means live. Once both half buffers hold a pass, a flat mean is
        not enough: the halves must agree within one 8-bit level too (`learning.stoprule.
        flat_halves`, the served route's rule): a mean can be flat over halves that differ."""
        flat = flat_blocks(batch.mean, exposure)
        if batch.half_spp is not None and batch.has_halves:
            check = np.flatnonzero(flat & (batch.half_spp.min(axis=1) > 0))
            if check.size:
                flat[check] = flat_halves(*batch.halves_of(check), exposure)
        tally.add("flat_units", int(flat.sum()))
        return flat

    @staticmethod
    def _dots(batch: UnitBatch, ask: np.ndarray, exposure: float, tau: float, tally: Tally) -> np.ndarray:
        """float64 [len(batch)]: the asked units' dot term from their half buffers, relative
        to tau (`learning.stoprule.dots_ratio`; 0 for the others). Above 1 a unit still
        holds more isolated outlier pixels than the observer lets through, so it stays noisy
        whatever its score (`learning.stoprule.hold_dotted`, the served route's guard too)."""
        out = np.zeros(len(batch.spp))
        if ask.size:
            out[ask] = dots_ratio(*batch.halves_of(ask), exposure, tau)
            tally.add("dotted_units", int((out[ask] > 1).sum()))
        return out

    @staticmethod
    def _ready(batch: UnitBatch, flat: np.ndarray) -> np.ndarray:
        """The units with a noise estimate to judge: not flat, and both half buffers hold a
        pass (with one pass the halves cannot disagree yet)."""
        return np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0))   # type: ignore[union-attr]
