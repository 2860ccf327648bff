"""Block (crop-window) rendering and exact per-block accumulation.

The paper cuts every image into a grid of blocks and keeps sampling only the blocks a
human would still find noisy, so the renderer must be able to spend samples on any
subset of blocks. `BlockRenderer` does that with the film's crop window, which Mitsuba 3
exposes through ``mi.traverse(sensor)`` as ``film.crop_offset`` / ``film.crop_size``
(``params.update()`` then notifies film and sensor). With a box reconstruction filter
(what the built-in scenes use, see `renderer.scenes`) a block rendered alone is the same
estimator as that block cut from a full-frame render.

JIT note: Mitsuba bakes the crop window into the compiled kernel (scalar parameters
cannot be made opaque, mitsuba3 issue #908), so each distinct block costs one kernel
compilation the first time it is rendered in a process (about 0.2 s on llvm, then
cached in memory and in Dr.Jit's on-disk cache). Seeds are opaque: new passes never
recompile.

`learning.accumulator.BlockAccumulator` keeps the float64 running
sums so cumulative means are exact, plus two half buffers (even and odd passes) for the
half-buffer criteria (Cycles-style variance, FLIP between the halves).
"""

from __future__ import annotations

import hashlib
import logging
import statistics
import struct
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from .variant import select_variant

logger = logging.getLogger(__name__)

FULL_FRAME = -1  # block id used to derive the seeds of full-frame renders


def derive_seed(seed: int, block_id: int, pass_index: int) -> int:
    """Deterministic 32-bit Mitsuba seed for (base seed, block, pass).

    Hashing (rather than e.g. ``seed + block_id``) keeps the streams of different
    blocks and passes apart even when callers pick consecutive base seeds, and makes any
    pass reproducible on its own, which is what resuming an interrupted build needs.
    """
    data = struct.pack("<qqq", int(seed), int(block_id), int(pass_index))
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


#: quick images the renderer can make (learning.table.QUICK_MODES adds 'none')
QUICK_KINDS = ("albedo", "direct")


