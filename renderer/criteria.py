"""Stopping criteria: one interface for the live adaptive loop and the dataset simulation.

A criterion sees all the blocks it is asked about at once, as a `BlockBatch` (cumulative
means and the two half buffers as tensors on the accumulator's device, spp, quick blocks;
`BlockView`s, one per block, for callers outside the loop) and answers +1 (converged: stop
sampling it) or -1 (noisy: keep sampling) for each. The live loop (`renderer.adaptive`)
and the simulation on stored stacks (`renderer.simulate`) build the same batches from the
same accumulator and call the same `decide`, so what is measured offline is what runs
online.

Criteria:

* `ModelCriterion`: a learned model (a `learning.models.bundle.Model` in-process, or a
  `renderer.client.RemoteModel` talking to a verdict server); both expose
  ``score_blocks(blocks, quick) -> (verdict, score)``.
* `FlipCriterion`: training-free: FLIP between the display images of the two half
  buffers (`learning.inputs.halves`), converged when at most a calibrated c.
* `VarianceCriterion`: Blender Cycles' adaptive-sampling pixel test, grouped per block.
* `OracleCriterion`: the true thresholds of a labelled stack (the best possible stops).
* `UniformCriterion`: never stops (every block rendered to max spp: the baseline).

The model and flip criteria decide by the one stop rule (`learning.stoprule`): a block is
converged when its score exceeds the offset, or at once when it is flat (its display image
within one 8-bit level: no noise to see, whatever a model trained on textured scenes might
say about such out-of-distribution input). The loops around `decide` add the rest of the
rule: no decision before min spp, and a stop is held. `VarianceCriterion` applies the same
flat test (``flat_shortcut``, counted as ``flat_blocks``). This is what makes the
degenerate scenes (``allblack``, ``sky``) stop at their first decision.
"""
from __future__ import annotations

import hashlib
import logging
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from learning.stoprule import CONVERGED, NOISY, StopRule, flat_blocks
from noisefeat.pooling import CRITERION_POOLING
from noisefeat.runtime import torch_threads

from learning.names import DEFAULT_TAU

from .names import CRITERIA

logger = logging.getLogger(__name__)
# decide_calls: calls to decide; blocks_asked: verdicts given; blocks_featured: blocks whose
# current image went through the feature extractor (here or on a server); feature_rows:
# 26-feature rows computed in this process (current and quick blocks); converged: +1
# verdicts; flat_blocks: blocks settled by the flat shortcut; nonfinite_blocks: verdicts on
# blocks that held non-finite samples.
COUNTER_NAMES = ("decide_calls", "blocks_asked", "blocks_featured", "feature_rows", "converged",
                 "flat_blocks", "nonfinite_blocks", "dotted_blocks")
TIMER_NAMES = ("features_s", "decisions_s")


@dataclass(frozen=True)
class BlockView:
    """What a criterion may look at for one block at one moment of the render.

    `mean` is the cumulative mean of every sample so far, [bh, bw, 3] linear RGB.
    `halves` = (A, B): means of the even-numbered and odd-numbered passes (the
    `BlockAccumulator` convention), or None when the caller does not track them.
    `half_spp` = samples in A and in B. `quick` is the block of the quick noise-free image
    (None if not rendered). `nonfinite` counts (pixel, pass) values the accumulator dropped.
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
    is [k, bh, bw, 3] or None.
    """

    def __init__(self, spp: np.ndarray, *, mean: Any = None, halves: Any = None,
                 half_spp: np.ndarray | None = None, nonfinite: Any = None, quick: np.ndarray | None = None,
                 source: Any = None) -> None:
        self.spp = np.asarray(spp, np.int64).reshape(-1)
        self.half_spp = None if half_spp is None else np.asarray(half_spp, np.int64).reshape(-1, 2)
        self.quick = quick
        self._mean, self._halves, self._nonfinite, self._source = mean, halves, nonfinite, source

    @classmethod
    def from_accumulator(cls, acc: Any, ids: Sequence[int], quick: np.ndarray | None = None) -> BlockBatch:
        """The blocks `ids` of a `BlockAccumulator`, read lazily from its device tensors."""
        ids_a = np.asarray(ids, np.int64)
        return cls(acc.spp_all()[ids_a], half_spp=acc.half_spp_all()[ids_a],
                   quick=None if quick is None else quick[ids_a], source=(acc, ids_a))

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
                                       for v in views], np.int64), quick=quick)

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

    @property
    def nonfinite(self) -> np.ndarray:
        if self._nonfinite is None:
            acc, ids = self._source
            self._nonfinite = acc.nonfinite_all()[ids]
        return np.asarray(self._nonfinite, np.int64)

    def block_shape(self) -> tuple[int, ...]:
        if self._source is not None:
            return (*self._source[0].block, self._source[0].channels)
        return tuple(self.mean.shape[1:])


