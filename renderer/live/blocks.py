"""Block rendering: samples for any subset of a frame's units, the full-frame estimator.

The paper cuts every image into blocks and keeps sampling only the blocks a human would
still find noisy, so the renderer must spend samples on any subset of the loop's units
(the blocks' tiles, or the blocks themselves at block grain: `renderer.live.passloop` has the
words), and a unit rendered alone must be the very estimator of that unit cut out of a
full-frame render.

Geometry. Blocks are a grid that divides the frame or windows of a given size in pixels,
the last row and column flush with the frame's edge, and each is cut into tiles
(`renderer.live.block_windows`, which also composes the final image from overlapping windows).

Engines. On vectorised variants (llvm, cuda) `renderer.live.wavefront.WavefrontTracer` traces
the pixels of all requested units in one kernel launch (its docstring says why a subset is
the full frame's estimator). On scalar variants each unit is one ``mi.render`` of the
film's crop window grown by the filter's guard band and cut back: the same estimator in
distribution (Mitsuba seeds lanes by position, so not the same random numbers). What a
render costs goes to the renderer's `ledger` (`renderer.live.ledger`), read there.

`learning.data.accumulator.UnitAccumulator` keeps the float64 running sums so cumulative means
are exact, plus two half buffers (even and odd passes) for the half-buffer criteria.
"""

from __future__ import annotations

import hashlib
import logging
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from learning.data.variant import select_variant
from noisefeat.extras import require

from ..plugin_schema import noisestop_of
from .block_windows import BlockWindows
from .ledger import Ledger
from .wavefront import Traced, WavefrontTracer, filter_guard, filter_nonnegative, torch_device

logger = logging.getLogger(__name__)

#: the unit id that keys the seeds of passes traced over the whole frame: full-frame renders,
#: quick images and every wavefront pass (keyed per pixel, a pass of some units is the
#: frame's pass cut down); -1, no unit's id
FRAME_SEED_KEY = -1


def derive_seed(seed: int, unit: int, pass_index: int) -> int:
    """Deterministic 32-bit Mitsuba seed for (base seed, unit, pass index).

    Hashing (rather than e.g. ``seed + unit``) keeps the streams of different
    units and passes apart even when callers pick consecutive base seeds, and makes any
    pass reproducible on its own, which is what resuming an interrupted build needs.
    """
    data = struct.pack("<qqq", int(seed), int(unit), int(pass_index))
    return int.from_bytes(hashlib.blake2b(data, digest_size=4).digest(), "little")


