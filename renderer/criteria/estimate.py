"""The learned stop at tile grain: the halves' history score corrected per tile by
a learned estimate of the observer's error, against a curve c(tau) calibrated out of fold."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.inputs.history import STATISTIC, combine
from learning.stoprule import StopRule
from noisefeat.pooling import CRITERION_POOLING

from .batch import UnitBatch
from .contract import Tally
from .flip import FlipCriterion
from .registry import TILE, Setting, declare

if TYPE_CHECKING:
    from ..spec import RenderSpec


@declare
class EstimateCriterion(FlipCriterion):
    """Learned: a tile stops when its estimated observer error is at most c(tau). The estimate
    (`learning.models.tile_error`) is flip's history e_hist times exp(g(x)), g learned from what
    the loop has at the decision (`learning.inputs.tile_features`): higher where the halves are
    blind (dark tiles, rare paths both miss), lower where texture masks what they see. c(tau) is
    the bundle's, chosen out of fold, so the margin is the estimate's own error. Flat and dotted
    tiles as with flip; the ratio is estimate / c."""

    name = "estimate"
    summary = "learned: the halves' history corrected per tile by a learned error estimate, at most c(tau)"
    grain = TILE
    settings = {"threshold": Setting(doc="c, the estimated observer error a tile stops at (default c(tau), "
                                         "the bundle's calibration)")}

    def __init__(self, c: float | None = None, exposure: float | None = None, tau: float | None = None,
                 tile: int | None = None, bundle: Any = None) -> None:
        """`c` None: the bundle's c(tau); `tile`: the unit side, the bundle's (None: checked at
        the first decision); `bundle`: a `TileErrorBundle` (None: the shipped one)."""
        from learning.inputs.halves import flip_offset
        from learning.models.tile_error_bundle import load_tile_error_bundle

        given = self.checked(threshold=c, exposure=exposure, tau=tau)
        self.tau, self.exposure = given["tau"], given["exposure"]
        self.bundle = load_tile_error_bundle() if bundle is None else bundle
        if tile is not None and tile != self.bundle.tile:
            raise ValueError(self._grain_error(tile))
        self.unit = f"tile{self.bundle.tile}"
        if given["threshold"] is None:
            self.c, self.source = self.bundle.c(self.tau), self.bundle.source
        else:
            self.c, self.source = given["threshold"], "argument"
        self.rule = StopRule(flip_offset(self.c))
        self.statistic = STATISTIC

    def _grain_error(self, tile: int) -> str:
        return (f"criterion estimate decides per {self.bundle.tile}-px tile (its training grain), got "
                f"{tile}-px units: give --tile {self.bundle.tile} or another criterion")

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> EstimateCriterion:
        return cls(spec.threshold, exposure=spec.exposure, tau=spec.tau, tile=spec.unit_side())

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "estimator": self.bundle.describe()}

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        from learning.inputs.tile_features import tile_features
        from learning.inputs.tile_stats import tile_stats
        from noisefeat.flip import pool_tiles
        from noisefeat.flip_maps import flip_maps_tensor

        flat = self._flat(batch, self.exposure, tally)
        ask = self._ready(batch, flat)
        e = np.full(len(ids), np.nan)
        estimate = np.full(len(ids), np.nan)
        dots = self._dots(batch, ask, self.exposure, self.tau, tally)
        if ask.size:
            if batch.tiling is not None:
                a, b, row, slot = batch.block_halves(ask)
                windows = batch.tiling.tile_windows()
            else:                   # whole blocks of the tile's size: each its own context
                a, b = batch.halves_of(ask)
                if tuple(a.shape[1:3]) != (self.bundle.tile, self.bundle.tile):
                    raise ValueError(self._grain_error(int(a.shape[1])))
                row, slot, windows = np.arange(len(ask)), np.zeros(len(ask), np.int64), [(0, 0, a.shape[2], a.shape[1])]
            block_e = pool_tiles(flip_maps_tensor(a, b, self.exposure), windows, CRITERION_POOLING).cpu().numpy()
            stats = tile_stats(a, b, windows, self.exposure).cpu().numpy()
            e[ask] = block_e[row, slot]
            tally.add("units_featured", int(ask.size))
        e_hist, evidence = combine(batch.evidence, e, batch.spp)
        if ask.size:
            # the dot term as the stacks hold it (`learning.inputs.halves.stack_tile_terms`):
            # relative to nothing, so the ratio to tau is brought back
            X = tile_features(e[ask], e_hist[ask], batch.spp[ask], dots[ask] * self.tau, block_e[row],
                              stats[row, slot])
            estimate[ask] = self.bundle.estimator.estimate(X)
            tally.add("feature_rows", int(ask.size))
        return *self._verdicts(-estimate, flat, dots), evidence