class BlockRatios:
    """Per block, how far its last verdict was from the target, as a ratio (> 1: above it,
    noisy; NaN: no estimate): what a budget render spends its passes by.

    Arrays indexed by block id (grown on demand), read and written a batch at a time
    (`take`, `put`) so a round costs no Python loop over blocks; the dict-like methods
    serve reports and tests. A block is in it once it has been asked, even with NaN."""

    def __init__(self) -> None:
        self.asked = np.zeros(0, bool)
        self.value = np.zeros(0, np.float64)

    def _grow(self, n: int) -> None:
        if n > len(self.asked):
            self.asked = np.concatenate([self.asked, np.zeros(n - len(self.asked), bool)])
            self.value = np.concatenate([self.value, np.full(n - len(self.value), np.nan)])

    def put(self, ids: Any, ratio: Any) -> None:
        idx = np.asarray(ids, np.int64).reshape(-1)
        if idx.size:
            self._grow(int(idx.max()) + 1)
            self.asked[idx] = True
            self.value[idx] = np.asarray(ratio, np.float64).reshape(-1)

    def take(self, ids: Any) -> tuple[np.ndarray, np.ndarray]:
        """(asked bool [k], ratio float64 [k], NaN where unknown) of blocks `ids`."""
        idx = np.asarray(ids, np.int64).reshape(-1)
        if idx.size:
            self._grow(int(idx.max()) + 1)
        return self.asked[idx].copy(), np.where(self.asked[idx], self.value[idx], np.nan)

    def __contains__(self, b: object) -> bool:
        return isinstance(b, (int, np.integer)) and 0 <= int(b) < len(self.asked) and bool(self.asked[int(b)])

    def __getitem__(self, b: int) -> float:
        if b not in self:
            raise KeyError(b)
        return float(self.value[int(b)])

    def __setitem__(self, b: int, ratio: float) -> None:
        self.put([b], [ratio])

    def get(self, b: int, default: float | None = None) -> float | None:
        return self[b] if b in self else default

    def __len__(self) -> int:
        return int(self.asked.sum())


class ScoresBlocks(Protocol):
    """Anything that turns linear RGB blocks into verdicts (local Model or RemoteModel)."""

    def score_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None, exposure: float = 0.0,
                     offset: float | None = None) -> tuple[np.ndarray, np.ndarray]: ...


