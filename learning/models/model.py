"""What every model bundle shares: the manifest's format constants, `Model` (a loaded
bundle giving verdicts through the one stop rule) and the small helpers the writers of both
kinds of bundle use.

Its own module so that `learning.models.bundle` (SVM bundles, and `load_model`, which
dispatches to the transfer bundles) and `learning.models.transfer_bundle` (whose
`TransferModel` is a `Model`) both import it and neither imports the other's internals:
`bundle` -> `transfer_bundle` -> `model`, no circle.
"""
from __future__ import annotations

import math
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from noisefeat import FeatureBase, default_base, extract_features
from noisefeat.base import N_FEATURES
from noisefeat.display import nonfinite_pixels
from noisefeat.extract import analyse_many

from ..inputs.noise_input import HALVES, halves_input, halves_input_and_stats, noise_lightness
from ..inputs.table import feature_input, raw_input
from ..names import DEFAULT_TAU
from ..stoprule import FLAT_TOLERANCE, StopRule, dots_ratio, flat_blocks, flat_halves, hold_dotted
from .estimators import RBFSVM
from .noise_target import offset_at, tau_range

FORMAT = "noisestop-model"
VERSION = 1
MANIFEST = "manifest.json"


def versions() -> dict[str, str]:
    """Library versions a bundle records (what it was trained and written with)."""
    import skops
    import sklearn
    return {"python": platform.python_version(), "numpy": np.__version__,
            "scikit-learn": sklearn.__version__, "torch": torch.__version__,
            "skops": skops.__version__}


