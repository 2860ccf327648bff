"""One kernel launch per pass for any set of pixels: the live loop's Mitsuba calls.

`mi.render` traces a whole film (or its crop window). An adaptive render wants samples
only for the pixels of its active units (`renderer.live.passloop`: tiles, or blocks), which may
be any set; a crop window per unit costs one Mitsuba call and, the first time, one kernel
compilation per unit (the crop is baked into the kernel, mitsuba3 #908).
`WavefrontTracer` instead does what Mitsuba's
``SamplingIntegrator.render`` does per sample, for a wavefront of exactly the requested
pixels: a film position per sample, ``sensor.sample_ray_differential``, the scene's own
integrator's ``sample``, and the film's reconstruction filter. Every value that changes
between passes (the pixels, the pass key, spp) is opaque, so one render compiles its
kernel once, whatever the active set.

Random numbers are keyed per sample, not per lane: sample j of pixel p in a pass with key
k draws from a PCG32 stream seeded by TEA(p, k) and TEA(j, .) (`KeyedSampler`). A pixel
therefore gets the same samples whichever other pixels are traced with it, and any set of
units is bit for bit the same estimator as those units cut out of a full-frame trace:

* box filter (radius 1/2): each sample is summed into its own pixel (the pixel's
  consecutive lanes, summed on the device by `dr.block_sum`), so units are independent;
* wider filters (the Gaussian of most published scenes): samples are splatted with the
  film's filter into a frame-sized ``mi.ImageBlock``, and the traced set is the requested
  pixels grown by a guard band of ``floor(radius + 1/2)`` pixels, every pixel whose samples
  can reach a requested one (`guard_band`). Only the requested pixels are kept.

Pixels on the frame's edge get no samples from outside it, as in a full-frame render
without ``sample_border``.

Keys are per lane, so one launch can also trace several passes (`trace_jobs`: a pixel set
and a key per job): the units of a budget round at different pass counts, or k passes
of the active units as one k times larger wavefront (few units left, or no decision due
before the k-th pass: `renderer.live.launches.grown_passes`). With a box filter each job's
values are bit for bit those of its pass traced alone; with a wider filter, to float32
rounding (the samples are the same; a launch of several jobs evaluates them first and
splats each job's own lanes in a kernel of its own, one job fuses the splat into the
path tracer's kernel). Launches, lanes and samples traced go to the tracer's `ledger`
(`renderer.live.ledger`: its renderer's).
"""
from __future__ import annotations

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


def guard_band(radius: float) -> int:
    """Pixels around a requested one whose samples can reach it through the filter.

    A sample of pixel q lies in [q, q + 1] (inclusive: q + u rounds to q + 1 in float32
    for u close to 1) and reaches pixel p when |p + 1/2 - x| <= radius.
    """
    return int(math.floor(float(radius) + 0.5))


def filter_nonnegative(rfilter: Any) -> bool:
    """Whether a reconstruction filter is >= 0 over its radius (box, tent, gaussian; not
    mitchell or catmullrom), sampled at 64 points: a checkpoint's sums are then >= 0."""
    r = float(rfilter.radius())
    return all(float(np.asarray(rfilter.eval(r * i / 63)).min()) >= 0.0 for i in range(64))


def filter_guard(rfilter: Any) -> int:
    """The guard band a film's reconstruction filter needs, for both engines: none for a box
    filter (each sample stays in its own pixel), else `guard_band` of its radius."""
    return 0 if rfilter.is_box_filter() else guard_band(rfilter.radius())


def _keyed_sampler_class() -> type:
    """`KeyedSampler` needs a variant; built on first use and cached."""
    global _KEYED
    if _KEYED is not None:
        return _KEYED
    mi = require("mitsuba")

    class KeyedSampler(mi.Sampler):
        """Independent uniform numbers from one PCG32 stream per (pixel, sample, pass).

        Mitsuba's `independent` sampler seeds lane i's stream from (seed, i): a pixel's
        samples would depend on its position in the wavefront, i.e. on which other
        pixels are traced. Here the caller gives each lane its stream (`set_streams`).
        """

        DRJIT_STRUCT = {"rng": mi.PCG32}

        def __init__(self, props: Any = None) -> None:
            super().__init__(props if props is not None else mi.Properties())
            self.rng = mi.PCG32()

        def seed(self, seed: Any, wavefront_size: int = 0) -> None:
            """Streams come from `set_streams`; Mitsuba's own seeding is not used."""

        def set_streams(self, state: Any, sequence: Any) -> None:
            # seed() on a default generator: a constructor given the size would add
            # arange(size) to both values (tying a lane's stream to its position in the
            # wavefront) and compile a small kernel for every new wavefront size
            self.rng = mi.PCG32()
            self.rng.seed(state, sequence)

        def next_1d(self, active: Any = True) -> Any:
            return self.rng.next_float32(active)

        def next_2d(self, active: Any = True) -> Any:
            return mi.Point2f(self.next_1d(active), self.next_1d(active))

    _KEYED = KeyedSampler
    return KeyedSampler


