"""Exact cumulative per-block means and the even/odd half buffers of a progressive render.

Shared by the live loop (`renderer.adaptive`, fed rendered passes) and everything that
replays a stored stack (`learning.inputs.halves`, `renderer.simulate`, fed passes recovered
from its levels): one arithmetic, so a criterion sees bit-identical buffers either way.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

logger = logging.getLogger(__name__)


class BlockAccumulator:
    """Exact cumulative per-block means, sample counts and even/odd half buffers.

    Each ``add`` is one *pass*: a block image that is the mean of `spp` new samples.
    Sums are kept in float64 as ``image * spp`` so ``mean = sum / spp`` whatever the
    pass sizes. Passes alternate between two half buffers per block: pass 0, 2, 4...
    go to A and 1, 3, 5... to B (the Cycles-style criterion compares the mean of all
    samples with the mean of one half; with equal pass sizes ``mean = (A + B) / 2``).

    Non-finite values (Mitsuba can emit NaN/Inf): a pixel whose value in a pass is not
    finite in any channel is dropped *for that pixel and pass only*: it adds nothing to
    the pixel's sum nor to its sample weight, so the pixel's mean stays an average of
    finite passes instead of being dragged to 0 or poisoned. The block's `spp` still
    counts the samples spent (it is a cost), and `nonfinite` counts the dropped
    (pixel, pass) pairs. A pixel with no finite pass has mean 0.
    """

    STATE_VERSION = 1

    def __init__(self, grid: tuple[int, int], block: tuple[int, int], channels: int = 3) -> None:
        gh, gw = (int(g) for g in grid)
        bh, bw = (int(b) for b in block)
        if min(gh, gw, bh, bw, int(channels)) < 1:
            raise ValueError(f"grid {grid!r}, block {block!r} and channels {channels!r} must be positive")
        self.grid, self.block, self.channels = (gh, gw), (bh, bw), int(channels)
        n = gh * gw
        self._sum = np.zeros((2, n, bh, bw, self.channels), dtype=np.float64)
        self._weight = np.zeros((2, n, bh, bw), dtype=np.int64)
        self._spp = np.zeros((n, 2), dtype=np.int64)
        self._passes = np.zeros(n, dtype=np.int64)
        self._nonfinite = np.zeros(n, dtype=np.int64)

    @property
    def n_blocks(self) -> int:
        return self.grid[0] * self.grid[1]

    def _check_id(self, block_id: int) -> int:
        if not isinstance(block_id, (int, np.integer)) or not 0 <= int(block_id) < self.n_blocks:
            raise ValueError(f"block id {block_id!r} out of range 0..{self.n_blocks - 1}")
        return int(block_id)

    def add(self, block_id: int, image: np.ndarray, spp: int) -> int:
        """Add one pass (`image` = mean of `spp` samples); return its dropped pixel count."""
        b = self._check_id(block_id)
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        img = np.asarray(image, dtype=np.float64)
        want = (*self.block, self.channels)
        if img.shape != want:
            raise ValueError(f"block {b}: image shape {img.shape} does not match {want}")
        ok = np.isfinite(img).all(axis=-1)
        half = int(self._passes[b] % 2)
        self._sum[half, b] += np.where(ok[..., None], img, 0.0) * spp
        self._weight[half, b] += ok * int(spp)
        self._spp[b, half] += int(spp)
        self._passes[b] += 1
        dropped = int(ok.size - ok.sum())
        self._nonfinite[b] += dropped
        if dropped:
            logger.debug("block %d: dropped %d non-finite pixel(s) of a %d-spp pass", b, dropped, spp)
        return dropped

    def add_many(self, block_ids: Sequence[int], images: np.ndarray, spp: int) -> int:
        """`add` for a batch as returned by `BlockRenderer.render_blocks`."""
        if len(block_ids) != len(images):
            raise ValueError(f"{len(block_ids)} block ids but {len(images)} images")
        return sum(self.add(b, img, spp) for b, img in zip(block_ids, images))

    @staticmethod
    def _divide(total: np.ndarray, weight: np.ndarray) -> np.ndarray:
        w = weight[..., None].astype(np.float64)
        return np.divide(total, w, out=np.zeros_like(total), where=w > 0)

    def mean(self, block_id: int) -> np.ndarray:
        """Cumulative mean of all finite samples of the block, float64 [bh, bw, C]."""
        b = self._check_id(block_id)
        return self._divide(self._sum[:, b].sum(axis=0), self._weight[:, b].sum(axis=0))

    def half_buffer(self, block_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(A, B): cumulative means of the even-numbered and the odd-numbered passes."""
        b = self._check_id(block_id)
        return self._divide(self._sum[0, b], self._weight[0, b]), self._divide(self._sum[1, b], self._weight[1, b])

    def spp(self, block_id: int) -> int:
        """Samples per pixel spent on the block (dropped non-finite passes included)."""
        return int(self._spp[self._check_id(block_id)].sum())

    def half_spp(self, block_id: int) -> tuple[int, int]:
        """Samples per pixel spent in half buffers A and B."""
        a, b_ = self._spp[self._check_id(block_id)]
        return int(a), int(b_)

    def passes(self, block_id: int) -> int:
        return int(self._passes[self._check_id(block_id)])

    def nonfinite(self, block_id: int) -> int:
        """How many (pixel, pass) values of the block were non-finite and dropped."""
        return int(self._nonfinite[self._check_id(block_id)])

    def image(self) -> np.ndarray:
        """All cumulative block means assembled into the frame, float64 [H, W, C]."""
        (gh, gw), (bh, bw) = self.grid, self.block
        out = np.zeros((gh * bh, gw * bw, self.channels), dtype=np.float64)
        for b in range(self.n_blocks):
            r, c = divmod(b, gw)
            out[r * bh:(r + 1) * bh, c * bw:(c + 1) * bw] = self.mean(b)
        return out

    # -- checkpointing -------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (e.g. for ``np.savez``)."""
        return {
            "version": np.array(self.STATE_VERSION, dtype=np.int64),
            "grid": np.array(self.grid, dtype=np.int64),
            "block": np.array(self.block, dtype=np.int64),
            "sum": self._sum.copy(),
            "weight": self._weight.copy(),
            "spp": self._spp.copy(),
            "passes": self._passes.copy(),
            "nonfinite": self._nonfinite.copy(),
        }

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> BlockAccumulator:
        """Rebuild an accumulator from `state()`; ValueError if anything does not fit."""
        need = ("version", "grid", "block", "sum", "weight", "spp", "passes", "nonfinite")
        missing = [k for k in need if k not in state]
        if missing:
            raise ValueError(f"accumulator state lacks {', '.join(missing)}")
        version = int(np.asarray(state["version"]))
        if version != cls.STATE_VERSION:
            raise ValueError(f"accumulator state version {version}, this code reads {cls.STATE_VERSION}")
        grid = tuple(int(v) for v in np.asarray(state["grid"]).ravel())
        block = tuple(int(v) for v in np.asarray(state["block"]).ravel())
        if len(grid) != 2 or len(block) != 2:
            raise ValueError(f"accumulator state: bad grid {grid} or block {block}")
        channels = int(np.asarray(state["sum"]).shape[-1]) if np.asarray(state["sum"]).ndim == 5 else 0
        acc = cls(grid, block, max(channels, 1))  # type: ignore[arg-type]
        for key, arr in (("sum", acc._sum), ("weight", acc._weight), ("spp", acc._spp),
                         ("passes", acc._passes), ("nonfinite", acc._nonfinite)):
            got = np.asarray(state[key])
            if got.shape != arr.shape:
                raise ValueError(f"accumulator state: {key!r} has shape {got.shape}, expected {arr.shape}")
            arr[...] = got
        return acc
