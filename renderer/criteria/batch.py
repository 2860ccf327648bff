"""What a criterion reads: the units it is asked about at once (`UnitBatch`), or one `UnitView`
per unit. torch is imported where a tensor is made: the command line's parser goes without it."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch

@dataclass(frozen=True)
class UnitView:
    """One unit (a block, or a tile of one) now: `mean` [bh, bw, 3] linear RGB of every
    sample, `halves` (A, B) the means of the even and odd passes (None: not tracked) with
    `half_spp` samples, `quick` its part of the quick image, `nonfinite` the dropped
    (pixel, pass) values. A non-finite pixel in `mean`, or in a half that holds a pass, has
    no finite estimate (`renderer.criteria.contract`)."""

    mean: np.ndarray
    spp: int
    halves: tuple[np.ndarray, np.ndarray] | None = None
    half_spp: tuple[int, int] | None = None
    quick: np.ndarray | None = None
    nonfinite: int = 0


class UnitBatch:
    """All the units a criterion is asked about, at once: batched so that a criterion reading
    whole tensors on the renderer's device sends only its verdicts to the host. `mean` and
    `halves`: float64 [k, bh, bw, 3] on that device, read on first use; `spp`, `half_spp` [k, 2],
    `nonfinite` and `unestimated` (pixels with no finite estimate): int64 host arrays; `quick`:
    what the criterion's `prepare` made of the quick blocks, or None; `evidence`: the units'
    earlier decisions (`learning.inputs.history.Evidence`; None: every unit new); `tiling`: the
    renderer's `BlockWindows` when the units are tiles of blocks."""

    def __init__(self, spp: np.ndarray, *, mean: Any = None, halves: Any = None,
                 half_spp: np.ndarray | None = None, nonfinite: Any = None, quick: np.ndarray | None = None,
                 source: Any = None, tiling: Any = None, evidence: np.ndarray | None = None,
                 unestimated: Any = None) -> None:
        self.spp = np.asarray(spp, np.int64).reshape(-1)
        self.half_spp = None if half_spp is None else np.asarray(half_spp, np.int64).reshape(-1, 2)
        self.tiling, self.evidence, self.quick = tiling, evidence, quick
        self._mean, self._halves, self._nonfinite, self._source = mean, halves, nonfinite, source
        self._unestimated = unestimated
        self._blocks: Any = None           # the tiles' whole blocks, assembled once (`_assembled`)
        self._tile_halves: Any = None      # the halves of those blocks' tiles, as read for that

    @classmethod
    def from_accumulator(cls, acc: Any, ids: Sequence[int], quick: np.ndarray | None = None,
                         tiling: Any = None, evidence: np.ndarray | None = None) -> UnitBatch:
        """The units `ids` of a `UnitAccumulator`, read lazily; `quick` is per block."""
        ids_a = np.asarray(ids, np.int64)
        rows = ids_a if tiling is None else ids_a // tiling.tiles_per_block
        return cls(acc.spp_all()[ids_a], half_spp=acc.half_spp_all()[ids_a],
                   quick=None if quick is None else quick[rows], source=(acc, ids_a), tiling=tiling,
                   evidence=None if evidence is None else evidence.rows(ids_a))

    @classmethod
    def from_views(cls, views: Sequence[UnitView]) -> UnitBatch:
        """One batch from per-unit views."""
        import torch

        def stack(arrays: Any) -> torch.Tensor:
            return torch.from_numpy(np.stack([np.asarray(a, np.float64) for a in arrays]))

        shapes = {np.shape(v.mean) for v in views}
        if len(shapes) != 1:
            raise ValueError(f"the blocks of one decision must share a shape, got {sorted(shapes)}")
        halves = (tuple(stack(v.halves[j] for v in views) for j in (0, 1))  # type: ignore[index]
                  if all(v.halves is not None for v in views) else None)
        half_spp = np.array([v.half_spp for v in views], np.int64) if all(v.half_spp is not None for v in views) \
            else None
        quick = np.stack([np.asarray(v.quick) for v in views]) if all(v.quick is not None for v in views) else None
        return cls(np.array([v.spp for v in views], np.int64), mean=stack(v.mean for v in views), halves=halves,
                   half_spp=half_spp, quick=quick, nonfinite=np.array(
                       [v.nonfinite if np.isfinite(v.mean).all() else max(v.nonfinite, 1) for v in views], np.int64),
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

    @property
    def has_halves(self) -> bool:
        """Whether the batch holds half buffers, without reading them."""
        return self._halves is not None or self._source is not None

    def _assembled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[torch.Tensor, torch.Tensor]]:
        """Once a batch, of the blocks its tiles lie in: (their ids, the first of the batch's
        tiles in each, each tile's block row, the ids of all their tiles, their halves put
        together from all their tiles, stopped ones as they stopped, [kb, bh, bw, C])."""
        if self._blocks is None:
            acc, ids = self._source
            t = self.tiling.tiles_per_block
            blocks, first, row = np.unique(ids // t, return_index=True, return_inverse=True)
            every = (blocks[:, None] * t + np.arange(t)).reshape(-1)
            a, b = acc.halves(every)
            shape = (len(blocks), t, *a.shape[1:])
            self._tile_halves = (a, b)
            self._blocks = (blocks, first, row, every,
                            (self.tiling.assemble(a.reshape(shape)), self.tiling.assemble(b.reshape(shape))))
        return self._blocks

    def halves_of(self, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(A, B) of the units `rows` only, [len(rows), uh, uw, C]: tiles read just those, or
        cut them from the tiles `block_halves` read (bit for bit the same); whole blocks read
        every unit's once."""
        import torch

        rows = np.asarray(rows, np.int64)
        if self._halves is None and self._source is not None and self.tiling is not None:
            acc, ids = self._source
            if self._blocks is None:
                return acc.halves(ids[rows])
            _, _, block_row, _, _ = self._blocks
            t = self.tiling.tiles_per_block
            rows = block_row[rows] * t + ids[rows] % t       # the tiles' rows in `_tile_halves`
            a, b = self._tile_halves
        else:
            a, b = self.halves      # type: ignore[misc]
        sel = torch.from_numpy(rows).to(a.device)
        return a[sel], b[sel]

    def block_halves(self, among: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray]:
        """(A, B, row, slot): the assembled halves of the blocks the tiles `among` lie in;
        tile among[i] is tile `slot[i]` of block `row[i]`."""
        import torch

        _, _, rows, _, (a, b) = self._assembled()
        need, row = np.unique(rows[among], return_inverse=True)
        sel = torch.from_numpy(need).to(a.device)
        return a[sel], b[sel], row, self._source[1][among] % self.tiling.tiles_per_block

    def whole_blocks(self) -> tuple[UnitBatch, np.ndarray, np.ndarray]:
        """(batch, blocks, row): the blocks the tiles lie in as a batch of whole blocks (spp
        and half spp of their least sampled tile, dropped values summed), their ids, and
        each tile's block row: what a block-grain criterion judges a tile's block by."""
        acc, _ = self._source
        blocks, first, row, every, halves = self._assembled()
        per_block = (len(blocks), self.tiling.tiles_per_block)
        mean = acc.means(every)
        batch = UnitBatch(acc.spp_all()[every].reshape(per_block).min(axis=1),
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


def _unestimated_view(v: UnitView) -> int:
    """A view's pixels with no finite estimate (a half of unknown spp counts)."""
    bad = ~np.isfinite(np.asarray(v.mean, np.float64)).all(axis=-1)
    for j, half in enumerate(v.halves or ()):
        if v.half_spp is None or v.half_spp[j] > 0:
            bad |= ~np.isfinite(np.asarray(half, np.float64)).all(axis=-1)
    return int(bad.sum())