class Criterion(ABC):
    """Base class: validates inputs, keeps counters and timers, enforces int8 +-1 output.

    `needs_quick` / `needs_halves` tell the caller what the views must carry, so the
    quick image is rendered (and half buffers recovered) only when some criterion uses
    them; `quick_kind` says which quick image ('albedo' or 'direct').
    """

    name: str = "criterion"
    needs_quick: bool = False
    quick_kind: str = "albedo"
    needs_halves: bool = False

    def __init__(self) -> None:
        self.counters: dict[str, int] = {k: 0 for k in COUNTER_NAMES}
        self.timers: dict[str, float] = {k: 0.0 for k in TIMER_NAMES}
        self.ratios = BlockRatios()

    def describe(self) -> dict[str, Any]:
        """Name and parameters, for reports."""
        return {"name": self.name}

    def reset_counters(self) -> None:
        """Start a render afresh: counters, timers and the per-block ratios of the last
        one (a criterion object reused for a second render must not prioritise its blocks
        by the first render's verdicts)."""
        self.counters = {k: 0 for k in COUNTER_NAMES}
        self.timers = {k: 0.0 for k in TIMER_NAMES}
        self.ratios = BlockRatios()

    def start_render(self) -> None:
        """Forget what a previous render left: the per-block ratios a budget render spends
        by (a criterion object reused for a second render must not prioritise its blocks
        by the first one's verdicts). Counters are the caller's to keep or reset."""
        self.ratios = BlockRatios()

    def restore_counters(self, counters: Mapping[str, int], timers: Mapping[str, float] | None = None) -> None:
        """Continue counting from a checkpoint."""
        self.counters.update({k: int(v) for k, v in counters.items()})
        if timers:
            self.timers.update({k: float(v) for k, v in timers.items()})

    def decide(self, ids: Sequence[int], batch: BlockBatch | Sequence[BlockView]) -> np.ndarray:
        """Verdicts int8 [len(ids)]: +1 converged, -1 noisy, for the listed blocks: a
        `BlockBatch` (the live loop's), or one `BlockView` per block."""
        ids = np.asarray(ids, np.int64).reshape(-1).tolist()
        if not isinstance(batch, BlockBatch):
            views = list(batch)
            if len(ids) != len(views):
                raise ValueError(f"{len(ids)} block ids but {len(views)} views")
            if not ids:
                return np.zeros(0, np.int8)
            for b, v in zip(ids, views):
                if not isinstance(v, BlockView):
                    raise ValueError(f"block {b}: expected a BlockView, got {type(v).__name__}")
                if np.ndim(v.mean) != 3 or np.shape(v.mean)[-1] != 3:
                    raise ValueError(f"block {b}: mean must be [bh, bw, 3], got shape {np.shape(v.mean)}")
                if self.needs_quick and v.quick is None:
                    raise ValueError(f"{self.name} criterion needs the quick image, block {b} has none")
                if self.needs_halves and (v.halves is None or v.half_spp is None):
                    raise ValueError(f"{self.name} criterion needs half buffers, block {b} has none")
            batch = BlockBatch.from_views(views)
        if len(ids) != len(batch):
            raise ValueError(f"{len(ids)} block ids but a batch of {len(batch)} blocks")
        if not ids:
            return np.zeros(0, np.int8)
        if self.needs_quick and batch.quick is None:
            raise ValueError(f"{self.name} criterion needs the quick image, the batch has none")
        if self.needs_halves and batch.half_spp is None:
            raise ValueError(f"{self.name} criterion needs half buffers, the batch has none")
        t0 = time.perf_counter()
        features_before = self.timers["features_s"]
        out = np.asarray(self._decide(ids, batch))
        if out.shape != (len(ids),):
            raise RuntimeError(f"{self.name} criterion returned shape {out.shape} for {len(ids)} blocks")
        if not np.isin(out, (-1, 1)).all():
            raise RuntimeError(f"{self.name} criterion returned values other than -1/+1: "
                               f"{np.unique(out)[:5].tolist()}")
        out = out.astype(np.int8)
        elapsed = time.perf_counter() - t0
        self.timers["decisions_s"] += max(0.0, elapsed - (self.timers["features_s"] - features_before))
        self.counters["decide_calls"] += 1
        self.counters["blocks_asked"] += len(ids)
        self.counters["converged"] += int((out > 0).sum())
        self.counters["nonfinite_blocks"] += int((batch.nonfinite > 0).sum())
        return out

    def prepare(self, ids: Sequence[int], quick: np.ndarray) -> None:
        """Called once with every block's quick image before the first decision (optional work)."""

    @abstractmethod
    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        """Verdicts for validated, non-empty input."""

    def _keep_ratios(self, ids: list[int], ratio: np.ndarray) -> None:
        self.ratios.put(ids, ratio)

    def _flat(self, batch: BlockBatch, exposure: float) -> np.ndarray:
        """bool [n]: blocks with no visible variation at all (the stop rule's flat test),
        computed where the means live."""
        flat = flat_blocks(batch.mean, exposure)
        self.counters["flat_blocks"] += int(flat.sum())
        return flat

    def _dots(self, batch: BlockBatch, ask: np.ndarray, exposure: float, tau: float) -> np.ndarray:
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
            self.counters["dotted_blocks"] += int((out[ask] > 1).sum())
        return out