def _to_rgb(img: Any, where: str) -> np.ndarray:
    """Mitsuba's developed film as float32 [h, w, 3] (drops alpha, widens luminance)."""
    arr = np.asarray(img, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise ValueError(f"{where}: Mitsuba returned an image of shape {arr.shape}, expected [h, w, c]")
    c = arr.shape[2]
    if c == 1:
        return np.repeat(arr, 3, axis=2)
    if c >= 3:
        return np.ascontiguousarray(arr[..., :3])
    raise ValueError(f"{where}: film has {c} channels; need 1 (luminance), 3 (rgb) or 4 (rgba)")


#: quick images the renderer can make (learning.inputs.table.QUICK_MODES adds 'none')
QUICK_KINDS = ("albedo", "direct")


class BlockRenderer(BlockWindows):
    """Render any subset of the blocks of one scene's first sensor.

    Blocks are numbered row-major, block 0 top-left: a `grid` (rows, columns) that must
    divide the frame, or windows of `block` pixels (`BlockWindows`). If the film has a
    crop window (possible in XML files), that window is the frame. Each block is cut into
    tiles of `tile` pixels (one tile: the block): the units it renders. `engine`
    'wavefront' or 'crop' overrides the choice by variant (tests). `sensor` and
    `integrator` default to the scene's first sensor and its own integrator; a scene whose
    integrator is the ``noisestop`` plugin is traced with the plugin's nested integrator.
    What it costs goes to `ledger` (one of its own until a session hands it the render's).
    """

    def __init__(self, scene: Any, grid: tuple[int, int] | None = None, block: int | None = None,
                 engine: str | None = None, sensor: Any = None, integrator: Any = None,
                 tile: int | None = None) -> None:
        variant = select_variant()
        mi = require("mitsuba")

        self._mi = mi
        self.scene = scene
        self.sensor = scene.sensors()[0] if sensor is None else sensor
        film = self.sensor.film()
        self._frame_offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        super().__init__(int(film.crop_size()[0]), int(film.crop_size()[1]), grid, block, tile)
        # an XML scene may declare no integrator (mi.render then refuses): Mitsuba's path tracer
        self._integrator = scene.integrator() if integrator is None else integrator
        plugin = noisestop_of(self._integrator)
        if plugin is not None:              # the noisestop plugin: its nested one (a bad property: one line)
            plugin.check()
            self._integrator = plugin.nested
        if self._integrator is None:
            logger.info("scene declares no integrator; using Mitsuba's 'path'")
            self._integrator = mi.load_dict({"type": "path"})
        self.guard = filter_guard(film.rfilter())           # the crop engine's; the tracer has its own
        #: whether the film's filter has no negative lobe (then every pixel's radiance is >= 0)
        self.nonnegative = filter_nonnegative(film.rfilter())
        if engine is None:
            engine = "wavefront" if variant.split("_")[0] in ("llvm", "cuda") else "crop"
        if engine not in ("wavefront", "crop"):
            raise ValueError(f"engine must be 'wavefront' or 'crop', got {engine!r}")
        self.engine = engine
        # where passes live: the variant's device for the wavefront engine; the crop engine's
        # mi.render calls return host images (scalar variants)
        self.device = torch_device(variant) if engine == "wavefront" else torch.device("cpu")
        self._ledger = Ledger()
        self._tracer = WavefrontTracer(scene, self.sensor, self._integrator, self.device, self._ledger) \
            if engine == "wavefront" else None
        self._unit_idx = self._unit_idx.to(self.device)       # the units' pixels, where passes live
        # a JIT variant: Dr.Jit's kernel history can count its compilations (kernel_compiles)
        self._counts_kernels = variant.split("_")[0] in ("llvm", "cuda")
        self._history_flag_before: bool | None = None
        if self._counts_kernels:
            dr = require("drjit")
            self._history_flag_before = bool(dr.flag(dr.JitFlag.KernelHistory))
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()                               # start counting from here
        self._params = mi.traverse(self.sensor)
        self._crop: tuple[int, int, int, int] | None = None
        self._set_crop(0, 0, self.width, self.height)

    def close(self) -> None:
        """Put the process-wide kernel-history flag back as it was before this renderer
        (it is on only to count compilations; left on, Dr.Jit keeps a record of every
        launch for whoever renders next in the process)."""
        if self._counts_kernels and self._history_flag_before is not None:
            dr = require("drjit")
            self.count_kernels()
            dr.set_flag(dr.JitFlag.KernelHistory, self._history_flag_before)
            self._history_flag_before = None

    def __enter__(self) -> BlockRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- rendering --------------------------------------------------------------

    def _set_crop(self, x: int, y: int, w: int, h: int) -> None:
        """Point the film's crop window at frame-relative (x, y, w, h), if it moved."""
        crop = (x, y, w, h)
        if crop == self._crop:
            return
        mi = self._mi
        ox, oy = self._frame_offset
        self._params["film.crop_offset"] = mi.ScalarPoint2u(ox + x, oy + y)
        self._params["film.crop_size"] = mi.ScalarVector2u(w, h)
        self._params.update()
        self._crop = crop

    @property
    def ledger(self) -> Ledger:
        """Where this renderer's costs go; a session sets the render's (`renderer.live.ledger`)."""
        return self._ledger

    @ledger.setter
    def ledger(self, ledger: Ledger) -> None:
        self._ledger = ledger
        if self._tracer is not None:
            self._tracer.ledger = ledger

    def count_kernels(self) -> None:
        """Add the compilations in Dr.Jit's kernel history since the last count to the
        ledger, emptying it. Reading the history waits for every queued kernel, so a launch
        reads it once its own images are in (`submit_passes`), before the loop queues the
        next: nothing else is queued then, and a queued launch still traces while the loop
        judges the last. Why every launch: the history keeps a record of every kernel run
        until it is read (hundreds of kB a pass), so read only at checkpoints a render's
        memory grew with its passes (1.8 GB after 2,500)."""
        if self._counts_kernels:
            dr = require("drjit")
            self._ledger.count("kernel_compiles", sum(1 for k in dr.kernel_history()
                                                      if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit")))

    @property
    def kernel_compiles(self) -> int:
        """Kernels compiled (not found in Dr.Jit's cache), in the ledger."""
        self.count_kernels()
        return self._ledger.get("kernel_compiles")

    def _render(self, spp: int, mitsuba_seed: int, integrator: Any = None, where: str = "render") -> np.ndarray:
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        img = self._mi.render(self.scene, sensor=self.sensor,
                              integrator=self._integrator if integrator is None else integrator,
                              spp=int(spp), seed=int(mitsuba_seed))
        self._ledger.count("mitsuba_calls")
        if self._tracer is None:                  # the crop engine's launches are its Mitsuba calls
            self._ledger.count("kernel_launches")
        self.count_kernels()
        return _to_rgb(img, where)

    def render_units(self, units: Sequence[int], spp: int, seed: int, pass_index: int = 0) -> torch.Tensor:
        """`spp` new samples for each listed unit: float32 [len(units), th, tw, 3] on `device`.

        Pass (seed, pass_index) always draws the same samples for a pixel: call again
        with a new `pass_index` (or `seed`) for an independent pass of the same units.
        """
        ids = np.asarray(units).reshape(-1)        # its dtype checked with the jobs'
        return self.render_passes(np.stack([ids, np.full_like(ids, int(pass_index))], axis=1), spp, seed)

    def _check_jobs(self, jobs: Sequence[tuple[int, int]] | np.ndarray, spp: int | Sequence[int]) -> tuple[np.ndarray, np.ndarray,
                                                                                               np.ndarray]:
        """(units, pass indices, sizes) as int64 arrays; one-line errors for bad jobs."""
        arr = np.asarray(jobs)
        if arr.size and (arr.dtype == bool or not np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"block ids and pass indices must be whole numbers, got {jobs!r:.80}")
        arr = arr.astype(np.int64).reshape(-1, 2)
        units, pass_ids = arr[:, 0], arr[:, 1]
        if units.size and (units.min() < 0 or units.max() >= self.n_units):
            unit = "block" if self.tiles_per_block == 1 else "tile"
            raise ValueError(f"{unit} id {int(units[(units < 0) | (units >= self.n_units)][0])!r} out of range "
                             f"0..{self.n_units - 1}")
        if len(np.unique(arr, axis=0)) != len(arr):
            raise ValueError(f"duplicate block ids or (block, pass) jobs in {arr.tolist()[:8]}: one call renders "
                             "each once")
        given = np.asarray(spp)
        if isinstance(spp, bool) or given.dtype == bool or not np.issubdtype(given.dtype, np.integer):
            raise ValueError(f"spp must be a positive integer, got {spp!r:.80}")
        sizes = np.broadcast_to(given, units.shape).astype(np.int64) if given.ndim == 0 else given.astype(np.int64)
        if sizes.shape != units.shape:
            raise ValueError(f"{len(units)} jobs but {sizes.size} pass sizes")
        if sizes.size and sizes.min() < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r:.80}")
        return units, pass_ids, sizes

    def render_passes(self, jobs: Sequence[tuple[int, int]] | np.ndarray, spp: int | Sequence[int], seed: int) -> torch.Tensor:
        """One pass per (unit, pass index) job, all in as few launches as the engine allows:
        float32 [len(jobs), th, tw, 3] on `device`: `submit_passes`, waited for. A unit is a
        block, or one of its tiles when the renderer cuts blocks into tiles (`tile`).

        Job (u, p) is exactly ``render_units([u], spp, seed, pass_index=p)``: units at
        different pass counts (a budget render spends passes unevenly), or several passes
        of the same unit, share one wavefront. `spp`: one size for all, or per job (jobs
        of the same size share a launch). The wavefront engine gathers every unit of a
        pass from the traced frame on the device in one indexing operation.
        """
        return self.submit_passes(jobs, spp, seed).result()

    def submit_passes(self, jobs: Sequence[tuple[int, int]] | np.ndarray, spp: int | Sequence[int],
                      seed: int) -> Traced[torch.Tensor]:
        """`render_passes` without waiting for the wavefront engine's launches (what the
        live loop calls: `renderer.live.session.RenderSession.advance`): `result()` gives the
        tensor `render_passes` returns (`WavefrontTracer.submit_jobs`; the crop engine
        renders at once)."""
        units, pass_ids, sizes = self._check_jobs(jobs, spp)
        out = torch.empty((len(units), self.tile_h, self.tile_w, 3), dtype=torch.float32, device=self.device)
        if not len(units):
            return Traced(lambda: out)
        if self._tracer is None:                  # scalar variants: one mi.render per unit
            try:
                for i, (u, p, s) in enumerate(zip(units.tolist(), pass_ids.tolist(), sizes.tolist())):
                    out[i] = torch.from_numpy(self._render_crop(u, s, seed, p))
            finally:
                self._set_crop(0, 0, self.width, self.height)  # leave the scene as we found it
            return Traced(lambda: out)
        launched = []
        for size in np.unique(sizes).tolist():
            same = sizes == size
            masks = []
            for p in np.unique(pass_ids[same]).tolist():   # the distinct pass indices: one in a plain pass
                rows = np.flatnonzero(same & (pass_ids == p))
                mask = torch.zeros(self.height * self.width, dtype=torch.bool, device=self.device)
                mask[self._unit_idx[torch.from_numpy(units[rows]).to(self.device)].flatten()] = True
                masks.append((mask.view(self.height, self.width), derive_seed(seed, FRAME_SEED_KEY, p), rows))
            launched.append((self._tracer.submit_jobs([(m, k) for m, k, _ in masks], int(size)), masks))
            self._ledger.count("mitsuba_calls")

        def gather() -> torch.Tensor:
            for traced, masks in launched:
                for frame, (_, _, rows) in zip(traced.result(), masks):
                    idx = self._unit_idx[torch.from_numpy(units[rows]).to(self.device)]
                    out[torch.from_numpy(rows).to(self.device)] = frame.view(-1, 3)[idx].view(
                        len(rows), self.tile_h, self.tile_w, 3)
            self.count_kernels()      # its kernels are done: read their records now, so they do not pile up
            return out
        return Traced(gather)

    def _render_crop(self, u: int, spp: int, seed: int, pass_index: int) -> np.ndarray:
        """The crop engine: unit `u` (a block, or a tile) as one mi.render of its window grown
        by the guard band (the caller puts the crop back)."""
        g = self.guard
        x0, y0, w, h = self.unit_window(u)
        gx, gy = min(g, x0), min(g, y0)          # the guard band, clipped to the frame
        x1, y1 = min(self.width, x0 + w + g), min(self.height, y0 + h + g)
        self._set_crop(x0 - gx, y0 - gy, x1 - x0 + gx, y1 - y0 + gy)
        img = self._render(spp, derive_seed(seed, u, pass_index), where=f"unit {u}")
        traced = int(spp) * img.shape[0] * img.shape[1]
        self._ledger.count("kernel_lanes", traced)
        self._ledger.count("samples_traced", traced)
        return img[gy:gy + h, gx:gx + w]

    def render_full(self, spp: int, seed: int, pass_index: int = 0) -> np.ndarray:
        """`spp` samples for the whole frame: float32 [H, W, 3] (host)."""
        if self._tracer is not None:
            image = self._tracer.trace(torch.ones((self.height, self.width), dtype=torch.bool), spp,
                                       derive_seed(seed, FRAME_SEED_KEY, pass_index))
            self._ledger.count("mitsuba_calls")
            self.count_kernels()
            return image.cpu().numpy()
        self._set_crop(0, 0, self.width, self.height)
        return self._render(spp, derive_seed(seed, FRAME_SEED_KEY, pass_index), where="full frame")

    def quick_image(self, spp: int = 16, seed: int = 0, kind: str = "albedo") -> np.ndarray:
        """The noise-free-ish 'quick' image of the design, full frame.

        kind 'albedo' (the design's default): the albedo AOV, no light transport at all;
        'direct': direct lighting only (Mitsuba's `direct` integrator), which carries the
        shading and shadows but still some noise under area lights (quick-image ablation).
        """
        self._set_crop(0, 0, self.width, self.height)
        if kind == "albedo":
            integrator = self._mi.load_dict({"type": "aov", "aovs": "albedo:albedo"})
        elif kind == "direct":
            integrator = self._mi.load_dict({"type": "direct"})
        else:
            raise ValueError(f"quick image kind must be one of {QUICK_KINDS}, got {kind!r}")
        return self._render(spp, derive_seed(seed, FRAME_SEED_KEY, -1), integrator=integrator,
                            where=f"{kind} quick image")

