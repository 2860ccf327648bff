"""Held-out scenes (`catalog.SCENES` describes them): eight views no model is trained or
calibrated on, sharing nothing with the training library but the render settings (`scene_kit`),
most of whose blocks converge within `make heldout`'s 2048 spp. Textures and the environment map
come from seeded numpy noise: no files, the same scenes on every machine.
"""
from __future__ import annotations

import math

import numpy as np

from .scene_kit import (SceneDict, T, base, bitmap_texture, checker_texture, cube, diffuse, panel, rgb, room_box,
                        sphere, sphere_light, value_noise)
from noisefeat.extras import require


def marble(size: int = 256, seed: int = 3) -> np.ndarray:
    """Veined marble, linear RGB [size, size, 3]."""
    n = value_noise(size, 5, seed)
    x = np.linspace(0, 6 * math.pi, size)[None, :]
    veins = 0.5 + 0.5 * np.sin(x + 9.0 * n)
    v = 0.45 + 0.4 * veins ** 3
    return np.stack([v, v * 0.96, v * 0.9], -1).astype(np.float32)


def wood(size: int = 256, seed: int = 4) -> np.ndarray:
    """Wood-grain stripes, linear RGB."""
    n = value_noise(size, 4, seed)
    y = np.linspace(0, 40 * math.pi, size)[:, None]
    rings = 0.5 + 0.5 * np.sin(y + 6.0 * n)
    v = 0.18 + 0.2 * rings
    return np.stack([v * 1.0, v * 0.62, v * 0.35], -1).astype(np.float32)