@dataclass
class Model:
    """A loaded bundle: the estimator plus what it needs to turn blocks into verdicts.

    Verdicts always come from the one stop rule (`learning.stoprule`) at the estimator's
    calibrated `offset_`, or at the `offset` a caller passes (the user's speed/accuracy
    knob: `--offset` on render, evaluate and serve).
    """

    estimator: RBFSVM
    manifest: dict[str, Any]
    path: Path | None = None

    def __post_init__(self) -> None:
        tau_range(self.manifest)      # a damaged offsets-by-tau curve is refused on load, not on use

    @property
    def name(self) -> str:
        return self.manifest.get("name", self.manifest["kind"])

    @property
    def input(self) -> str:
        """'features' (26 noise features) or 'raw' (flattened L*/100 block)."""
        return self.manifest["input"]

    @property
    def offset(self) -> float:
        """The calibrated decision offset (the estimator's fitted `offset_`)."""
        return float(self.estimator.offset_)

    def offset_at(self, tau: float | None) -> float:
        """The calibrated offset at the noise target `tau` (None: the model's own;
        `learning.models.noise_target`); a tau the bundle was not calibrated for raises
        ValueError naming its range."""
        return offset_at(self.manifest, self.offset, tau)

    def rule(self, offset: float | None = None, min_spp: int | None = None) -> StopRule:
        """The stop rule at this model's offset, or at `offset` if given."""
        return StopRule(self.offset if offset is None else float(offset), min_spp)

    @property
    def quick(self) -> str:
        """The input mode: 'halves' (the half buffers: noise features for a feature model,
        the raw noise image for a raw one) or, for a feature model, the paper's quick image
        'albedo' (default), 'direct' or 'none'. A raw model otherwise reads the block alone."""
        default = "albedo" if self.input == "features" else "none"
        return self.manifest.get("quick") or default

    @property
    def needs_quick(self) -> bool:
        """Whether verdicts need the quick image (feature models on a quick image but 'none')."""
        return self.input == "features" and self.quick not in ("none", "halves")

    @property
    def needs_halves(self) -> bool:
        """Whether verdicts need the two half buffers (even, odd) instead of the block."""
        return self.quick == "halves"

    @property
    def n_features(self) -> int:
        return int(self.estimator.n_features_in_)

    @property
    def composition(self) -> str | None:
        """A `halves` model's input composition (`learning.inputs.noise_input`), else None."""
        return self.manifest.get("composition", HALVES) if self.needs_halves and self.input == "features" \
            else None

    def table_options(self) -> dict[str, Any]:
        """`learning.inputs.table.load_table` options that give the rows this model reads."""
        opts: dict[str, Any] = {"raw": self.input == "raw", "quick": self.quick}
        if self.composition is not None:
            opts["composition"] = self.composition
        return opts

    def decision_function(self, X: np.ndarray) -> np.ndarray:
        return self.estimator.decision_function(X)

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.estimator.predict(X)

    def inputs_from_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None,
                           base: FeatureBase | None = None, exposure: float = 0.0) -> np.ndarray:
        """Model inputs from linear RGB blocks [N, h, w, 3] (and their quick blocks)."""
        if self.needs_halves:
            raise ValueError("this model reads the two half buffers (even and odd passes) of every "
                             "block, not the block alone: use score_halves")
        if self.input == "raw":
            self._check_raw_size(np.shape(blocks))
            return raw_input(blocks, exposure)
        if self.needs_quick and quick is None:
            raise ValueError("a feature model needs the quick image of every block")
        base = base or default_base()
        quick_feats = extract_features(quick, base=base, exposure=exposure) if self.needs_quick else None
        return feature_input(extract_features(blocks, base=base, exposure=exposure), quick_feats)

    def _check_raw_size(self, shape: tuple[int, ...]) -> None:
        n = self.estimator.n_features_in_
        if len(shape) == 4 and shape[1] * shape[2] != n:
            side = math.isqrt(n)
            size = f"{side}x{side}" if side * side == n else f"{n}-pixel"
            raise ValueError(f"this raw-pixel model takes {size} blocks (its training size), "
                             f"got {shape[1]}x{shape[2]}")

    def inputs_from_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = 0.0) -> np.ndarray:
        """Model inputs from the half buffers of N blocks (a `halves` model): the noise
        features of `learning.inputs.noise_input` in the model's composition, or the raw noise image."""
        if not self.needs_halves:
            raise ValueError(f"this model reads {'raw blocks' if self.input == 'raw' else 'blocks'}"
                             f"{' and their quick images' if self.needs_quick else ''}, not half buffers")
        if self.input == "raw":
            self._check_raw_size(np.shape(even))
            return noise_lightness(even, odd, exposure)
        return halves_input(even, odd, exposure, composition=self.composition or HALVES)

    def score_inputs(self, X: np.ndarray, offset: float | None = None,
                     flat: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(verdict int8 [N], score float [N]) for model inputs (e.g. [N, 26] features), by
        the stop rule; `flat` (bool [N]) marks rows whose blocks were flat."""
        f = self.decision_function(X)
        return self.rule(offset).verdict(f, flat), f

    def score_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None,
                     exposure: float = 0.0, offset: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(verdict int8 [N], score float [N]) for linear RGB blocks: the stop rule's verdict,
        flat blocks included (they are converged whatever their score)."""
        verdict, score, _ = self.assess_blocks(blocks, quick, exposure, offset)
        return verdict, score

    def assess_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None, exposure: float = 0.0,
                      offset: float | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """`score_blocks` plus the non-finite pixel counts per block of what was read
        ({'blocks': [N]} and 'quick' when the model reads it): a feature model gets
        features, counts and the flat test from one fused pass (the server's route)."""
        if self.input == "features" and not self.needs_halves:
            score, flat, counts = self.assess_feature_batches([(blocks, quick)], exposure)[0]
            return self.rule(offset).verdict(score, flat), score, counts
        flat = flat_blocks(blocks, exposure) if len(blocks) else np.zeros(0, bool)
        x = self.inputs_from_blocks(blocks, quick, exposure=exposure)
        counts = {"blocks": nonfinite_counts(blocks)}
        if self.needs_quick and quick is not None:
            counts["quick"] = nonfinite_counts(quick)
        return (*self.score_inputs(x, offset, flat), counts)

    def assess_feature_batches(self, batches: list[tuple[np.ndarray, np.ndarray | None]], exposure: float = 0.0
                               ) -> list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]]:
        """For a feature model, several (blocks, quick) batches of one block size at once
        (a request's, or several requests'): one fused feature call and one SVM call for
        all. Per batch: (score [N], flat [N], non-finite counts as in `assess_blocks`)."""
        images, ranges = [], []
        for blocks, quick in batches:
            if self.needs_quick:
                if quick is None:
                    raise ValueError("a feature model needs the quick image of every block")
                if np.shape(quick) != np.shape(blocks):
                    raise ValueError(f"quick images {list(np.shape(quick))} and blocks {list(np.shape(blocks))} "
                                     "must have the same shape")
                images += [blocks, quick]
                ranges += [True, False]
            else:
                images.append(blocks)
                ranges.append(True)
        results = iter(analyse_many(images, exposure=exposure, display_range=ranges))
        rows, out = [], []
        for _ in batches:
            feats, stats = next(results)
            counts = {"blocks": stats.nonfinite}
            quick_feats = None
            if self.needs_quick:
                quick_feats, quick_stats = next(results)
                counts["quick"] = quick_stats.nonfinite
            rows.append(feature_input(feats, quick_feats))
            out.append((stats.display_range <= FLAT_TOLERANCE, counts))
        X = np.concatenate(rows) if rows else np.zeros((0, N_FEATURES), np.float32)
        scores = self.decision_function(X) if len(X) else np.zeros(0)
        bounds = np.cumsum([0] + [len(r) for r in rows])
        return [(scores[a:b], flat, counts) for a, b, (flat, counts) in zip(bounds[:-1], bounds[1:], out)]

    def score_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                     offset: float | None = None, tau: float = DEFAULT_TAU) -> tuple[np.ndarray, np.ndarray]:
        """(verdict int8 [N], score float [N]) for the half buffers of N blocks (a `halves`
        model); the block judged is their mean, which is also what the flat test reads."""
        verdict, score, _ = self.assess_halves(even, odd, exposure, offset, tau)
        return verdict, score

    def assess_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                      offset: float | None = None, tau: float = DEFAULT_TAU) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`score_halves` plus the non-finite pixels per block of both half buffers [N],
        counted in the pass that computes the input (the server's route). A block whose
        halves still disagree on more isolated pixels than the observer at `tau` lets through
        is noisy whatever its score (`learning.stoprule.hold_dotted`, the live loop's guard too)."""
        if not self.needs_halves:
            raise ValueError(f"this model reads {'raw blocks' if self.input == 'raw' else 'blocks'}"
                             f"{' and their quick images' if self.needs_quick else ''}, not half buffers")
        if self.input == "raw":
            x = self.inputs_from_halves(even, odd, exposure)
            flat = flat_halves(even, odd, exposure) if len(x) else np.zeros(0, bool)
            verdict, score = self.score_inputs(x, offset, flat)
            bad = nonfinite_counts(even) + nonfinite_counts(odd)
        else:
            x, stats = halves_input_and_stats(even, odd, exposure, composition=self.composition or HALVES)
            flat = flat_halves(even, odd, exposure) if len(x) else np.zeros(0, bool)
            (verdict, score), bad = self.score_inputs(x, offset, flat), stats.nonfinite
        return hold_dotted(verdict, dots_ratio(even, odd, exposure, tau), flat), score, bad


def nonfinite_counts(rgb: np.ndarray) -> np.ndarray:
    """int64 [N]: pixels holding a NaN or Inf channel, per block of [N, h, w, 3] (what a
    verdict reports alongside, for the blocks, quick images or half buffers it read)."""
    rgb = np.asarray(rgb)
    if not len(rgb):
        return np.zeros(0, np.int64)
    return nonfinite_pixels(torch.as_tensor(rgb)).numpy().astype(np.int64)
