"""Block rendering: samples for any subset of a frame's units, each the full-frame estimator cut down.

The wavefront engine (llvm, cuda: `WavefrontTracer`) traces all requested units in one launch; the
crop engine (scalar variants) renders each unit's crop window grown by the filter's guard band: the
same estimator in distribution, not the same random numbers (Mitsuba seeds lanes by position).
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
from .wavefront import Traced, WavefrontTracer, filter_guard, filter_nonnegative

logger = logging.getLogger(__name__)

#: the unit id keying the seeds of passes traced over the whole frame: full frames, quick images and every
#: wavefront pass (a cut of the frame's)
FRAME_SEED_KEY = -1


def derive_seed(seed: int, unit: int, pass_index: int) -> int:
    """Deterministic 32-bit Mitsuba seed for (base seed, unit, pass index): hashed, so streams
    stay apart for consecutive base seeds and any pass is reproducible on its own (a resume)."""
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
    if c in (0, 2):
        raise ValueError(f"{where}: film has {c} channels; need 1 (luminance), 3 (rgb) or 4 (rgba)")
    return np.repeat(arr, 3, axis=2) if c == 1 else np.ascontiguousarray(arr[..., :3])


#: (unit, pass index) jobs of `render_passes`
Jobs = Sequence[tuple[int, int]] | np.ndarray
#: the integrators of the quick images the renderer can make (learning.inputs.table.QUICK_MODES adds 'none')
_QUICK_INTEGRATORS = {"albedo": {"type": "aov", "aovs": "albedo:albedo"}, "direct": {"type": "direct"}}
QUICK_KINDS = tuple(_QUICK_INTEGRATORS)


class BlockRenderer(BlockWindows):
    """Render any subset of the units of a scene's sensor (by default its first), the film's crop window as the
    frame, cut as `cut` says (`BlockWindows`' grid, block and tile). `engine`: 'wavefront' or 'crop' (default:
    by variant). `integrator`: by default the scene's (the ``noisestop`` plugin's nested one)."""

    def __init__(self, scene: Any, *, engine: str | None = None, sensor: Any = None, integrator: Any = None,
                 **cut: Any) -> None:
        variant = select_variant()
        mi = self._mi = require("mitsuba")
        self.scene = scene
        self.sensor = scene.sensors()[0] if sensor is None else sensor
        film = self.sensor.film()
        self._frame_offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        super().__init__(int(film.crop_size()[0]), int(film.crop_size()[1]), **cut)
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
        jit = variant.split("_")[0] in ("llvm", "cuda")
        self.engine = ("wavefront" if jit else "crop") if engine is None else engine
        if self.engine not in ("wavefront", "crop"):
            raise ValueError(f"engine must be 'wavefront' or 'crop', got {engine!r}")
        # where passes live: the variant's device for the wavefront engine (the crop engine's are host images)
        self.device = torch.device("cuda" if self.engine == "wavefront" and variant.startswith("cuda") else "cpu")
        self._ledger = Ledger()
        self._tracer = WavefrontTracer(scene, self.sensor, self._integrator, self.device, self._ledger) \
            if self.engine == "wavefront" else None
        self._unit_idx = self._unit_idx.to(self.device)       # the units' pixels, where passes live
        self._counts_kernels = jit                            # Dr.Jit's kernel history counts compilations
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
        """Put the process-wide kernel-history flag back (left on, Dr.Jit keeps a record of every
        launch for whoever renders next in the process)."""
        if self._history_flag_before is not None:
            dr = require("drjit")
            self.count_kernels()
            dr.set_flag(dr.JitFlag.KernelHistory, self._history_flag_before)
            self._history_flag_before = None

    def __enter__(self) -> BlockRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _set_crop(self, x: int, y: int, w: int, h: int) -> None:
        """Point the film's crop window at frame-relative (x, y, w, h), if it moved."""
        crop = (x, y, w, h)
        if crop == self._crop:
            return
        ox, oy = self._frame_offset
        self._params["film.crop_offset"] = self._mi.ScalarPoint2u(ox + x, oy + y)
        self._params["film.crop_size"] = self._mi.ScalarVector2u(w, h)
        self._params.update()
        self._crop = crop

    @property
    def ledger(self) -> Ledger:
        """Where this renderer's costs go (its tracer's too); a session sets the render's."""
        return self._ledger

    @ledger.setter
    def ledger(self, ledger: Ledger) -> None:
        self._ledger = ledger
        if self._tracer is not None:
            self._tracer.ledger = ledger

    def count_kernels(self) -> None:
        """Add the compilations in Dr.Jit's kernel history since the last count to the ledger, emptying it:
        read after every launch's images are in (reading waits for queued kernels), as the history keeps
        every kernel run until read (read at checkpoints only, 1.8 GB after 2,500 passes)."""
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
        """`spp` new samples for each listed unit: float32 [len(units), th, tw, 3] on `device`;
        (seed, pass_index) always draws the same samples for a pixel."""
        ids = np.asarray(units).reshape(-1)        # its dtype checked with the jobs'
        return self.render_passes(np.stack([ids, np.full_like(ids, int(pass_index))], axis=1), spp, seed)

    def _check_jobs(self, jobs: Jobs, spp: int | Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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

    def render_passes(self, jobs: Jobs, spp: int | Sequence[int], seed: int) -> torch.Tensor:
        """One pass per (unit, pass index) job in as few launches as the engine allows: float32
        [len(jobs), th, tw, 3] on `device`. Job (u, p) is exactly ``render_units([u], spp, seed,
        pass_index=p)``. `spp`: one for all, or per job (jobs of one size share a launch)."""
        return self.submit_passes(jobs, spp, seed).result()

    def submit_passes(self, jobs: Jobs, spp: int | Sequence[int], seed: int) -> Traced[torch.Tensor]:
        """`render_passes` without waiting for the wavefront engine's launches (the crop engine
        renders at once): `result()` gives its tensor."""
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
            jobs_p = []                                    # (mask, key) job, its rows, their pixels
            for p in np.unique(pass_ids[same]).tolist():   # the distinct pass indices: one in a plain pass
                rows = np.flatnonzero(same & (pass_ids == p))
                idx = self._unit_idx[torch.from_numpy(units[rows]).to(self.device)]
                mask = torch.zeros(self.height * self.width, dtype=torch.bool, device=self.device)
                mask[idx.flatten()] = True
                jobs_p.append(((mask.view(self.height, self.width), derive_seed(seed, FRAME_SEED_KEY, p)), rows, idx))
            launched.append((self._tracer.submit_jobs([job for job, _, _ in jobs_p], int(size)), jobs_p))
            self._ledger.count("mitsuba_calls")

        def gather() -> torch.Tensor:
            for traced, jobs_p in launched:
                for frame, (_, rows, idx) in zip(traced.result(), jobs_p):
                    out[torch.from_numpy(rows).to(self.device)] = frame.view(-1, 3)[idx].view(-1, *out.shape[1:])
            self.count_kernels()      # its kernels are done: read their records now, so they do not pile up
            return out
        return Traced(gather)

    def _render_crop(self, u: int, spp: int, seed: int, pass_index: int) -> np.ndarray:
        """The crop engine: unit `u` as one mi.render of its window grown by the guard band (the
        caller puts the crop back)."""
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
        """The design's noise-free-ish 'quick' image, full frame: kind 'albedo' (the default, no light transport) or
        'direct' (direct lighting: shading and shadows, some noise under area lights; the quick-image ablation)."""
        if kind not in QUICK_KINDS:
            raise ValueError(f"quick image kind must be one of {QUICK_KINDS}, got {kind!r}")
        self._set_crop(0, 0, self.width, self.height)
        return self._render(spp, derive_seed(seed, FRAME_SEED_KEY, -1),
                            integrator=self._mi.load_dict(_QUICK_INTEGRATORS[kind]), where=f"{kind} quick image")

