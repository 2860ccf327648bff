"""One kernel launch per pass for any set of pixels (docs/how-it-works.md, "The loop").

`WavefrontTracer` does ``SamplingIntegrator.render``'s work for the requested pixels only (a crop window per
unit would compile a kernel per unit), every value that changes between passes opaque: one kernel per render.
Random numbers are keyed per (pixel, sample, pass) (`KeyedSampler`), so any set of units is a full-frame trace
cut down: bit for bit with a box filter, to float32 rounding with a wider one. Edge pixels get no samples from
outside the frame (no ``sample_border``).
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, Generic, TypeVar

import numpy as np
import torch

from noisefeat.extras import require

from .ledger import Ledger

T = TypeVar("T")

#: lanes per kernel launch: larger pixel sets are traced in chunks (same kernel)
MAX_LANES = 1 << 24


def filter_nonnegative(rfilter: Any) -> bool:
    """Whether a reconstruction filter is >= 0 over its radius (box, tent, gaussian; not
    mitchell, catmullrom), sampled at 64 points: a checkpoint's sums are then >= 0."""
    r = float(rfilter.radius())
    return all(float(np.asarray(rfilter.eval(r * i / 63)).min()) >= 0.0 for i in range(64))


def filter_guard(rfilter: Any) -> int:
    """The guard band a film's filter needs, for both engines (none for a box filter): the pixels around
    a requested one whose samples reach it, as a sample of pixel q lies in [q, q + 1] (inclusive: q + u
    rounds to q + 1 in float32 for u near 1) and reaches pixel p when |p + 1/2 - x| <= radius."""
    return 0 if rfilter.is_box_filter() else int(math.floor(float(rfilter.radius()) + 0.5))


@functools.cache
def _keyed_sampler_class() -> type:
    """`KeyedSampler` needs a variant: built on first use."""
    mi = require("mitsuba")

    class KeyedSampler(mi.Sampler):
        """One PCG32 stream per (pixel, sample, pass), given per lane (`set_streams`): Mitsuba's
        `independent` sampler seeds by lane, tying a pixel's samples to the other pixels traced."""

        DRJIT_STRUCT = {"rng": mi.PCG32}

        def __init__(self, props: Any = None) -> None:
            super().__init__(props if props is not None else mi.Properties())
            self.rng = mi.PCG32()

        def seed(self, seed: Any, wavefront_size: int = 0) -> None:
            """Streams come from `set_streams`; Mitsuba's own seeding is not used."""

        def set_streams(self, state: Any, sequence: Any) -> None:
            # seed() on a default generator: a constructor given the size would add arange(size)
            # (a lane's position) and compile a small kernel for every new wavefront size
            self.rng = mi.PCG32()
            self.rng.seed(state, sequence)

        def next_1d(self, active: Any = True) -> Any:
            return self.rng.next_float32(active)

        def next_2d(self, active: Any = True) -> Any:
            return mi.Point2f(self.next_1d(active), self.next_1d(active))

    return KeyedSampler