class UniformCriterion(Criterion):
    """Never converged: every block is rendered to max spp (the uniform baseline)."""

    name = "uniform"

    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        return np.full(len(ids), NOISY, np.int8)


class OracleCriterion(Criterion):
    """Block b is converged iff spp >= T_b; a null threshold (censored) never converges.

    With the thresholds of a labelled stack this is the best any criterion can do on that
    stack: the yardstick of `spp_ratio_vs_oracle`.
    """

    name = "oracle"

    def __init__(self, thresholds: Sequence[int | None]) -> None:
        super().__init__()
        th = list(thresholds)
        for i, t in enumerate(th):
            if t is not None and (isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 1):
                raise ValueError(f"threshold of block {i} must be a positive integer or None, got {t!r}")
        self.thresholds: list[int | None] = [None if t is None else int(t) for t in th]

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "thresholds": self.thresholds}

    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        idx = np.asarray(ids, np.int64)
        bad = idx[(idx < 0) | (idx >= len(self.thresholds))]
        if bad.size:
            raise ValueError(f"block id {int(bad[0])} out of range: the oracle knows {len(self.thresholds)} blocks")
        th = np.array([np.inf if t is None else t for t in self.thresholds], np.float64)[idx]
        self._keep_ratios(ids, th / np.maximum(batch.spp, 1))
        return np.where(batch.spp >= th, CONVERGED, NOISY).astype(np.int8)


