"""What a stopping criterion is: the `Criterion` contract, the `BlockBatch` it reads, and
the `Decision` it returns.

A criterion sees all the blocks it is asked about at once, as a `BlockBatch` (cumulative
means and the two half buffers as tensors on the accumulator's device, spp, quick blocks;
`BlockView`s, one per block, for callers outside the loop) and answers, per block, +1
(converged: stop sampling it) or -1 (noisy: keep sampling) with its ratio to the target
(> 1: above it; what a budget render spends by). The live loop and the simulation on
stored stacks build the same batches and call the same `decide`
(`renderer.passloop.PassLoop.judge`), so what is measured offline is what runs online.

A criterion is configuration only, as a scikit-learn estimator's parameters are: one
object may judge any number of renders, in any order, in any process. What a render
accumulates (its counters, timers and ratios) is the loop's (`renderer.passloop`); a
`Decision` carries one call's share of it.

The model and flip criteria decide by the one stop rule (`learning.stoprule`): a block is
converged when its score exceeds the offset, or at once when it is flat (its display image
within one 8-bit level: no noise to see). The loop adds the rest of the rule: no decision
before min spp, and a stop is held.

Non-finite samples (issue 51): a unit with no finite estimate is never converged, whatever
the criterion (`Criterion.decide` holds it noisy, ratio NaN, after the criterion's own
verdict; uniform never stops anyway), so it renders to max spp. "No finite estimate"
(`BlockBatch.unestimated`): some pixel of the unit has no finite value in a half buffer
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
from typing import Any

import numpy as np
import torch

from learning.stoprule import NOISY, flat_blocks, flat_halves

# decide_calls: calls to decide; blocks_asked: verdicts given; blocks_featured: blocks whose
# current image went through the feature extractor or FLIP (here or on a server);
# feature_rows: 26-feature rows computed in this process (current and quick blocks);
# converged: +1 verdicts; flat_blocks: blocks settled by the flat test; nonfinite_blocks:
# verdicts on blocks that held non-finite samples; dotted_blocks: blocks held noisy by the
# dot guard; gated_tiles: tiles flip called converged that the model's block verdict held
# (the model at tile grain, `renderer.criteria.gated`).
COUNTER_NAMES = ("decide_calls", "blocks_asked", "blocks_featured", "feature_rows", "converged",
                 "flat_blocks", "nonfinite_blocks", "dotted_blocks", "gated_tiles")
TIMER_NAMES = ("features_s", "decisions_s")


@dataclass(frozen=True)
class BlockView:
    """What a criterion may look at for one block at one moment of the render.

    `mean` is the cumulative mean of every sample so far, [bh, bw, 3] linear RGB.
    `halves` = (A, B): means of the even-numbered and odd-numbered passes (the
    `UnitAccumulator` convention), or None when the caller does not track them.
    `half_spp` = samples in A and in B. `quick` is the block of the quick noise-free image
    (None if not rendered). `nonfinite` counts (pixel, pass) values the accumulator dropped.
    A non-finite pixel in `mean`, or in a half whose `half_spp` is positive, is one with no
    finite estimate: the block is never converged (the module docstring).
    """

    mean: np.ndarray
    spp: int
    halves: tuple[np.ndarray, np.ndarray] | None = None
    half_spp: tuple[int, int] | None = None
    quick: np.ndarray | None = None
    nonfinite: int = 0


class BlockBatch:
    """What a criterion may look at for all the blocks it is asked about, at once.

    Why batched: the live loop keeps its accumulators on the renderer's device, and a
    criterion that reads whole tensors (flip: FLIP on the device) sends only its verdicts
    to the host. `mean` and `halves` are float64 tensors [k, bh, bw, 3] on that device,
    computed on first use (a criterion that does not read them costs nothing); `spp`
    int64 [k], `half_spp` int64 [k, 2] and `nonfinite` int64 [k] are host arrays; `quick`
    is what the criterion's `prepare` made of the quick image's blocks [k, ...] (the
    blocks themselves unless it prepares them), or None. `evidence` float64 [k, 3]: each
    unit's earlier decisions as the loop keeps them (`learning.inputs.history.Evidence`),
    or None (no history: a criterion that reads it treats every unit as new). `tiling` (the renderer's
    `BlockWindows`, when the units are tiles of blocks): `block_halves` puts the asked
    tiles' blocks back together, for a criterion that judges a tile in its context.
    `unestimated` int64 [k] (host): pixels with no finite estimate (the module docstring).
    """

    def __init__(self, spp: np.ndarray, *, mean: Any = None, halves: Any = None,
                 half_spp: np.ndarray | None = None, nonfinite: Any = None, quick: np.ndarray | None = None,
                 source: Any = None, tiling: Any = None, evidence: np.ndarray | None = None,
                 unestimated: Any = None) -> None:
        self.spp = np.asarray(spp, np.int64).reshape(-1)
        self.tiling = tiling
        self.evidence = evidence
        self.half_spp = None if half_spp is None else np.asarray(half_spp, np.int64).reshape(-1, 2)
        self.quick = quick
        self._mean, self._halves, self._nonfinite, self._source = mean, halves, nonfinite, source
        self._unestimated = unestimated
        self._blocks: Any = None           # the tiles' whole blocks, assembled once (`_assembled`)

    @classmethod
    def from_accumulator(cls, acc: Any, ids: Sequence[int], quick: np.ndarray | None = None,
                         tiling: Any = None, evidence: np.ndarray | None = None) -> BlockBatch:
        """The units `ids` of a `UnitAccumulator`, read lazily from its device tensors.
        `quick` is per block: with `tiling`, a tile's row is its block's. `evidence`: the
        loop's `learning.inputs.history.Evidence`, or None."""
        ids_a = np.asarray(ids, np.int64)
        rows = ids_a if tiling is None else ids_a // tiling.tiles_per_block
        return cls(acc.spp_all()[ids_a], half_spp=acc.half_spp_all()[ids_a],
                   quick=None if quick is None else quick[rows], source=(acc, ids_a), tiling=tiling,
                   evidence=None if evidence is None else evidence.rows(ids_a))

    @classmethod
    def from_views(cls, views: Sequence[BlockView]) -> BlockBatch:
        """One batch from per-block views (callers outside the live loop, tests)."""
        shapes = {np.shape(v.mean) for v in views}
        if len(shapes) != 1:
            raise ValueError(f"the blocks of one decision must share a shape, got {sorted(shapes)}")
        halves = None
        if all(v.halves is not None for v in views):
            halves = tuple(torch.from_numpy(np.stack([np.asarray(v.halves[j], np.float64) for v in views]))  # type: ignore[index]
                           for j in (0, 1))
        half_spp = np.array([v.half_spp for v in views], np.int64) if all(v.half_spp is not None for v in views) \
            else None
        quick = np.stack([np.asarray(v.quick) for v in views]) if all(v.quick is not None for v in views) else None
        mean = torch.from_numpy(np.stack([np.asarray(v.mean, np.float64) for v in views]))
        return cls(np.array([v.spp for v in views], np.int64), mean=mean, halves=halves, half_spp=half_spp,
                   nonfinite=np.array([v.nonfinite if np.isfinite(v.mean).all() else max(v.nonfinite, 1)
                                       for v in views], np.int64), quick=quick,
                   unestimated=np.array([_unestimated_view(v) for v in views], np.int64))

    def __len__(self) -> int:
        return len(self.spp)

    @property
    def mean(self) -> torch.Tensor:
        if self._mean is None:
            acc, ids = self._source
            self._mean = acc.means(ids)
        return self._mean

    @property
    def halves(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        if self._halves is None and self._source is not None:
            acc, ids = self._source
            self._halves = acc.halves(ids)
        return self._halves

    def _assembled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[torch.Tensor, torch.Tensor]]:
        """(blocks, first, row, every, (A, B)) of the blocks the batch's tiles lie in, once a
        batch: their ids, the first of the batch's tiles in each, each tile's block row, the
        ids of all their tiles, and their half buffers put together from all their tiles
        (stopped ones as they stopped), [kb, bh, bw, C] on the device."""
        if self._blocks is None:
            acc, ids = self._source
            t = self.tiling.tiles_per_block
            blocks, first, row = np.unique(ids // t, return_index=True, return_inverse=True)
            every = (blocks[:, None] * t + np.arange(t)).reshape(-1)
            a, b = acc.halves(every)
            shape = (len(blocks), t, *a.shape[1:])
            self._blocks = (blocks, first, row, every,
                            (self.tiling.assemble(a.reshape(shape)), self.tiling.assemble(b.reshape(shape))))
        return self._blocks

    def block_halves(self, among: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
        """(A, B, row, slot): the half buffers of the blocks the batch's tiles `among` lie in,
        each block window put together from all its tiles (stopped ones as they stopped),
        [kb, bh, bw, C] on the device; tile among[i] is tile `slot[i]` of block `row[i]`."""
        _, _, rows, _, (a, b) = self._assembled()
        need, row = np.unique(rows[among], return_inverse=True)
        sel = torch.from_numpy(need).to(a.device)
        return a[sel], b[sel], row, self._source[1][among] % self.tiling.tiles_per_block

    def whole_blocks(self) -> tuple[BlockBatch, np.ndarray, np.ndarray]:
        """(batch, blocks, row): the blocks the batch's tiles lie in as one batch of whole
        blocks (windows put together from all their tiles, stopped ones as they stopped; a
        block's spp and half spp are its least sampled tile's, its dropped values the sum),
        their ids, and the row of each asked tile's block: what a block-grain criterion
        judges a tile's block by."""
        acc, _ = self._source
        blocks, first, row, every, halves = self._assembled()
        per_block = (len(blocks), self.tiling.tiles_per_block)
        mean = acc.means(every)
        batch = BlockBatch(acc.spp_all()[every].reshape(per_block).min(axis=1),
                           mean=self.tiling.assemble(mean.reshape(*per_block, *mean.shape[1:])), halves=halves,
                           half_spp=acc.half_spp_all()[every].reshape(*per_block, 2).min(axis=1),
                           nonfinite=acc.nonfinite_all()[every].reshape(per_block).sum(axis=1),
                           unestimated=acc.unestimated(every).reshape(per_block).sum(axis=1),
                           quick=None if self.quick is None else self.quick[first])
        return batch, blocks, row

    @property
    def nonfinite(self) -> np.ndarray:
        if self._nonfinite is None:
            acc, ids = self._source
            self._nonfinite = acc.nonfinite_all()[ids]
        return np.asarray(self._nonfinite, np.int64)

    @property
    def unestimated(self) -> np.ndarray:
        if self._unestimated is None:
            if self._source is None:
                return np.zeros(len(self.spp), np.int64)
            acc, ids = self._source
            self._unestimated = acc.unestimated(ids)
        return np.asarray(self._unestimated, np.int64)


def _unestimated_view(v: BlockView) -> int:
    """A view's pixels with no finite estimate: non-finite in its mean, or in a half that
    holds a pass (a half of unknown spp counts when given)."""
    bad = ~np.isfinite(np.asarray(v.mean, np.float64)).all(axis=-1)
    for j, half in enumerate(v.halves or ()):
        if v.half_spp is None or v.half_spp[j] > 0:
            bad |= ~np.isfinite(np.asarray(half, np.float64)).all(axis=-1)
    return int(bad.sum())


@dataclass(frozen=True)
class Decision:
    """One `decide` call's answer: `verdict` int8 [k] (+1 converged, -1 noisy), `ratio`
    float64 [k] (each block's distance to the target as a ratio, > 1 above it, 0 flat, NaN
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
    them; `quick_kind` says which quick image ('albedo' or 'direct'). `per_tile`: whether it
    judges the tiles of blocks (the render spec gives the others whole blocks).
    `noise_ratio`: whether the loop may skip decisions from its ratio (below).
    """

    name: str = "criterion"
    #: judges tiles as well as blocks (DESIGN "Decision grain"); else whole blocks only
    per_tile: bool = True
    needs_quick: bool = False
    quick_kind: str = "albedo"
    needs_halves: bool = False
    #: its ratio is a noise level over the target, falling as 1/sqrt(spp) as Monte Carlo
    #: noise does, so the loop may predict when a unit can stop and skip its decisions
    #: before then (`renderer.passloop.next_decision`); else every pass is judged
    noise_ratio: bool = False

    def describe(self) -> dict[str, Any]:
        """Name and parameters, for reports."""
        return {"name": self.name}

    def prepare(self, quick: np.ndarray) -> tuple[np.ndarray, Tally]:
        """What the batches' `quick` holds, from every block's quick image [n, bh, bw, 3]
        (the blocks themselves unless a criterion reads something computed from them once
        per render), and what making it cost."""
        return quick, Tally()

    def decide(self, ids: Sequence[int], batch: BlockBatch | Sequence[BlockView]) -> Decision:
        """The `Decision` on the listed blocks: a `BlockBatch` (the loop's), or one
        `BlockView` per block."""
        ids = np.asarray(ids, np.int64).reshape(-1).tolist()
        tally = Tally()
        if not isinstance(batch, BlockBatch):
            batch = self._batch_of_views(ids, list(batch), tally)
        if len(ids) != len(batch):
            raise ValueError(f"{len(ids)} block ids but a batch of {len(batch)} blocks")
        if not ids:
            return Decision(np.zeros(0, np.int8), np.zeros(0))
        if self.needs_quick and batch.quick is None:
            raise ValueError(f"{self.name} criterion needs the quick image, the batch has none")
        if self.needs_halves and batch.half_spp is None:
            raise ValueError(f"{self.name} criterion needs half buffers, the batch has none")
        t0 = time.perf_counter()
        verdict, ratio, *rest = self._decide(ids, batch, tally)
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
        counts = {"decide_calls": 1, "blocks_asked": len(ids), "converged": int((verdict > 0).sum()),
                  "nonfinite_blocks": int((batch.nonfinite > 0).sum()), **tally}
        timers = {"features_s": features_s,
                  "decisions_s": max(0.0, time.perf_counter() - t0 - features_s)}
        return Decision(verdict, ratio, evidence, counts, timers)

    def _batch_of_views(self, ids: list[int], views: list[BlockView], tally: Tally) -> BlockBatch:
        if len(ids) != len(views):
            raise ValueError(f"{len(ids)} block ids but {len(views)} views")
        for b, v in zip(ids, views):
            if not isinstance(v, BlockView):
                raise ValueError(f"block {b}: expected a BlockView, got {type(v).__name__}")
            if np.ndim(v.mean) != 3 or np.shape(v.mean)[-1] != 3:
                raise ValueError(f"block {b}: mean must be [bh, bw, 3], got shape {np.shape(v.mean)}")
            if self.needs_quick and v.quick is None:
                raise ValueError(f"{self.name} criterion needs the quick image, block {b} has none")
            if self.needs_halves and (v.halves is None or v.half_spp is None):
                raise ValueError(f"{self.name} criterion needs half buffers, block {b} has none")
        batch = BlockBatch.from_views(views) if views else BlockBatch(np.zeros(0, np.int64))
        if batch.quick is not None and len(batch):
            batch.quick, made = self.prepare(batch.quick)
            for k, v in made.items():
                tally.add(k, v)
        return batch

    @abstractmethod
    def _decide(self, ids: list[int], batch: BlockBatch, tally: Tally) -> tuple[np.ndarray, ...]:
        """(verdict [k], ratio [k]) for validated, non-empty input, and for a criterion that
        decides from the history a third, the decision's evidence [k] (`Decision`); counts
        go into `tally`."""

    @staticmethod
    def _flat(batch: BlockBatch, exposure: float, tally: Tally) -> np.ndarray:
        """bool [n]: blocks with no visible variation at all (the stop rule's flat test),
        computed where the means live. Once both half buffers hold a pass, a flat mean is
        not enough: the halves must agree within one 8-bit level too (`learning.stoprule.
        flat_halves`, the served route's rule): a mean can be flat over halves that differ."""
        flat = flat_blocks(batch.mean, exposure)
        if batch.half_spp is not None and batch.halves is not None:
            check = np.flatnonzero(flat & (batch.half_spp.min(axis=1) > 0))
            if check.size:
                a, b = batch.halves
                sel = torch.from_numpy(check).to(a.device)
                flat[check] = flat_halves(a[sel], b[sel], exposure)
        tally.add("flat_blocks", int(flat.sum()))
        return flat

    @staticmethod
    def _dots(batch: BlockBatch, ask: np.ndarray, exposure: float, tau: float, tally: Tally) -> np.ndarray:
        """float64 [len(batch)]: the asked blocks' dot term from their half buffers, relative
        to tau (`noisefeat.dots.halves_dots` / tau; 0 for the others). Above 1 a block still
        holds more isolated outlier pixels than the observer lets through, so it stays noisy
        whatever its score: the observer's version-3 rule, seen through the halves (issue 33).
        Computed where the buffers live; only the numbers cross to the host."""
        from noisefeat.dots import halves_dots

        out = np.zeros(len(batch.spp))
        if ask.size:
            a, b = batch.halves     # type: ignore[misc]
            sel = torch.from_numpy(ask).to(a.device)
            out[ask] = halves_dots(a[sel], b[sel], exposure).cpu().numpy() / tau
            tally.add("dotted_blocks", int((out[ask] > 1).sum()))
        return out

    @staticmethod
    def _ready(batch: BlockBatch, flat: np.ndarray) -> np.ndarray:
        """The blocks with a noise estimate to judge: not flat, and both half buffers hold a
        pass (with one pass the halves cannot disagree yet)."""
        return np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0))   # type: ignore[union-attr]