def studio_environment(width: int = 256, seed: int = 5) -> np.ndarray:
    """A photographer's studio as an equirectangular map: dim grey surround, two soft boxes."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * math.pi               # 0 at the zenith
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    img = 0.12 + 0.10 * np.cos(th)[..., None] * np.ones(3)    # brighter above
    for centre_phi, centre_th, size, power in ((1.2, 0.9, 0.35, 9.0), (4.0, 1.1, 0.5, 3.0)):
        d = np.hypot((ph - centre_phi) / size, (th - centre_th) / (0.6 * size))
        img += (power * np.clip(1.2 - d, 0, 1) ** 2)[..., None]
    img += 0.02 * value_noise(width, 3, seed)[:h, :, None]
    return img.astype(np.float32)


def studio_preview(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.1, 4.2), target=(0.0, 0.25, 0.0), fov=35.0)
    d["env"] = {"type": "envmap", "bitmap": require("mitsuba").Bitmap(studio_environment()), "scale": 1.6}
    d["ground"] = {"type": "disk", "bsdf": diffuse(0.45), "to_world": T().rotate([1, 0, 0], -90).scale(6.0)}
    d["plastic"] = sphere([-1.05, 0.45, 0.0], 0.45,
                          {"type": "roughplastic", "diffuse_reflectance": rgb([0.6, 0.12, 0.1]), "alpha": 0.15})
    d["metal"] = sphere([0.0, 0.45, -0.2], 0.45, {"type": "roughconductor", "material": "Al", "alpha": 0.25})
    d["matte"] = sphere([1.05, 0.45, 0.0], 0.45, diffuse(0.75))
    return d


def sunlit_courtyard(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 3.2, 7.5), target=(0.0, 0.4, 0.0), fov=40.0)
    d["sky"] = {"type": "sunsky", "hour": 16.5, "sky_scale": 2.0, "sun_scale": 2.0,
                "to_world": T().rotate([0, 1, 0], 40)}
    d["ground"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(12),
                   "bsdf": {"type": "diffuse", "reflectance": checker_texture(0.30, 0.38, 10)}}
    for i, x in enumerate((-2.4, -0.8, 0.8, 2.4)):
        d[f"pillar{i}"] = {"type": "cylinder", "radius": 0.22, "p0": [x, 0, -1.5], "p1": [x, 2.4, -1.5],
                           "bsdf": diffuse(0.7)}
    d["block_a"] = cube([-1.2, 0.35, 0.9], [0.9, 0.7, 0.9], diffuse([0.55, 0.45, 0.35]), 25)
    d["block_b"] = cube([1.4, 0.25, 1.2], [1.2, 0.5, 0.6], diffuse([0.3, 0.4, 0.55]), -10)
    d["lintel"] = cube([0.0, 2.55, -1.5], [5.4, 0.3, 0.5], diffuse(0.65))
    return d


def marble_hall(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.4, 3.2), target=(0.0, 0.9, -2.0), fov=50.0)
    floor = {"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": bitmap_texture(marble())}
    d.update(room_box(5.0, 6.5, 3.0, floor=floor, walls=diffuse([0.75, 0.7, 0.6]),
                      back={"type": "diffuse", "reflectance": bitmap_texture(wood())}, front=3.5, closed=True))
    d["light"] = panel([0.0, 2.99, -2.0], 0.8, 0.5, [9.0, 8.5, 7.5])
    d["sphere"] = sphere([0.8, 0.5, -2.2], 0.5,
                         {"type": "roughplastic", "diffuse_reflectance": rgb([0.15, 0.3, 0.55]), "alpha": 0.1})
    d["plinth"] = cube([-0.9, 0.4, -2.6], [0.6, 0.8, 0.6], diffuse(0.8), 15)
    return d


def spot_stage(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.6, 4.0), target=(0.0, 0.5, 0.0), fov=42.0)
    d.update(room_box(8.0, 10.5, 4.0, floor={"type": "roughplastic", "alpha": 0.25, "diffuse_reflectance": rgb(0.08)},
                      walls=diffuse(0.06), front=4.5))
    d["spot"] = {"type": "spot", "intensity": rgb(60.0), "cutoff_angle": 28.0, "beam_width": 18.0,
                 "to_world": T().look_at(origin=[0.6, 3.8, 1.2], target=[0.0, 0.0, -1.0], up=[0, 1, 0])}
    d["copper"] = sphere([-0.5, 0.55, -1.0], 0.55, {"type": "roughconductor", "material": "Cu", "alpha": 0.2})
    d["cube"] = cube([0.75, 0.4, -0.7], [0.8, 0.8, 0.8], diffuse(0.8), 30)
    return d


def lamp_room(resolution: int) -> SceneDict:
    d = base(resolution, origin=(1.6, 1.7, 3.4), target=(0.0, 0.8, -1.0), fov=48.0)
    d.update(room_box(5.0, 6.0, 3.0, floor={"type": "diffuse", "reflectance": bitmap_texture(wood(seed=8))},
                      walls=diffuse([0.8, 0.65, 0.5]), front=3.6, closed=True))
    d["lamp"] = sphere_light([0.0, 1.9, -1.2], 0.14, [40.0, 32.0, 20.0])
    top = diffuse([0.5, 0.35, 0.2])
    d["table_top"] = cube([0.0, 0.75, -1.2], [1.6, 0.06, 0.9], top)
    for i, (x, z) in enumerate(((-0.72, -0.8), (0.72, -0.8), (-0.72, -1.6), (0.72, -1.6))):
        d[f"leg{i}"] = cube([x, 0.36, z], [0.06, 0.72, 0.06], top)
    d["vase"] = {"type": "cylinder", "radius": 0.09, "p0": [0.3, 0.78, -1.1], "p1": [0.3, 1.1, -1.1],
                 "bsdf": {"type": "roughplastic", "diffuse_reflectance": rgb([0.1, 0.35, 0.3]), "alpha": 0.1}}
    return d


def corridor(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.3, 1.5), target=(0.0, 1.1, -8.0), fov=55.0)
    floor = {"type": "roughplastic", "alpha": 0.12, "diffuse_reflectance": rgb([0.25, 0.25, 0.28])}
    d.update(room_box(2.4, 12.0, 2.6, floor=floor, walls=diffuse([0.7, 0.72, 0.75]), back=diffuse([0.45, 0.2, 0.15])))
    for i, z in enumerate((-1.5, -4.5, -7.5, -10.5)):
        d[f"light{i}"] = panel([0.0, 2.59, z], 0.35, 0.2, [14.0, 14.0, 12.0])
    for i, z in enumerate((-3.0, -6.0, -9.0)):
        d[f"door{i}"] = {"type": "rectangle", "bsdf": diffuse([0.35, 0.22, 0.12]),
                         "to_world": T().translate([1.19, 1.0, z]).rotate([0, 1, 0], -90).scale([0.45, 1.0, 1])}
    return d


def pastel_blocks(resolution: int) -> SceneDict:
    d = base(resolution, origin=(4.5, 4.5, 6.0), target=(0.0, 0.3, 0.0), fov=38.0)
    d["sky"] = {"type": "constant", "radiance": rgb([0.9, 0.92, 1.0])}
    d["ground"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(15), "bsdf": diffuse(0.6)}
    rng = np.random.default_rng(21)
    colours = [[0.9, 0.6, 0.6], [0.6, 0.85, 0.7], [0.6, 0.7, 0.95], [0.95, 0.9, 0.55], [0.8, 0.65, 0.9]]
    for i in range(4):
        for j in range(4):
            h = float(rng.uniform(0.3, 1.6))
            d[f"block{i}{j}"] = cube([-2.1 + 1.4 * i, h / 2, -2.1 + 1.4 * j], [0.9, h, 0.9],
                                      diffuse(colours[(i + 2 * j) % len(colours)]))
    return d


def window_light(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.6, 1.4, 2.6), target=(-0.4, 1.0, -2.0), fov=55.0)
    walls = diffuse([0.78, 0.76, 0.72])
    d.update(room_box(4.0, 7.0, 2.8, floor=diffuse([0.45, 0.4, 0.35]), walls=walls, open_left=True,
                      front=3.0, closed=True))
    w, h, depth = 2.0, 2.8, 4.0
    # the left wall, with a window 1.2 m wide and 1 m high in its middle
    for name, (z0, z1, y0, y1) in {"sill": (-3.0, depth, 0.0, 0.9), "head": (-3.0, depth, 1.9, h),
                                   "jamb_a": (-3.0, 1.4, 0.9, 1.9), "jamb_b": (2.6, depth, 0.9, 1.9)}.items():
        d[f"wall_{name}"] = {"type": "rectangle", "bsdf": walls, "to_world": T().translate(
            [-w, (y0 + y1) / 2, -(z0 + z1) / 2]).rotate([0, 1, 0], 90).scale([(z1 - z0) / 2, (y1 - y0) / 2, 1])}
    d["sky"] = {"type": "constant", "radiance": rgb([0.5, 0.65, 0.9])}      # seen through the window
    d["sun"] = {"type": "directional", "direction": [0.75, -0.55, -0.2], "irradiance": rgb([14.0, 12.5, 10.5])}
    d["sofa"] = cube([0.6, 0.3, -2.6], [1.6, 0.6, 0.7], diffuse([0.25, 0.3, 0.45]))
    return d