class VarianceCriterion(Criterion):
    """Blender Cycles' adaptive-sampling test, applied to every pixel of a block.

    Exact rule implemented (per pixel, channels r, g, b; I = cumulative mean of all
    samples, A = mean of the even-numbered passes, the first half buffer):

        diff      = |I_r - A_r| + |I_g - A_g| + |I_b - A_b|
        intensity = max(I_r + I_g + I_b, 0)
        norm      = sqrt(intensity) if intensity < 1 else intensity
        error     = diff / (1e-4 + norm)
        pixel passes  iff  error < scale * threshold        (scale = 1 by default)

    This is Cycles' ``film_adaptive_sampling_convergence_check``
    (intern/cycles/kernel/film/adaptive_sampling.h): there I and A are sums and A holds
    one class of samples doubled, and both are multiplied by 1/N, so I/N and A/N are the
    two means used here. The kernel compares against the user's noise threshold itself
    (``error < threshold``); REFERENCES.md's "5 x noise_threshold" is not in that source,
    so `scale` defaults to 1 and is exposed for anyone who wants the other reading.

    Block rule (Octane's "group pixels"): the block is converged when a fraction of at
    least `quantile` of its pixels pass (1.0, the default: every pixel). Cycles' one-pixel
    dilation of unconverged pixels is irrelevant with quantile 1 and is not done.

    Half buffers need two passes: with only one pass A equals I and the test would pass
    trivially, so a block whose odd half B is still empty is noisy. The first variance
    decision therefore comes at max(min_spp, 2 x step) unless the block is flat.
    Non-finite values follow noisefeat's rule (NaN/-Inf -> 0, +Inf -> 1), so no decision
    is ever NaN.
    """

    name = "variance"
    needs_halves = True

    def __init__(self, threshold: float = 0.01, quantile: float = 1.0, scale: float = 1.0,
                 flat_shortcut: bool = True, exposure: float = 0.0) -> None:
        super().__init__()
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"variance threshold must be a positive number, got {threshold!r}")
        if not (0.0 < quantile <= 1.0):
            raise ValueError(f"quantile must be in (0, 1], got {quantile!r}")
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        self.threshold, self.quantile, self.scale = float(threshold), float(quantile), float(scale)
        self.flat_shortcut, self.exposure = bool(flat_shortcut), float(exposure)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "threshold": self.threshold, "quantile": self.quantile,
                "scale": self.scale, "flat_shortcut": self.flat_shortcut}

    @staticmethod
    def _finite(x: Any) -> torch.Tensor:
        """The display rule's mapping of non-finite values, in linear float64: NaN and -Inf
        -> 0, +Inf -> 1 (so no error is ever NaN)."""
        return torch.nan_to_num(torch.as_tensor(x).to(torch.float64), nan=0.0, posinf=1.0, neginf=0.0)

    def pixel_error(self, mean: Any, half_a: Any) -> torch.Tensor:
        """Cycles' per-pixel error [..., bh, bw] (finite, >= 0), where the inputs live."""
        i = self._finite(mean)
        a = self._finite(half_a)
        diff = (i - a).abs().sum(dim=-1)
        intensity = i.sum(dim=-1).clamp_min(0.0)
        norm = torch.where(intensity < 1.0, intensity.sqrt(), intensity)
        return diff / (1e-4 + norm)

    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        flat = self._flat(batch, self.exposure) if self.flat_shortcut else np.zeros(len(ids), bool)
        out = np.full(len(ids), NOISY, np.int8)
        ratio = np.full(len(ids), np.nan)
        assert batch.half_spp is not None
        # one pass only: no noise estimate yet (A equals the mean)
        ask = np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0))
        if ask.size:
            sel = torch.from_numpy(ask).to(batch.mean.device)
            err = self.pixel_error(batch.mean[sel], batch.halves[0][sel]).flatten(1)   # type: ignore[index]
            limit = self.scale * self.threshold
            passed = (err < limit).to(torch.float64).mean(dim=1)
            q = torch.quantile(err, self.quantile, dim=1) if err.shape[1] <= 1 << 24 else \
                torch.from_numpy(np.quantile(err.cpu().numpy(), self.quantile, axis=1))
            out[ask] = np.where(passed.cpu().numpy() >= self.quantile, CONVERGED, NOISY)
            ratio[ask] = q.cpu().numpy() / limit
        out[flat] = CONVERGED
        ratio[flat] = 0.0
        self._keep_ratios(ids, ratio)
        return out