_KEYED: type | None = None


def as_int32_bits(values: torch.Tensor) -> torch.Tensor:
    """32-bit keys (int64 in [0, 2^32)) as int32 tensors of the same bits: Dr.Jit's UInt32
    takes them bit for bit, and int32 crosses DLPack on every torch device."""
    return torch.where(values >= 2**31, values - 2**32, values).to(torch.int32)


def torch_device(variant: str) -> torch.device:
    """Where a render's per-pass arrays live: the GPU for a ``cuda_*`` variant, else the CPU."""
    return torch.device("cuda") if variant.startswith("cuda") else torch.device("cpu")


class WavefrontTracer:
    """Trace `spp` samples for any set of a frame's pixels; one compiled kernel per render.

    `frame` is the film's crop window (the whole film unless an XML file sets a crop):
    pixel indices are row-major within it. Needs a vectorised (JIT) Mitsuba variant.
    Pixel sets come in and frames go out as torch tensors on `device`, shared with Dr.Jit
    through DLPack: on a GPU no pass ever crosses to the host. `ledger`: where its launches
    ("kernel_launches"), their lanes ("kernel_lanes", one a sample) and the samples traced,
    guard band included ("samples_traced"), are counted (None: a ledger of its own).
    """

    def __init__(self, scene: Any, sensor: Any, integrator: Any, device: torch.device | None = None,
                 ledger: Ledger | None = None) -> None:
        dr = require("drjit")
        mi = require("mitsuba")

        self._mi, self._dr = mi, dr
        self.scene, self.sensor, self.integrator = scene, sensor, integrator
        self.device = torch.device("cpu") if device is None else device
        film = sensor.film()
        self.width, self.height = int(film.crop_size()[0]), int(film.crop_size()[1])
        self._offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        self._film_size = (int(film.size()[0]), int(film.size()[1]))
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
        """Pixel estimates float32 [H, W, 3] for the pixels of `mask` (others are 0).

        `key` (32 bits) selects the pass's random numbers: the same (pixel, spp, key)
        always gives the same value, whatever else is in `mask`.
        """
        return self.trace_jobs([(mask, key)], spp)[0]

    def trace_jobs(self, jobs: Sequence[tuple[Any, int]], spp: int) -> list[torch.Tensor]:
        """Several passes in one launch: float32 [H, W, 3] per (pixel mask, key) job.

        Each job is what `trace(mask, spp, key)` returns (random numbers are keyed
        per (pixel, sample, key), and every job's pixels are summed on their own), so
        passes of different units at different pass indices, or several passes of the same
        units, share one launch: a larger wavefront, whose fixed cost per launch (about
        10 ms here) is paid once. With a box filter each pixel's samples are summed on
        their own; a wider filter splats each job into its own frame (one ImageBlock per
        job; `_submit_splat`), equal to the job traced alone to float32 rounding.
        """
        return self.submit_jobs(jobs, spp).result()

    def submit_jobs(self, jobs: Sequence[tuple[Any, int]], spp: int) -> Traced[list[torch.Tensor]]:
        """`trace_jobs` without waiting: the launches are queued on Dr.Jit's device (its
        LLVM thread pool or CUDA stream) and the caller's thread goes on; `result()`
        waits for them and returns what `trace_jobs` would. What the live loop judges one
        launch by while the next traces (`renderer.live.session`)."""
        if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        masks = [self._mask(m) for m, _ in jobs]
        keys = [int(k) & 0xFFFFFFFF for _, k in jobs]
        frame = (self.height, self.width, 3)
        grown = masks if self.box else [self.traced_pixels(m) for m in masks]
        pixels = [torch.nonzero(m.flatten()).flatten() for m in grown]
        counts = [int(p.numel()) for p in pixels]
        total = sum(counts)
        if total == 0:
            return Traced(lambda: [torch.zeros(frame, dtype=torch.float32, device=self.device) for _ in masks])
        all_pixels = torch.cat(pixels).to(torch.int32)
        job_of = torch.repeat_interleave(torch.arange(len(masks)), torch.tensor(counts)).to(self.device)
        all_keys = as_int32_bits(torch.tensor(keys, dtype=torch.int64, device=self.device)[job_of])
        self.ledger.count("samples_traced", total * int(spp))
        per_launch = max(1, MAX_LANES // int(spp))
        if self.box:
            chunks = [self._submit_box(all_pixels[i:i + per_launch], int(spp), all_keys[i:i + per_launch])
                      for i in range(0, total, per_launch)]

            def box_result() -> list[torch.Tensor]:
                values = torch.cat([finish() for finish in chunks])
                outs = []
                for pix, part in zip(pixels, torch.split(values, counts)):
                    out = torch.zeros((self.height * self.width, 3), dtype=torch.float32, device=self.device)
                    out[pix] = part
                    outs.append(out.view(frame))
                return outs
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
            self._submit_splat(all_pixels[i:j], int(spp), all_keys[i:j], spans)
        tensors = [f.tensor() for f in films]      # a job's frame: its ImageBlock

        def splat_result() -> list[torch.Tensor]:
            self._sync()
            outs = []
            for mask, t in zip(masks, tensors):
                sums = t.torch().reshape(-1, 4)
                w = sums[:, 3:]
                # float32 division of float32 sums: the correctly rounded quotient, as float64's rounded
                value = torch.where(w > 0, sums[:, :3] / torch.where(w > 0, w, 1.0), 0.0)
                outs.append(torch.where(mask.reshape(-1, 1), value, 0.0).view(frame))
            return outs
        return Traced(splat_result)

    # -- one launch ---------------------------------------------------------------

    def _samples(self, pixels: torch.Tensor, spp: int, keys: torch.Tensor) -> tuple[Any, Any]:
        """(film position, radiance) of every sample of `pixels`, each pixel with its pass
        key (`keys`, int32 tensors read as UInt32): lanes pixel-major."""
        mi, dr = self._mi, self._dr
        n = int(pixels.numel()) * spp
        lane = dr.arange(mi.UInt32, n)
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
        """Dr.Jit and torch queue GPU work on their own streams: hand arrays across only
        once the other side's work is done (one wait per launch; nothing on the CPU)."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self._dr.sync_thread()

    def _queued(self, pixels: torch.Tensor, spp: int) -> None:
        self.ledger.count("kernel_launches")
        self.ledger.count("kernel_lanes", int(pixels.numel()) * spp)

    def _submit_box(self, pixels: torch.Tensor, spp: int, keys: torch.Tensor) -> Callable[[], torch.Tensor]:
        """Box filter: queue one launch; its finish gives the mean of each pixel's own
        samples, float32 [n, 3] on the device. Lanes are pixel-major, so each pixel's spp
        samples are consecutive: Dr.Jit sums them by blocks of spp (`dr.block_sum`, in
        float32, in lane order: a pixel's sum depends on its samples alone), on the device,
        once the lanes are evaluated (summed straight from the path tracer's expression, each
        channel would trace the paths again)."""
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
        """Any filter: queue one launch of `pixels`' samples, then splat each span of its
        pixels (block, first, end: pixel positions in `pixels`) into its block with the film's
        filter. One job (a plain pass) is one kernel, the splat fused in; several are the
        samples evaluated once and a splat per job over its own lanes (masked splats over
        every lane would cost a filter footprint per lane per job). Start and size are opaque,
        so no job layout compiles anything new."""
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
    """Work queued on Dr.Jit's device and not yet read (`WavefrontTracer.submit_jobs`,
    `BlockRenderer.submit_passes`): `result()` waits for it once and returns what the
    waiting call (`trace_jobs`, `render_passes`) would have."""

    def __init__(self, finish: Callable[[], T]) -> None:
        self._finish: Callable[[], T] | None = finish
        self._value: T | None = None

    def result(self) -> T:
        if self._finish is not None:
            self._value, self._finish = self._finish(), None
        return self._value  # type: ignore[return-value]
