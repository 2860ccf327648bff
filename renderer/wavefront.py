"""One kernel launch per pass for any set of pixels: the live loop's Mitsuba calls.

`mi.render` traces a whole film (or its crop window). An adaptive render wants samples
only for the pixels of its active blocks, which may be any set; a crop window per block
costs one Mitsuba call and, the first time, one kernel compilation per block (the crop is
baked into the kernel, mitsuba3 #908). `WavefrontTracer` instead does what Mitsuba's
``SamplingIntegrator.render`` does per sample, for a wavefront of exactly the requested
pixels: a film position per sample, ``sensor.sample_ray_differential``, the scene's own
integrator's ``sample``, and the film's reconstruction filter. Every value that changes
between passes (the pixels, the pass key, spp) is opaque, so one render compiles its
kernel once, whatever the active set.

Random numbers are keyed per sample, not per lane: sample j of pixel p in a pass with key
k draws from a PCG32 stream seeded by TEA(p, k) and TEA(j, .) (`KeyedSampler`). A pixel
therefore gets the same samples whichever other pixels are traced with it, and any set of
blocks is bit for bit the same estimator as those blocks cut out of a full-frame trace:

* box filter (radius 1/2): each sample is summed into its own pixel (the pixel's
  consecutive lanes), so blocks are independent;
* wider filters (the Gaussian of most published scenes): samples are splatted with the
  film's filter into a frame-sized ``mi.ImageBlock``, and the traced set is the requested
  pixels grown by a guard band of ``floor(radius + 1/2)`` pixels, every pixel whose samples
  can reach a requested one (`guard_band`). Only the requested pixels are read back.

Pixels on the frame's edge get no samples from outside it, as in a full-frame render
without ``sample_border``.

Keys are per lane, so one launch can also trace several passes (`trace_jobs`: a pixel set
and a key per job): the blocks of a budget round at different pass counts, or k steps of
few active blocks as one k times larger wavefront, each job's values exactly those of
its pass traced alone.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from noisefeat.extras import require

#: lanes per kernel launch: larger pixel sets are traced in chunks (same kernel)
MAX_LANES = 1 << 24


def guard_band(radius: float) -> int:
    """Pixels around a requested one whose samples can reach it through the filter.

    A sample of pixel q lies in [q, q + 1] (inclusive: q + u rounds to q + 1 in float32
    for u close to 1) and reaches pixel p when |p + 1/2 - x| <= radius.
    """
    return int(math.floor(float(radius) + 0.5))


def _keyed_sampler_class() -> type:
    """`KeyedSampler` needs a variant; built on first use and cached."""
    global _KEYED
    if _KEYED is not None:
        return _KEYED
    dr = require("drjit")
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


class WavefrontTracer:
    """Trace `spp` samples for any set of a frame's pixels; one compiled kernel per render.

    `frame` is the film's crop window (the whole film unless an XML file sets a crop):
    pixel indices are row-major within it. Needs a vectorised (JIT) Mitsuba variant.
    """

    def __init__(self, scene: Any, sensor: Any, integrator: Any) -> None:
        dr = require("drjit")
        mi = require("mitsuba")

        self._mi, self._dr = mi, dr
        self.scene, self.sensor, self.integrator = scene, sensor, integrator
        film = sensor.film()
        self.width, self.height = int(film.crop_size()[0]), int(film.crop_size()[1])
        self._offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        self._film_size = (int(film.size()[0]), int(film.size()[1]))
        self.rfilter = film.rfilter()
        self.box = bool(self.rfilter.is_box_filter())
        self.guard = 0 if self.box else guard_band(self.rfilter.radius())
        self._sampler = _keyed_sampler_class()()
        self.launches = 0
        self.lanes = 0            # lanes launched (one per sample), over every launch
        self.samples = 0          # samples traced, guard band included

    def traced_pixels(self, mask: np.ndarray) -> np.ndarray:
        """The requested pixel mask [H, W] grown by the guard band (clipped to the frame)."""
        mask = np.asarray(mask, bool)
        g = self.guard
        if g == 0 or not mask.any():
            return mask
        # separable dilation by a (2g+1) square: first along x, then along y
        cum = np.cumsum(np.pad(mask, ((0, 0), (g + 1, g)), constant_values=False), axis=1, dtype=np.int32)
        row_grown = (cum[:, 2 * g + 1:] - cum[:, :-2 * g - 1]) > 0
        cum = np.cumsum(np.pad(row_grown, ((g + 1, g), (0, 0)), constant_values=False), axis=0, dtype=np.int32)
        return (cum[2 * g + 1:] - cum[:-2 * g - 1]) > 0

    def trace(self, mask: np.ndarray, spp: int, key: int) -> np.ndarray:
        """Pixel estimates float32 [H, W, 3] for the pixels of `mask` (others are 0).

        `key` (32 bits) selects the pass's random numbers: the same (pixel, spp, key)
        always gives the same value, whatever else is in `mask`.
        """
        return self.trace_jobs([(mask, key)], spp)[0]

    def trace_jobs(self, jobs: Sequence[tuple[np.ndarray, int]], spp: int) -> list[np.ndarray]:
        """Several passes in one launch: float32 [H, W, 3] per (pixel mask, key) job.

        Each job is exactly what `trace(mask, spp, key)` returns (random numbers are keyed
        per (pixel, sample, key), and every job's pixels are summed on their own), so
        passes of different blocks at different pass indices, or several steps of the same
        blocks, share one launch: a larger wavefront when few pixels are active. With a
        box filter all jobs go in one launch; a wider filter splats each job into its own
        frame, one launch per job.
        """
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        masks, keys = [], []
        for mask, key in jobs:
            mask = np.asarray(mask, bool)
            if mask.shape != (self.height, self.width):
                raise ValueError(f"pixel mask {mask.shape} does not match the frame {(self.height, self.width)}")
            masks.append(mask)
            keys.append(int(key) & 0xFFFFFFFF)
        outs = [np.zeros((self.height, self.width, 3), np.float32) for _ in masks]
        if not self.box:
            for out, mask, key in zip(outs, masks, keys):
                self._trace_splat(out, mask, int(spp), key)
            return outs
        pixels = [np.flatnonzero(m.ravel()).astype(np.uint32) for m in masks]
        lane_keys = [np.full(p.size, k, np.uint32) for p, k in zip(pixels, keys)]
        job_of = np.repeat(np.arange(len(masks)), [p.size for p in pixels])
        all_pixels = np.concatenate(pixels) if pixels else np.zeros(0, np.uint32)
        all_keys = np.concatenate(lane_keys) if lane_keys else np.zeros(0, np.uint32)
        if all_pixels.size == 0:
            return outs
        self.samples += int(all_pixels.size) * int(spp)
        per_launch = max(1, MAX_LANES // int(spp))
        values = np.empty((all_pixels.size, 3), np.float32)
        for i in range(0, all_pixels.size, per_launch):
            values[i:i + per_launch] = self._launch_box(all_pixels[i:i + per_launch], int(spp),
                                                        all_keys[i:i + per_launch])
        for j, out in enumerate(outs):
            out.reshape(-1, 3)[pixels[j]] = values[job_of == j]
        return outs

    def _trace_splat(self, out: np.ndarray, mask: np.ndarray, spp: int, key: int) -> None:
        """One job with a wide filter: splat the grown pixel set, read back `mask`."""
        traced = self.traced_pixels(mask)
        pixels = np.flatnonzero(traced.ravel()).astype(np.uint32)
        if pixels.size == 0:
            return
        self.samples += int(pixels.size) * int(spp)
        per_launch = max(1, MAX_LANES // int(spp))
        acc = np.zeros((self.height * self.width, 4), np.float64)
        for i in range(0, pixels.size, per_launch):
            chunk = pixels[i:i + per_launch]
            acc += self._launch_splat(chunk, spp, np.full(chunk.size, key, np.uint32))
        want = np.flatnonzero(mask.ravel())
        w = acc[want, 3:]
        out.reshape(-1, 3)[want] = np.divide(acc[want, :3], w, out=np.zeros((want.size, 3)), where=w > 0)

    # -- one launch ---------------------------------------------------------------

    def _samples(self, pixels: np.ndarray, spp: int, keys: np.ndarray) -> tuple[Any, Any]:
        """(film position, radiance) of every sample of `pixels`, each pixel with its pass
        key (`keys`, uint32 like `pixels`): lanes pixel-major."""
        mi, dr = self._mi, self._dr
        n = int(pixels.size) * spp
        lane = dr.arange(mi.UInt32, n)
        spp_o = dr.opaque(mi.UInt32, spp)
        which = lane // spp_o
        j = lane - which * spp_o
        pix = dr.gather(mi.UInt32, mi.UInt32(pixels), which)
        key = dr.gather(mi.UInt32, mi.UInt32(keys), which)
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

    def _launch_box(self, pixels: np.ndarray, spp: int, keys: np.ndarray) -> np.ndarray:
        """Box filter: the mean of each pixel's own samples, float32 [n, 3]."""
        mi, dr = self._mi, self._dr
        _, rgb = self._samples(pixels, spp, keys)
        dr.eval(rgb)
        self.launches += 1
        self.lanes += int(pixels.size) * spp
        # lanes are pixel-major: each pixel's spp samples are consecutive (numpy sums them
        # faster than dr.block_sum on the llvm backend)
        # (channel by channel: converting the Color3f at once would compile a copy kernel
        # for every wavefront size)
        values = np.stack([np.asarray(rgb[c], np.float32) for c in range(3)]).reshape(3, pixels.size, spp)
        return values.sum(axis=2, dtype=np.float64).T.astype(np.float32) / np.float32(spp)

    def _launch_splat(self, pixels: np.ndarray, spp: int, keys: np.ndarray) -> np.ndarray:
        """Any filter: weighted sums and weights [H * W, 4] splatted over the frame."""
        mi, dr = self._mi, self._dr
        pos, rgb = self._samples(pixels, spp, keys)
        block = mi.ImageBlock(mi.ScalarVector2u(self.width, self.height), mi.ScalarPoint2i(0, 0), 4,
                              self.rfilter, border=False)
        block.put(pos, [rgb[0], rgb[1], rgb[2], mi.Float(1.0)])
        tensor = block.tensor()
        dr.eval(tensor)
        self.launches += 1
        self.lanes += int(pixels.size) * spp
        return np.asarray(tensor, np.float64).reshape(-1, 4)
