"""Exact cumulative per-unit means and the even/odd half buffers of a progressive render.

A *unit* is what the loop samples, judges and stops: a live render's tiles (a whole block
at block grain), a stored stack's blocks. Shared by the live loop (`renderer.live.passloop`,
fed rendered passes) and everything that replays a stored stack (`learning.inputs.halves`,
`renderer.simulation.simulate`, fed passes recovered from its levels): one arithmetic, so a
criterion sees bit-identical buffers either way.

The sums live in torch tensors on the renderer's device (`device`: the GPU with Mitsuba's
``cuda_ad_rgb``, else the CPU), so a live pass is added and judged where it was traced:
one batched update per pass, no copy of an image to the host. The per-unit counts
(samples, passes) are small host arrays: the loop and the budget read them every pass.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

logger = logging.getLogger(__name__)


class UnitAccumulator:
    """Exact cumulative per-unit means, sample counts and even/odd half buffers.

    `grid`: the units as (rows, columns), numbered row-major (a stack's block grid; the
    live loop's (blocks, tiles a block)); `unit_shape`: a unit's (height, width) in pixels.
    Each pass of a unit is an image that is the mean of `spp` new samples. Sums are
    kept in float64 as ``image * spp`` so ``mean = sum / spp`` whatever the pass sizes.
    Passes alternate between two half buffers per unit: its passes 0, 2, 4... go to A and
    1, 3, 5... to B (the Cycles-style criterion compares the mean of all samples with the
    mean of one half; with equal pass sizes ``mean = (A + B) / 2``).

    Non-finite values (Mitsuba can emit NaN/Inf): a pixel whose value in a pass is not
    finite in any channel is dropped *for that pixel and pass only*: it adds nothing to
    the pixel's sum nor to its sample weight, so the pixel's mean stays an average of
    finite passes instead of being dragged to 0 or poisoned. The unit's `spp` still
    counts the samples spent (it is a cost), and `nonfinite` counts the dropped
    (pixel, pass) pairs. A pixel with no finite pass has mean 0, which is no estimate:
    `unestimated` counts such pixels per unit (in either half buffer that holds a pass),
    and a criterion never calls a unit with one converged (`renderer.criteria.contract`).

    `state()` names the unit shape "block" and the pass counts "passes": the checkpoint's
    array names (acc_block, acc_passes), kept.
    """

    STATE_VERSION = 1

    def __init__(self, grid: tuple[int, int], unit_shape: tuple[int, int], channels: int = 3,
                 device: torch.device | str | None = None) -> None:
        gh, gw = (int(g) for g in grid)
        uh, uw = (int(b) for b in unit_shape)
        if min(gh, gw, uh, uw, int(channels)) < 1:
            raise ValueError(f"grid {grid!r}, unit shape {unit_shape!r} and channels {channels!r} must be positive")
        self.grid, self.unit_shape, self.channels = (gh, gw), (uh, uw), int(channels)
        self.device = torch.device("cpu" if device is None else device)
        n = gh * gw
        self._sum = torch.zeros((2, n, uh, uw, self.channels), dtype=torch.float64, device=self.device)
        self._weight = torch.zeros((2, n, uh, uw), dtype=torch.int64, device=self.device)
        self._nonfinite_t = torch.zeros(n, dtype=torch.int64, device=self.device)
        self._spp = np.zeros((n, 2), dtype=np.int64)
        self._pass_counts = np.zeros(n, dtype=np.int64)

    @property
    def n_units(self) -> int:
        return self.grid[0] * self.grid[1]

    def _check_id(self, unit: int) -> int:
        if not isinstance(unit, (int, np.integer)) or not 0 <= int(unit) < self.n_units:
            raise ValueError(f"unit id {unit!r} out of range 0..{self.n_units - 1}")
        return int(unit)

    def _check_ids(self, units: Sequence[int] | np.ndarray, once: bool = False) -> np.ndarray:
        """The ids as int64, in range; with `once` (a pass adds each unit once) no repeats.
        Reads may repeat an id: the duplicate test is a sort, paid only where it matters."""
        ids = np.asarray(units, dtype=np.int64).reshape(-1)
        if ids.size and (ids.min() < 0 or ids.max() >= self.n_units):
            raise ValueError(f"unit ids out of range 0..{self.n_units - 1}: {ids[(ids < 0) | (ids >= self.n_units)][:5].tolist()}")
        if once and len(np.unique(ids)) != ids.size:
            raise ValueError("duplicate unit ids: one pass adds each unit once")
        return ids

    def add(self, unit: int, image: Any, spp: int) -> int:
        """Add one pass of one unit (`image` = mean of `spp` samples); return its dropped
        pixel count."""
        u = self._check_id(unit)
        img = image if isinstance(image, torch.Tensor) else torch.from_numpy(np.asarray(image))
        if tuple(img.shape) != (*self.unit_shape, self.channels):
            raise ValueError(f"unit {u}: image shape {tuple(img.shape)} does not match "
                             f"{(*self.unit_shape, self.channels)}")
        return int(self.add_batch([u], img[None], spp).sum())

    def add_many(self, units: Sequence[int], images: Any, spp: int) -> int:
        """`add` for a batch as returned by `BlockRenderer.render_units`; returns the
        dropped (pixel, pass) count."""
        return int(self.add_batch(units, images, spp).sum())

    def add_batch(self, units: Sequence[int] | np.ndarray, images: Any,
                  spp: int | Sequence[int]) -> torch.Tensor:
        """One pass of each listed unit, in one batched update: `images` [k, uh, uw, C]
        (a tensor on any device or an array), `spp` one size for all or one per unit.
        Returns the dropped pixel count of each unit, int64 [k] on the device (reading it
        is a host sync: the live loop does not)."""
        ids = self._check_ids(units, once=True)
        sizes = np.broadcast_to(np.asarray(spp), ids.shape)
        if sizes.size and (not np.issubdtype(sizes.dtype, np.integer) or sizes.min() < 1):
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        img = images if isinstance(images, torch.Tensor) else torch.from_numpy(np.asarray(images))
        want = (len(ids), *self.unit_shape, self.channels)
        if tuple(img.shape) != want:
            raise ValueError(f"unit images of shape {tuple(img.shape)} do not match {want}")
        if not ids.size:
            return torch.zeros(0, dtype=torch.int64, device=self.device)
        img = img.to(device=self.device, dtype=torch.float64)
        half_np = self._pass_counts[ids] % 2
        ids_t = torch.from_numpy(ids).to(self.device)
        half = torch.from_numpy(half_np).to(self.device)
        n_t = torch.from_numpy(sizes.astype(np.int64)).to(self.device)
        ok = torch.isfinite(img).all(dim=-1)
        self._sum.index_put_((half, ids_t), torch.where(ok[..., None], img, 0.0) * n_t[:, None, None, None],
                             accumulate=True)
        self._weight.index_put_((half, ids_t), ok * n_t[:, None, None], accumulate=True)
        dropped = (~ok).sum(dim=(1, 2))
        self._nonfinite_t.index_add_(0, ids_t, dropped)
        np.add.at(self._spp, (ids, half_np), sizes)
        self._pass_counts[ids] += 1
        return dropped

    @staticmethod
    def _divide(total: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        w = weight[..., None].to(torch.float64)
        return torch.where(w > 0, total / torch.where(w > 0, w, 1.0), 0.0)

    def means(self, units: Sequence[int] | np.ndarray) -> torch.Tensor:
        """Cumulative means of all finite samples, float64 [k, uh, uw, C] on the device."""
        ids = torch.from_numpy(self._check_ids(units)).to(self.device)
        return self._divide(self._sum[:, ids].sum(dim=0), self._weight[:, ids].sum(dim=0))

    def halves(self, units: Sequence[int] | np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(A, B) [k, uh, uw, C] each on the device: means of the even and the odd passes."""
        ids = torch.from_numpy(self._check_ids(units)).to(self.device)
        return (self._divide(self._sum[0, ids], self._weight[0, ids]),
                self._divide(self._sum[1, ids], self._weight[1, ids]))

    def mean(self, unit: int) -> np.ndarray:
        """Cumulative mean of all finite samples of the unit, float64 [uh, uw, C]."""
        return self.means([self._check_id(unit)])[0].cpu().numpy()

    def half_buffer(self, unit: int) -> tuple[np.ndarray, np.ndarray]:
        """(A, B): cumulative means of the even-numbered and the odd-numbered passes."""
        a, b = self.halves([self._check_id(unit)])
        return a[0].cpu().numpy(), b[0].cpu().numpy()

    def spp(self, unit: int) -> int:
        """Samples per pixel spent on the unit (dropped non-finite passes included)."""
        return int(self._spp[self._check_id(unit)].sum())

    def spp_all(self) -> np.ndarray:
        """Samples per pixel spent on every unit, int64 [n_units] (host)."""
        return self._spp.sum(axis=1)

    def half_spp(self, unit: int) -> tuple[int, int]:
        """Samples per pixel spent in half buffers A and B."""
        a, b_ = self._spp[self._check_id(unit)]
        return int(a), int(b_)

    def half_spp_all(self) -> np.ndarray:
        """int64 [n_units, 2]: samples in half buffers A and B of every unit (host)."""
        return self._spp.copy()

    def pass_count(self, unit: int) -> int:
        """How many passes the unit holds (so the index of its next pass)."""
        return int(self._pass_counts[self._check_id(unit)])

    def pass_counts(self) -> np.ndarray:
        """int64 [n_units]: how many passes every unit holds (host)."""
        return self._pass_counts.copy()

    def nonfinite(self, unit: int) -> int:
        """How many (pixel, pass) values of the unit were non-finite and dropped."""
        return int(self._nonfinite_t[self._check_id(unit)])

    def nonfinite_all(self) -> np.ndarray:
        """int64 [n_units]: dropped (pixel, pass) values of every unit (one device read)."""
        return self._nonfinite_t.cpu().numpy()

    def unestimated(self, units: Sequence[int] | np.ndarray) -> np.ndarray:
        """int64 [k] (host): the pixels of each unit that have no finite value in a half
        buffer holding a pass (every value there was dropped): no estimate of the pixel, so
        neither a mean to judge nor halves to compare."""
        ids = self._check_ids(units)
        out = np.zeros(len(ids), np.int64)
        # only a unit that dropped values can hold such a pixel: the others cost no pass over their weights
        some = np.flatnonzero(self.nonfinite_all()[ids] > 0)
        if not some.size:
            return out
        ids = ids[some]
        held = torch.from_numpy(self._spp[ids].T > 0).to(self.device)          # [2, k]: half holds a pass
        empty = (self._weight[:, torch.from_numpy(ids).to(self.device)] == 0) & held[:, :, None, None]
        out[some] = empty.any(dim=0).flatten(1).sum(dim=1).cpu().numpy()
        return out

    def unsampled(self, units: Sequence[int] | np.ndarray) -> np.ndarray:
        """bool [k, uh, uw] (host): pixels of sampled units with no finite value at all:
        their mean is 0, not an estimate (what a finished render warns about)."""
        ids = self._check_ids(units)
        total = self._weight[:, torch.from_numpy(ids).to(self.device)].sum(dim=0).cpu().numpy()
        return (total == 0) & (self._spp[ids].sum(axis=1) > 0)[:, None, None]

    def image(self) -> np.ndarray:
        """All cumulative unit means assembled into the frame their grid tiles (a stack's
        blocks), float64 [H, W, C]."""
        (gh, gw), (bh, bw) = self.grid, self.unit_shape
        m = self.means(np.arange(self.n_units)).cpu().numpy()
        return m.reshape(gh, gw, bh, bw, self.channels).transpose(0, 2, 1, 3, 4).reshape(gh * bh, gw * bw,
                                                                                         self.channels)

    # -- checkpointing -------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (e.g. for ``np.savez``)."""
        return {
            "version": np.array(self.STATE_VERSION, dtype=np.int64),
            "grid": np.array(self.grid, dtype=np.int64),
            "block": np.array(self.unit_shape, dtype=np.int64),
            "sum": self._sum.cpu().numpy().copy(),
            "weight": self._weight.cpu().numpy().copy(),
            "spp": self._spp.copy(),
            "passes": self._pass_counts.copy(),
            "nonfinite": self.nonfinite_all().copy(),
        }

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray], device: torch.device | str | None = None) -> UnitAccumulator:
        """Rebuild an accumulator from `state()`; ValueError if anything does not fit."""
        need = ("version", "grid", "block", "sum", "weight", "spp", "passes", "nonfinite")
        missing = [k for k in need if k not in state]
        if missing:
            raise ValueError(f"accumulator state lacks {', '.join(missing)}")
        version = int(np.asarray(state["version"]))
        if version != cls.STATE_VERSION:
            raise ValueError(f"accumulator state version {version}, this code reads {cls.STATE_VERSION}")
        grid = tuple(int(v) for v in np.asarray(state["grid"]).ravel())
        shape = tuple(int(v) for v in np.asarray(state["block"]).ravel())
        if len(grid) != 2 or len(shape) != 2:
            raise ValueError(f"accumulator state: bad grid {grid} or block {shape}")
        channels = int(np.asarray(state["sum"]).shape[-1]) if np.asarray(state["sum"]).ndim == 5 else 0
        acc = cls(grid, shape, max(channels, 1), device=device)  # type: ignore[arg-type]
        for key, arr in (("sum", acc._sum), ("weight", acc._weight), ("spp", acc._spp),
                         ("passes", acc._pass_counts), ("nonfinite", acc._nonfinite_t)):
            got = np.asarray(state[key])
            if got.shape != tuple(arr.shape):
                raise ValueError(f"accumulator state: {key!r} has shape {got.shape}, expected {tuple(arr.shape)}")
            if isinstance(arr, torch.Tensor):
                arr.copy_(torch.from_numpy(got.astype(np.float64 if key == "sum" else np.int64)))
            else:
                arr[...] = got
        return acc