class ModelCriterion(Criterion):
    """A learned verdict model: local `learning.models.bundle.Model` or a `RemoteModel`.

    Verdicts follow the one stop rule: flat blocks are converged without asking the model;
    the others are converged when their score exceeds the offset (the model's calibrated
    `offset_`, or `offset` if given: the user's speed/accuracy knob). A remote server
    applies the same rule itself (its model's offset, or the `offset` sent with the
    request), so its verdicts are used as they come.

    For a local feature model the model input features(quick) - features(current) is
    computed here, in two timed steps (features, then the SVM), with the quick blocks'
    features cached per (block id, content hash): the quick image never changes during a
    render, so its features are computed once per block, not once per pass. A `halves`
    model reads each block's two half buffers instead (`Model.inputs_from_halves`; remote:
    ``score_halves``), from the second pass on. Any other scorer (a remote server, a
    raw-input model) is called through ``score_blocks``.
    """

    name = "model"

    def __init__(self, model: ScoresBlocks, exposure: float = 0.0, offset: float | None = None,
                 tau: float | None = None) -> None:
        super().__init__()
        if not hasattr(model, "score_blocks"):
            raise ValueError(f"model must have score_blocks(blocks, quick), got {type(model).__name__}")
        self.model = model
        self.exposure = float(exposure)
        self.tau = tau
        if offset is None and tau is not None and hasattr(model, "offset_at"):
            offset = model.offset_at(tau)       # the model's calibrated offset at the noise target
        self.offset = None if offset is None else float(offset)
        self.needs_halves = bool(getattr(model, "needs_halves", False))
        self.needs_quick = not self.needs_halves and bool(
            getattr(model, "needs_quick", getattr(model, "input", "features") != "raw"))
        self.quick_kind = str(getattr(model, "quick", "albedo")) if self.needs_quick else "albedo"
        self._local = hasattr(model, "rule") and hasattr(model, "decision_function")
        self._local_features = self._local and getattr(model, "input", None) == "features"
        # local models: the rule is applied here; remote: the server applies it (the offset
        # and exposure go with every request)
        self.rule: StopRule | None = model.rule(self.offset) if self._local else None  # type: ignore[attr-defined]
        self._quick_cache: dict[tuple[int, bytes], np.ndarray] = {}

    @property
    def effective_offset(self) -> float | None:
        """The offset verdicts are made at (None: a remote server's own, not known here)."""
        return self.rule.offset if self.rule is not None else self.offset

    def describe(self) -> dict[str, Any]:
        m = self.model
        d: dict[str, Any] = {"name": self.name, "offset": self.effective_offset, "tau": self.tau}
        manifest = getattr(m, "manifest", None)
        if isinstance(manifest, Mapping):
            d["model"] = {"kind": manifest.get("kind"), "name": manifest.get("name"),
                          "input": manifest.get("input"), "quick": manifest.get("quick"),
                          "path": str(getattr(m, "path", "") or "")}
        elif hasattr(m, "url"):
            d["model"] = {"remote": str(m.url), "name": str(getattr(m, "model", ""))}
        else:
            d["model"] = {"type": type(m).__name__}
        return d

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_quick_cache"] = {}  # cheap to rebuild, no need to ship it to workers
        return state

    def _quick_features(self, ids: list[int], quick: np.ndarray) -> np.ndarray:
        from noisefeat import extract_features

        keys = [(b, hashlib.blake2b(np.ascontiguousarray(q, np.float32).tobytes(), digest_size=16).digest())
                for b, q in zip(ids, quick)]
        missing = [i for i, k in enumerate(keys) if k not in self._quick_cache]
        if missing:
            with torch_threads(1):
                feats = extract_features(np.ascontiguousarray(quick[missing], np.float32),
                                         exposure=self.exposure)
            self.counters["feature_rows"] += len(missing)
            for i, f in zip(missing, feats):
                self._quick_cache[keys[i]] = f
        return np.stack([self._quick_cache[k] for k in keys])

    def prepare(self, ids: Sequence[int], quick: np.ndarray) -> None:
        """Compute (and count) the quick blocks' features up front: every block needs them."""
        if self._local_features and self.needs_quick and len(ids):
            t0 = time.perf_counter()
            self._quick_features(np.asarray(ids, np.int64).tolist(), np.asarray(quick, np.float32))
            self.timers["features_s"] += time.perf_counter() - t0

    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        flat = self._flat(batch, self.exposure)
        if self.needs_halves:       # no estimate of the noise before both halves hold a pass
            ask = np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0)).tolist()  # type: ignore[union-attr]
        else:
            ask = np.flatnonzero(~flat).tolist()
        score = np.full(len(ids), np.nan)
        remote_verdict = np.full(len(ids), NOISY, np.int8)
        # the model runs on the host: only the asked blocks are gathered there
        sel = torch.tensor(ask, dtype=torch.int64)
        if ask and self.needs_halves:
            halves = batch.halves
            assert halves is not None
            even, odd = (h[sel.to(h.device)].to(torch.float32).cpu().numpy() for h in halves)
            self.counters["blocks_featured"] += len(ask)
            if self._local:
                with torch_threads(1):
                    t0 = time.perf_counter()
                    x = self.model.inputs_from_halves(even, odd, self.exposure)  # type: ignore[attr-defined]
                    self.counters["feature_rows"] += len(ask)
                    self.timers["features_s"] += time.perf_counter() - t0
                score[ask] = self.model.decision_function(x)  # type: ignore[attr-defined]
            else:
                verdict, _ = self.model.score_halves(even, odd, exposure=self.exposure,  # type: ignore[attr-defined]
                                                     offset=self.offset)
                remote_verdict[ask] = np.where(np.asarray(verdict) > 0, CONVERGED, NOISY)
        elif ask:
            mean = batch.mean
            blocks = mean[sel.to(mean.device)].to(torch.float32).cpu().numpy()
            quick = np.asarray(batch.quick, np.float32)[ask] if self.needs_quick else None
            self.counters["blocks_featured"] += len(ask)
            if self._local_features:
                from learning.inputs.table import feature_input
                from noisefeat import extract_features

                with torch_threads(1):
                    t0 = time.perf_counter()
                    quick_feats = self._quick_features([ids[i] for i in ask], quick) if self.needs_quick else None
                    x = feature_input(extract_features(blocks, exposure=self.exposure), quick_feats)
                    self.counters["feature_rows"] += len(ask)
                    self.timers["features_s"] += time.perf_counter() - t0
                    score[ask] = self.model.decision_function(x)  # type: ignore[attr-defined]
            elif self._local:
                score[ask] = self.model.decision_function(  # type: ignore[attr-defined]
                    self.model.inputs_from_blocks(blocks, quick, exposure=self.exposure))  # type: ignore[attr-defined]
            else:
                verdict, _ = self.model.score_blocks(blocks, quick, exposure=self.exposure, offset=self.offset)
                verdict = np.asarray(verdict)
                if verdict.shape != (len(ask),):
                    raise RuntimeError(f"model returned {verdict.shape} verdicts for {len(ask)} blocks")
                remote_verdict[ask] = np.where(verdict > 0, CONVERGED, NOISY)
        # a halves model sees the observer's dots through the same halves (`Criterion._dots`)
        dots = self._dots(batch, np.asarray(ask, np.int64), self.exposure, self.tau or DEFAULT_TAU) \
            if self.needs_halves else np.zeros(len(ids))
        dotted = dots > 1
        if self.rule is None:                  # a server's verdicts, by the same rule there
            self._keep_ratios(ids, np.where(flat, 0.0, np.where(dotted, dots, np.nan)))
            return np.where(flat, CONVERGED, np.where(dotted, NOISY, remote_verdict))
        # a score is a signed distance, not a ratio: exp(offset - score) is 1 at the offset
        with np.errstate(over="ignore"):
            ratio = np.exp(np.clip(self.rule.offset - score, -50, 50))
        self._keep_ratios(ids, np.where(flat, 0.0, np.where(dotted, np.fmax(ratio, dots), ratio)))
        return self.rule.verdict(np.where(dotted, np.nan, score), flat)