class WavefrontTracer:
    """Trace `spp` samples for any set of a frame's pixels (row-major in the film's crop window) on a JIT
    variant: masks in and frames out as torch tensors on `device`, shared with Dr.Jit through DLPack.
    `ledger` counts its launches, lanes and samples traced (guard band included)."""

    def __init__(self, scene: Any, sensor: Any, integrator: Any, device: torch.device | None = None,
                 ledger: Ledger | None = None) -> None:
        self._dr, self._mi = require("drjit"), require("mitsuba")
        self.scene, self.sensor, self.integrator = scene, sensor, integrator
        self.device = torch.device("cpu") if device is None else device
        film = sensor.film()
        self.width, self.height = int(film.crop_size()[0]), int(film.crop_size()[1])
        self.rfilter = film.rfilter()
        self.box = bool(self.rfilter.is_box_filter())
        self.guard = filter_guard(self.rfilter)
        self._sampler = _keyed_sampler_class()()
        self.ledger = Ledger() if ledger is None else ledger

    def _mask(self, mask: Any) -> torch.Tensor:
        m = torch.as_tensor(np.asarray(mask, bool) if not isinstance(mask, torch.Tensor) else mask)
        if tuple(m.shape) != (self.height, self.width):
            raise ValueError(f"pixel mask {tuple(m.shape)} does not match the frame {(self.height, self.width)}")
        return m.to(device=self.device, dtype=torch.bool)

    def traced_pixels(self, mask: Any) -> torch.Tensor:
        """The requested pixel mask [H, W] grown by the guard band (clipped to the frame)."""
        m = self._mask(mask)
        g = self.guard
        if g == 0 or bool(m.all()):
            return m
        grown = torch.nn.functional.max_pool2d(m[None, None].to(torch.float32), 2 * g + 1, stride=1, padding=g)
        return grown[0, 0] > 0

    def trace(self, mask: Any, spp: int, key: int) -> torch.Tensor:
        """Pixel estimates float32 [H, W, 3] for the pixels of `mask` (others 0); the same
        (pixel, spp, key) always gives the same value, whatever else is in `mask`."""
        return self.trace_jobs([(mask, key)], spp)[0]

    def trace_jobs(self, jobs: Sequence[tuple[Any, int]], spp: int) -> list[torch.Tensor]:
        """float32 [H, W, 3] per (pixel mask, key) job, in one launch (its fixed 10 ms paid
        once): each what `trace` returns, bit for bit with a box filter, to float32 rounding
        with a wider one (each job splats into its own ImageBlock)."""
        return self.submit_jobs(jobs, spp).result()

    def submit_jobs(self, jobs: Sequence[tuple[Any, int]], spp: int) -> Traced[list[torch.Tensor]]:
        """`trace_jobs` without waiting: the launches are queued on Dr.Jit's device (its LLVM
        thread pool or CUDA stream); `result()` waits and returns what `trace_jobs` would."""
        if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        spp = int(spp)
        masks = [self._mask(m) for m, _ in jobs]
        # int32 of the keys' low 32 bits: Dr.Jit's UInt32 takes them bit for bit, int32 crosses DLPack everywhere
        keys = [(int(k) + 2**31) % 2**32 - 2**31 for _, k in jobs]
        frame = (self.height, self.width, 3)
        grown = masks if self.box else [self.traced_pixels(m) for m in masks]
        pixels = [torch.nonzero(m.flatten()).flatten() for m in grown]
        counts = [int(p.numel()) for p in pixels]
        total = sum(counts)
        if total == 0:
            return Traced(lambda: [torch.zeros(frame, dtype=torch.float32, device=self.device) for _ in masks])
        flat = torch.cat(pixels)             # every job's pixels, one job after the other
        all_pixels = flat.to(torch.int32)
        job_of = torch.repeat_interleave(torch.arange(len(masks)), torch.tensor(counts)).to(self.device)
        all_keys = torch.tensor(keys, dtype=torch.int32, device=self.device)[job_of]
        self.ledger.count("samples_traced", total * spp)
        per_launch = max(1, MAX_LANES // spp)
        if self.box:
            chunks = [self._submit_box(all_pixels[i:i + per_launch], spp, all_keys[i:i + per_launch])
                      for i in range(0, total, per_launch)]

            def box_result() -> list[torch.Tensor]:
                outs = torch.zeros((len(masks), self.height * self.width, 3), dtype=torch.float32, device=self.device)
                outs[job_of, flat] = torch.cat([finish() for finish in chunks])
                return list(outs.view(len(masks), *frame))
            return Traced(box_result)
        # a wide filter: every job splats into its own frame; a launch's lanes hold its jobs'
        # pixels one job after the other, so each job's splat reads only its own lanes
        mi = self._mi
        films = [mi.ImageBlock(mi.ScalarVector2u(self.width, self.height), mi.ScalarPoint2i(0, 0), 4, self.rfilter,
                               border=False) for _ in masks]
        ends = np.cumsum([0, *counts])
        for i in range(0, total, per_launch):
            j = min(total, i + per_launch)
            spans = [(b, max(lo, i) - i, min(hi, j) - i) for b, lo, hi in zip(films, ends[:-1], ends[1:])
                     if min(hi, j) > max(lo, i)]
            self._submit_splat(all_pixels[i:j], spp, all_keys[i:j], spans)
        tensors = [f.tensor() for f in films]      # a job's frame: its ImageBlock

        def splat_result() -> list[torch.Tensor]:
            self._sync()
            sums = torch.stack([t.torch().reshape(-1, 4) for t in tensors])
            w = sums[..., 3:]
            # float32 division of float32 sums: the correctly rounded quotient, as float64's rounded
            value = torch.where(w > 0, sums[..., :3] / torch.where(w > 0, w, 1.0), 0.0)
            return list(torch.where(torch.stack(masks).reshape(len(masks), -1, 1), value, 0.0).view(len(masks), *frame))
        return Traced(splat_result)

    # -- one launch ---------------------------------------------------------------

    def _samples(self, pixels: torch.Tensor, spp: int, keys: torch.Tensor) -> tuple[Any, Any]:
        """(film position, radiance) of every sample of `pixels` with their pass `keys` (int32
        read as UInt32): lanes pixel-major; sample j of pixel p, key k seeds by TEA(p, k), TEA(j, .)."""
        mi, dr = self._mi, self._dr
        lane = dr.arange(mi.UInt32, int(pixels.numel()) * spp)
        spp_o = dr.opaque(mi.UInt32, spp)
        which = lane // spp_o
        j = lane - which * spp_o
        pix = dr.gather(mi.UInt32, mi.UInt32(pixels.contiguous()), which)
        key = dr.gather(mi.UInt32, mi.UInt32(keys.contiguous()), which)
        s0, s1 = mi.sample_tea_32(pix, key)
        t0, t1 = mi.sample_tea_32(j, s0)
        sampler = self._sampler
        sampler.set_streams(mi.UInt64(s1) | (mi.UInt64(t0) << 32), mi.UInt64(t1))
        w = dr.opaque(mi.UInt32, self.width)
        py = pix // w
        pos = mi.Vector2f(mi.Float(pix - py * w), mi.Float(py)) + sampler.next_2d()
        # as SamplingIntegrator::render_sample: film position relative to the crop window
        adjusted = pos / mi.ScalarVector2f(self.width, self.height)
        sensor = self.sensor
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        time = sensor.shutter_open()
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        ray, weight = sensor.sample_ray_differential(time, 0.0, adjusted, aperture)
        if ray.has_differentials:
            ray.scale_differential(dr.rsqrt(mi.Float(spp_o)))
        radiance, _, _ = self.integrator.sample(self.scene, sampler, ray, sensor.get_medium(), True)
        return pos, mi.Color3f(weight * radiance)

    def _sync(self) -> None:
        """Dr.Jit and torch queue GPU work on their own streams: wait for both before handing arrays across."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self._dr.sync_thread()

    def _queued(self, pixels: torch.Tensor, spp: int) -> None:
        self.ledger.count("kernel_launches")
        self.ledger.count("kernel_lanes", int(pixels.numel()) * spp)

    def _submit_box(self, pixels: torch.Tensor, spp: int, keys: torch.Tensor) -> Callable[[], torch.Tensor]:
        """Box filter: queue one launch; its finish gives each pixel's mean of its own samples, float32 [n, 3]:
        `dr.block_sum` of its consecutive lanes, in lane order, once they are evaluated (summed from the path
        tracer's expression, each channel would trace the paths again)."""
        dr = self._dr
        self._sync()
        _, rgb = self._samples(pixels, spp, keys)
        dr.eval(rgb)
        sums = [dr.block_sum(rgb[c], spp) for c in range(3)]
        dr.eval(*sums)
        self._queued(pixels, spp)

        def finish() -> torch.Tensor:
            self._sync()
            # channel by channel through DLPack: a Color3f converted at once would compile a
            # copy kernel per wavefront size
            return torch.stack([s.torch() for s in sums], dim=1) / np.float32(spp)
        return finish

    def _submit_splat(self, pixels: torch.Tensor, spp: int, keys: torch.Tensor,
                      spans: Sequence[tuple[Any, int, int]]) -> None:
        """Any filter: queue one launch of `pixels`' samples and splat each span (block, first,
        end: positions in `pixels`) into its block. One span fuses the splat into the kernel;
        several evaluate the samples once, then splat each over its own lanes (masked splats
        over every lane would cost a footprint per lane per job), start and size opaque."""
        mi, dr = self._mi, self._dr
        self._sync()
        pos, rgb = self._samples(pixels, spp, keys)
        if len(spans) == 1 and spans[0][1] == 0 and spans[0][2] == int(pixels.numel()):
            spans[0][0].put(pos, [rgb[0], rgb[1], rgb[2], mi.Float(1.0)])
        else:
            dr.eval(pos, rgb)
            for block, lo, hi in spans:
                lane = dr.arange(mi.UInt32, (hi - lo) * spp) + dr.opaque(mi.UInt32, lo * spp)
                p = mi.Vector2f(dr.gather(mi.Float, pos.x, lane), dr.gather(mi.Float, pos.y, lane))
                block.put(p, [dr.gather(mi.Float, rgb[c], lane) for c in range(3)] + [mi.Float(1.0)])
                dr.eval(block.tensor())    # alone: splats of equal size evaluated together fuse into a new kernel
        dr.eval(*[block.tensor() for block, _, _ in spans])
        self._queued(pixels, spp)


class Traced(Generic[T]):
    """Work queued on Dr.Jit's device: `result()` waits for it once and returns what the
    waiting call (`trace_jobs`, `render_passes`) would have."""

    def __init__(self, finish: Callable[[], T]) -> None:
        self._finish: Callable[[], T] | None = finish
        self._value: T | None = None

    def result(self) -> T:
        if self._finish is not None:
            self._value, self._finish = self._finish(), None
        return self._value  # type: ignore[return-value]