class BlockRenderer:
    """Render any subset of a grid of blocks of one scene's first sensor.

    `grid` is (rows, columns); blocks are numbered row-major, block 0 top-left. If the
    scene's film already has a crop window (possible in XML files), that window is the
    frame that gets cut into blocks.
    """

    def __init__(self, scene: Any, grid: tuple[int, int] = (4, 4)) -> None:
        select_variant()
        import mitsuba as mi

        self._mi = mi
        self.scene = scene
        self.sensor = scene.sensors()[0]
        film = self.sensor.film()
        gh, gw = (int(g) for g in grid)
        if gh < 1 or gw < 1:
            raise ValueError(f"grid must be two positive integers (rows, columns), got {grid!r}")
        self.grid = (gh, gw)
        self._frame_offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        self.width, self.height = int(film.crop_size()[0]), int(film.crop_size()[1])
        if self.width % gw or self.height % gh:
            raise ValueError(
                f"image {self.width}x{self.height} (WxH) cannot be cut into a {gh}x{gw} grid of equal "
                f"blocks: width must be divisible by {gw} and height by {gh}"
            )
        self.block_h, self.block_w = self.height // gh, self.width // gw
        radius = float(film.rfilter().radius())
        if radius > 0.5 + 1e-6:
            logger.warning(
                "film reconstruction filter %s has radius %.2f px > 0.5: block edges rendered alone "
                "differ slightly from a full-frame render (use rfilter 'box' for exact independence)",
                film.rfilter().class_name(), radius,
            )
        # an XML scene may declare no integrator (mi.render then refuses): Mitsuba's path tracer
        self._integrator = scene.integrator()
        if self._integrator is None:
            logger.info("scene declares no integrator; using Mitsuba's 'path'")
            self._integrator = mi.load_dict({"type": "path"})
        self._params = mi.traverse(self.sensor)
        self._crop: tuple[int, int, int, int] | None = None
        self._set_crop(0, 0, self.width, self.height)

    # -- geometry ---------------------------------------------------------------

    @property
    def n_blocks(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def block_shape(self) -> tuple[int, int]:
        """(block height, block width) in pixels."""
        return self.block_h, self.block_w

    def block_origin(self, block_id: int) -> tuple[int, int]:
        """(x, y) of the block's top-left pixel within the frame."""
        self._check_id(block_id)
        row, col = divmod(int(block_id), self.grid[1])
        return col * self.block_w, row * self.block_h

    def block_slices(self, block_id: int) -> tuple[slice, slice]:
        """(rows, columns) slices that cut the block out of a [H, W, ...] frame."""
        x0, y0 = self.block_origin(block_id)
        return slice(y0, y0 + self.block_h), slice(x0, x0 + self.block_w)

    def _check_id(self, block_id: int) -> None:
        if not isinstance(block_id, (int, np.integer)) or not 0 <= int(block_id) < self.n_blocks:
            raise ValueError(f"block id {block_id!r} out of range 0..{self.n_blocks - 1}")

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

    def _render(self, spp: int, mitsuba_seed: int, integrator: Any = None, where: str = "render") -> np.ndarray:
        if not isinstance(spp, (int, np.integer)) or spp < 1:
            raise ValueError(f"spp must be a positive integer, got {spp!r}")
        img = self._mi.render(self.scene, sensor=self.sensor,
                              integrator=self._integrator if integrator is None else integrator,
                              spp=int(spp), seed=int(mitsuba_seed))
        return _to_rgb(img, where)

    def render_blocks(self, block_ids: Sequence[int], spp: int, seed: int, pass_index: int = 0) -> np.ndarray:
        """`spp` new samples for each listed block: float32 [len(ids), bh, bw, 3].

        Block b uses Mitsuba seed ``derive_seed(seed, b, pass_index)``: call again with a
        new `pass_index` (or a new `seed`) for an independent pass of the same blocks.
        """
        ids = [int(b) for b in block_ids]
        for b in ids:
            self._check_id(b)
        if len(set(ids)) != len(ids):
            raise ValueError(f"duplicate block ids in {ids}: one call renders each block once")
        out = np.empty((len(ids), self.block_h, self.block_w, 3), dtype=np.float32)
        try:
            for i, b in enumerate(ids):
                x0, y0 = self.block_origin(b)
                self._set_crop(x0, y0, self.block_w, self.block_h)
                out[i] = self._render(spp, derive_seed(seed, b, pass_index), where=f"block {b}")
        finally:
            self._set_crop(0, 0, self.width, self.height)  # leave the scene as we found it
        return out

    def render_full(self, spp: int, seed: int, pass_index: int = 0) -> np.ndarray:
        """`spp` samples for the whole frame: float32 [H, W, 3]."""
        self._set_crop(0, 0, self.width, self.height)
        return self._render(spp, derive_seed(seed, FULL_FRAME, pass_index), where="full frame")

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
        return self._render(spp, derive_seed(seed, FULL_FRAME, -1), integrator=integrator,
                            where=f"{kind} quick image")


# ----------------------------------------------------------------------------- benchmark


def measure_crop_cost(
    scene_name: str = "cornell",
    resolution: int = 256,
    spp: int = 64,
    repeats: int = 3,
    block_ids: Sequence[int] = (0, 5, 10, 15),
    grid: tuple[int, int] = (4, 4),
) -> dict[str, Any]:
    """Wall time of rendering a few blocks vs the full frame, both warm.

    The first render of each crop compiles its kernel; that time is reported apart
    (``compile_*_s`` = first call minus the warm median). The goal is
    ``ratio ~= len(block_ids) / n_blocks`` (a quarter for 4 of 16).
    """
    from .scenes import load_scene
    from .variant import current_variant

    scene = load_scene(scene_name, resolution)
    r = BlockRenderer(scene, grid)
    ids = list(block_ids)

    t0 = time.perf_counter()
    r.render_full(spp, seed=0)
    first_full = time.perf_counter() - t0
    t0 = time.perf_counter()
    r.render_blocks(ids, spp, seed=0)
    first_blocks = time.perf_counter() - t0

    full_t, blocks_t = [], []
    for k in range(max(1, int(repeats))):
        t0 = time.perf_counter()
        r.render_full(spp, seed=1, pass_index=k)
        full_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        r.render_blocks(ids, spp, seed=1, pass_index=k)
        blocks_t.append(time.perf_counter() - t0)
    full_s, blocks_s = statistics.median(full_t), statistics.median(blocks_t)
    result = {
        "variant": current_variant(),
        "scene": scene_name,
        "resolution": resolution,
        "spp": spp,
        "grid": list(r.grid),
        "blocks": ids,
        "full_s": full_s,
        "blocks_s": blocks_s,
        "ratio": blocks_s / full_s if full_s > 0 else float("nan"),
        "ideal_ratio": len(ids) / r.n_blocks,
        "compile_full_s": max(0.0, first_full - full_s),
        "compile_blocks_s": max(0.0, first_blocks - blocks_s),
        "full_mpaths_per_s": resolution * resolution * spp / full_s / 1e6 if full_s > 0 else float("nan"),
    }
    logger.info("crop cost: %s", result)
    return result
