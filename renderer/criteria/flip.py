"""The training-free criterion: FLIP between the two half buffers' display images."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from learning.inputs.history import LAST, STATISTIC, combine
from learning.stoprule import StopRule, hold_dotted
from noisefeat.pooling import CRITERION_POOLING

from .batch import UnitBatch
from .contract import Criterion, Tally
from .registry import TILE, Setting, declare

if TYPE_CHECKING:
    from ..spec import RenderSpec


@declare
class FlipCriterion(Criterion):
    """Training-free: a unit is converged when e <= c, or at once when flat, and stays noisy while
    dotted (`Criterion._dots`) or with one pass only. e is the LDR-FLIP map between the display
    images of the two half buffers, pooled as the observer pools (the largest 16x16 tile mean);
    at tile grain, the tile's history (`learning.inputs.history`: one level's score is noisy).
    c defaults to c(tau), calibrated on training scenes only and on the same statistic
    (`learning/flip.json`). The ratio is e / c, or the dot term where larger."""

    name = "flip"
    summary = "training-free: FLIP between the two half buffers, at most c(tau)"
    grain = TILE
    settings = {"threshold": Setting(doc="c, the FLIP between the half buffers (default c(tau), the "
                                         "shipped calibration)")}
    needs_halves = True
    noise_ratio = True

    def __init__(self, c: float | None = None, exposure: float | None = None, tau: float | None = None,
                 tile: int | None = None) -> None:
        """`c` None: c(tau); `tile`: the tile side when blocks are cut into tiles (None: whole blocks)."""
        from learning.inputs.halves import flip_c, flip_offset, load_flip_calibration, unit_calibration

        given = self.checked(threshold=c, exposure=exposure, tau=tau)
        self.tau, self.exposure = given["tau"], given["exposure"]
        #: the grain c(tau) is taken at: "block", or "tile16" when blocks are cut into tiles
        self.unit = "block" if tile is None else f"tile{int(tile)}"
        if given["threshold"] is None:
            cal = unit_calibration(load_flip_calibration(), tile)
            self.c, self.source = flip_c(cal, self.tau), str(cal.get("source", "learning/flip.json"))
            self.unit = str(cal.get("unit", "block"))
        else:
            self.c, self.source = given["threshold"], "argument"
        self.rule = StopRule(flip_offset(self.c))
        #: what e is: one level's score ("last") or the unit's history ("history-mean")
        self.statistic = LAST if tile is None else STATISTIC

    @classmethod
    def from_spec(cls, spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> FlipCriterion:
        return cls(spec.threshold, exposure=spec.exposure, tau=spec.tau, tile=spec.tile_grain())

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "threshold": self.c, "tau": self.tau, "pooling": CRITERION_POOLING,
                "source": self.source, "unit": self.unit, "statistic": self.statistic}

    def _flip(self, batch: UnitBatch, ask: np.ndarray) -> np.ndarray:
        """e of the asked units; a tile's is its whole block's FLIP map (context) pooled over it."""
        from noisefeat.flip import flip_halves_tensor, pool_tiles
        from noisefeat.flip_maps import flip_maps_tensor

        if batch.tiling is None:
            return flip_halves_tensor(*batch.halves_of(ask), self.exposure, pooling=CRITERION_POOLING).cpu().numpy()
        a, b, row, slot = batch.block_halves(ask)
        e = pool_tiles(flip_maps_tensor(a, b, self.exposure), batch.tiling.tile_windows(), CRITERION_POOLING)
        return e.cpu().numpy()[row, slot]

    def _decide(self, ids: list[int], batch: UnitBatch, tally: Tally) -> tuple[np.ndarray, np.ndarray]:
        flat = self._flat(batch, self.exposure, tally)
        ask = self._ready(batch, flat)
        score = np.full(len(ids), np.nan)
        if ask.size:
            score[ask] = -self._flip(batch, ask)
            tally.add("units_featured", int(ask.size))
        evidence = None
        if self.statistic == STATISTIC:
            e_hist, evidence = combine(batch.evidence, -score, batch.spp)
            score = -e_hist
        dots = self._dots(batch, ask, self.exposure, self.tau, tally)
        return *self._verdicts(score, flat, dots), evidence

    def _verdicts(self, score: np.ndarray, flat: np.ndarray, dots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(verdicts, ratios) of the scores -e (NaN: not decided) against c."""
        with np.errstate(invalid="ignore"):
            ratio = np.fmax(-score / self.c if self.c > 0 else np.inf, dots)
        ratio = np.where(flat, 0.0, np.where(np.isnan(score), np.nan, ratio))
        return hold_dotted(self.rule.verdict(score, flat), dots, flat), ratio