class FlipCriterion(Criterion):
    """Training-free: FLIP between display(A) and display(B), the two half buffers.

    e = the raw LDR-FLIP map between the display images of the even-pass and odd-pass
    means, pooled as the observer pools (the largest 16x16 tile mean,
    `learning.inputs.halves`); the block is converged when e <= c (the stop rule with score
    -e), or at once when flat. `c` defaults to c(tau), the curve calibrated on training
    scenes only and shipped in `learning/flip.json`. A block whose halves still disagree on
    more isolated pixels than the observer lets through (`Criterion._dots`, issue 33) stays
    noisy whatever e is. A block whose odd half is
    still empty (one pass) has no estimate yet and stays noisy, so the first flip decision
    comes after two passes unless the block is flat. FLIP runs on the active, non-flat
    blocks only; its time is the decision cost (`decisions_s`).
    """

    name = "flip"
    needs_halves = True

    def __init__(self, c: float | None = None, exposure: float = 0.0, tau: float = DEFAULT_TAU) -> None:
        super().__init__()
        from learning.inputs.halves import flip_c, flip_offset, load_flip_calibration

        self.tau = float(tau)
        if c is None:
            cal = load_flip_calibration()
            self.c, self.source = flip_c(cal, self.tau), str(cal.get("source", "learning/flip.json"))
        else:
            self.c, self.source = float(c), "argument"
        self.rule = StopRule(flip_offset(self.c))
        self.exposure = float(exposure)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "threshold": self.c, "tau": self.tau, "pooling": CRITERION_POOLING,
                "source": self.source}

    def _decide(self, ids: list[int], batch: BlockBatch) -> np.ndarray:
        from noisefeat.flip import flip_halves_tensor

        flat = self._flat(batch, self.exposure)
        ask = np.flatnonzero(~flat & (batch.half_spp.min(axis=1) > 0))   # type: ignore[union-attr]
        score = np.full(len(ids), np.nan)
        if ask.size:
            a, b = batch.halves     # type: ignore[misc]
            sel = torch.from_numpy(ask).to(a.device)
            # FLIP where the half buffers live (the GPU with cuda_ad_rgb): scores come back
            score[ask] = -flip_halves_tensor(a[sel], b[sel], self.exposure, pooling=CRITERION_POOLING).cpu().numpy()
            self.counters["blocks_featured"] += int(ask.size)
        dots = self._dots(batch, ask, self.exposure, self.tau)
        # the half-buffer FLIP relative to c (the criterion's threshold c(tau)), or the dot
        # term relative to tau where that is larger; flat: 0
        with np.errstate(invalid="ignore"):
            ratio = np.fmax(-score / self.c if self.c > 0 else np.inf, dots)
        self._keep_ratios(ids, np.where(flat, 0.0, np.where(np.isnan(score), np.nan, ratio)))
        return self.rule.verdict(np.where(dots > 1, np.nan, score), flat)


