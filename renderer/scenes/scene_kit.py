"""Parts every built-in scene is made of, and the skeleton `base` whose settings all share:
``path`` to depth 8 (mirrors and caustics look right, a scene still takes about a second at
128x128 and 64 spp on llvm); a box-filtered film (each sample stays in its pixel, so a block
rendered alone as a crop window is the same estimator as that block cut from a full frame,
where Mitsuba's Gaussian splats 2 px wide); the ``independent`` sampler (passes with distinct
seeds are independent, as the cumulative means and half buffers assume; its ``sample_count``
is a placeholder for ``mi.render``'s).
"""
from __future__ import annotations

from typing import Any

import numpy as np
from noisefeat.extras import require

MAX_DEPTH = 8

SceneDict = dict[str, Any]


def T() -> Any:
    return require("mitsuba").ScalarTransform4f()


def rgb(v: float | list[float]) -> dict:
    vals = [float(v)] * 3 if isinstance(v, (int, float)) else [float(x) for x in v]
    return {"type": "rgb", "value": vals}


def diffuse(v: float | list[float]) -> dict:
    return {"type": "diffuse", "reflectance": rgb(v)}


def checker_texture(c0: float | list[float], c1: float | list[float], scale: float) -> dict:
    return {"type": "checkerboard", "color0": rgb(c0), "color1": rgb(c1),
            "to_uv": require("mitsuba").ScalarTransform3f().scale([scale, scale])}


def base(resolution: int, origin: tuple[float, float, float] = (0.0, 0.0, 3.9),
         target: tuple[float, float, float] = (0.0, 0.0, 0.0), fov: float = 39.3077) -> SceneDict:
    """Scene skeleton: path integrator, perspective camera, box-filtered hdrfilm (module docstring)."""
    if not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH},
        "sensor": {
            "type": "perspective", "fov_axis": "smaller", "fov": fov, "near_clip": 0.001, "far_clip": 100.0,
            "to_world": T().look_at(origin=list(origin), target=list(target), up=[0.0, 1.0, 0.0]),
            "sampler": {"type": "independent", "sample_count": 16},
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"},
        },
    }


def value_noise(size: int, octaves: int, seed: int) -> np.ndarray:
    """Smooth fractal noise in [0, 1], [size, size] float32 (bilinear octaves of random grids)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = 4 * 2 ** o
        grid = rng.random((cells + 1, cells + 1))
        t = np.linspace(0, cells, size, endpoint=False)
        i = t.astype(int)
        f = t - i
        f = f * f * (3 - 2 * f)
        rows = grid[i][:, i] * (1 - f)[None, :] + grid[i][:, i + 1] * f[None, :]
        rows2 = grid[i + 1][:, i] * (1 - f)[None, :] + grid[i + 1][:, i + 1] * f[None, :]
        out += amp * (rows * (1 - f)[:, None] + rows2 * f[:, None])
        total += amp
        amp *= 0.5
    out /= total
    return ((out - out.min()) / (np.ptp(out) + 1e-12)).astype(np.float32)


def bitmap_texture(image: np.ndarray) -> dict:
    return {"type": "bitmap", "bitmap": require("mitsuba").Bitmap(np.ascontiguousarray(image, np.float32)),
            "raw": True}


def room_box(width: float, depth: float, height: float, floor: dict, walls: dict, back: dict | None = None,
             open_left: bool = False, front: float = 0.0, closed: bool = False) -> SceneDict:
    """Floor, ceiling and walls of a box room centred on x, floor at y = 0, spanning z from
    `front` back to `front - depth`; open at the front unless `closed`."""
    w, d, h, zc = width / 2, depth / 2, height / 2, front - depth / 2
    x, y = [1, 0, 0], [0, 1, 0]
    parts = {      # name: (bsdf, centre, rotation axis and degrees, half sizes)
        "floor": (floor, [0, 0, zc], x, -90, [w, d, 1]),
        "ceiling": (walls, [0, height, zc], x, 90, [w, d, 1]),
        "back": (back or walls, [0, h, front - depth], y, 0, [w, h, 1]),
        "right": (walls, [w, h, zc], y, -90, [d, h, 1]),
        "left": (walls, [-w, h, zc], y, 90, [d, h, 1]),
        "front": (walls, [0, h, front], y, 180, [w, h, 1]),
    }
    return {name: {"type": "rectangle", "bsdf": bsdf, "to_world": T().translate(at).rotate(axis, deg).scale(size)}
            for name, (bsdf, at, axis, deg, size) in parts.items()
            if not ((name == "left" and open_left) or (name == "front" and not closed))}


def sphere(centre: list[float], radius: float, bsdf: dict) -> dict:
    return {"type": "sphere", "center": centre, "radius": radius, "bsdf": bsdf}


def sphere_light(centre: list[float], radius: float, radiance: list[float] | float) -> dict:
    return {"type": "sphere", "center": centre, "radius": radius,
            "emitter": {"type": "area", "radiance": rgb(radiance)}}


def panel(centre: list[float], sx: float, sz: float, radiance: list[float] | float) -> dict:
    """A downward-facing rectangular area light."""
    return {"type": "rectangle", "emitter": {"type": "area", "radiance": rgb(radiance)},
            "to_world": T().translate(centre).rotate([1, 0, 0], 90).scale([sx, sz, 1])}


def cube(centre: list[float], size: list[float], bsdf: dict, angle: float = 0.0) -> dict:
    return {"type": "cube", "bsdf": bsdf,
            "to_world": T().translate(centre).rotate([0, 1, 0], angle).scale([s / 2 for s in size])}