def build_criterion(kind: str, *, model: str | None = None, server: str | None = None,
                    token: str | None = None, thresholds: Sequence[int | None] | None = None,
                    threshold: float | None = None, quantile: float = 1.0,
                    exposure: float = 0.0, offset: float | None = None,
                    tau: float = DEFAULT_TAU) -> Criterion:
    """A criterion from command-line style options.

    model: bundle path (None: the bundled model); server: verdict server URL (then the
    model name is `default` unless the URL ends with ``#name``); offset: the model's
    decision offset (None: its calibrated one at `tau`); threshold: flip's c (None: c(tau)
    of the shipped calibration) or variance's noise threshold (None: 0.01); tau: the noise
    target (the observer's tau the model's offset and flip's c are calibrated for);
    thresholds: needed by the oracle (from a labelled stack).
    """
    if kind == "uniform":
        return UniformCriterion()
    if kind == "variance":
        return VarianceCriterion(0.01 if threshold is None else threshold, quantile=quantile, exposure=exposure)
    if kind == "flip":
        return FlipCriterion(threshold, exposure=exposure, tau=tau)
    if kind == "oracle":
        if thresholds is None:
            raise ValueError("the oracle criterion needs true thresholds: give a labelled dataset "
                             "or stack of this scene (--reference DIR)")
        return OracleCriterion(thresholds)
    if kind == "model":
        if server:
            from .client import RemoteModel

            url, _, name = server.partition("#")
            return ModelCriterion(RemoteModel(url, model=name or "default", token=token, tau=tau),
                                  exposure=exposure, offset=offset, tau=tau)
        from learning.models.bundle import load_model

        return ModelCriterion(load_model(model), exposure=exposure, offset=offset, tau=tau)
    raise ValueError(f"unknown criterion {kind!r}; choose one of {', '.join(CRITERIA)}")


def make_criterion(criterion: Criterion | str, *, tau: float, model: str | os.PathLike[str] | None = None,
                   threshold: float | None = None, offset: float | None = None,
                   exposure: float = 0.0) -> Criterion | str:
    """A criterion object from a name and its options ('oracle' stays a name: its
    thresholds come from the reference stack), or `criterion` itself if already built."""
    from learning.data.observer import check_tau

    check_tau(tau)
    if isinstance(criterion, Criterion):
        return criterion
    if not isinstance(criterion, str) or criterion not in CRITERIA:
        raise ValueError(f"unknown criterion {criterion!r}; choose one of {', '.join(CRITERIA)}")
    if criterion == "oracle":
        return criterion
    return build_criterion(criterion, model=None if model is None else os.fspath(model), threshold=threshold,
                           offset=offset, exposure=float(exposure), tau=float(tau))
