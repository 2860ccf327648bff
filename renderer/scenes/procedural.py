"""Seeded procedural scenes (`proc-0042` is seed 42, the same on every machine): as many training
views as the render budget buys, where the fourteen hand-built ones are too few and too alike.

A seed draws a room or an open scene, two to six objects of varied materials, lights from tiny
to large or an environment, albedos and an exposure; weighted so that most blocks converge within
2048 spp (glass only under broad light; docs/guide/training.md). A scene at resolution R is an
R x R crop window, at a seeded place, of a frame `zoom` = 1 to 4 times larger: a block shows part
of a view at the scales of larger frames, for the window's cost.
"""
from __future__ import annotations

import math
import re

import numpy as np

from .scene_kit import (SceneDict, T, base, bitmap_texture, checker_texture, cube, diffuse, panel, rgb,
                        room_box, sphere, sphere_light, value_noise)
from noisefeat.extras import require

PREFIX = "proc-"
_NAME = re.compile(rf"^{PREFIX}(\d{{1,6}})$")
_METALS = ("Au", "Cu", "Al", "Ag", "Cr")


def procedural_name(seed: int) -> str:
    return f"{PREFIX}{seed:04d}"


def procedural_seed(name: str) -> int | None:
    """The seed of a procedural scene name ('proc-0042' -> 42), None for any other name."""
    m = _NAME.match(name)
    return int(m.group(1)) if m else None


def expand_procedural(spec: str) -> list[str] | None:
    """'procedural:N' -> the first N scene names, 'procedural:A-B' -> seeds A..B-1; None if
    `spec` is not of that form. Raises ValueError for a malformed count."""
    if not spec.startswith("procedural:"):
        return None
    m = re.fullmatch(r"(\d+)(?:-(\d+))?", spec.split(":", 1)[1])
    if not m:
        raise ValueError(f"{spec!r}: expected procedural:N or procedural:A-B (seeds A..B-1)")
    a, b = (0, int(m.group(1))) if m.group(2) is None else (int(m.group(1)), int(m.group(2)))
    if not 0 <= a < b <= 1_000_000:
        raise ValueError(f"{spec!r}: need 0 <= A < B <= 1000000")
    return [procedural_name(s) for s in range(a, b)]


def _colour(rng: np.random.Generator, lo: float, hi: float) -> list[float]:
    """An albedo of random hue with mean level in [lo, hi]."""
    level = rng.uniform(lo, hi)
    tint = rng.dirichlet(np.ones(3) * rng.choice([1.5, 6.0, 40.0])) * 3
    return [float(np.clip(level * t, 0.01, 0.95)) for t in tint]


def _material(rng: np.random.Generator, kind: str, seed: int) -> dict:
    if kind == "diffuse":
        return diffuse(_colour(rng, 0.03, 0.9))
    if kind == "textured":
        if rng.random() < 0.5:
            return {"type": "diffuse", "reflectance": checker_texture(
                _colour(rng, 0.05, 0.4), _colour(rng, 0.4, 0.9), float(rng.uniform(2, 24)))}
        n = value_noise(128, int(rng.integers(2, 6)), seed)
        a, b = np.array(_colour(rng, 0.05, 0.4)), np.array(_colour(rng, 0.4, 0.9))
        stripes = 0.5 + 0.5 * np.sin(np.linspace(0, rng.uniform(4, 60), 128)[None, :] + rng.uniform(2, 12) * n)
        mix = (stripes if rng.random() < 0.5 else n)[..., None]
        return {"type": "diffuse", "reflectance": bitmap_texture((a + (b - a) * mix).astype(np.float32))}
    if kind == "glossy":
        return {"type": "roughplastic", "diffuse_reflectance": rgb(_colour(rng, 0.05, 0.8)),
                "alpha": float(rng.uniform(0.05, 0.4))}
    if kind == "metal":
        return {"type": "roughconductor", "material": str(rng.choice(_METALS)),
                "alpha": float(rng.uniform(0.08, 0.5))}
    if kind == "mirror":
        return {"type": "conductor"}
    if kind == "glass":
        if rng.random() < 0.5:
            return {"type": "roughdielectric", "alpha": float(rng.uniform(0.05, 0.3))}
        return {"type": "dielectric"}
    raise ValueError(kind)


def _objects(rng: np.random.Generator, seed: int, area: tuple[float, float, float, float],
             broad_light: bool) -> SceneDict:
    """Two to six objects standing on the floor inside area (x0, x1, z0, z1)."""
    kinds = ["diffuse", "textured", "glossy", "metal", "mirror"] + (["glass"] if broad_light else [])
    weights = np.array([0.3, 0.2, 0.2, 0.15, 0.05] + ([0.1] if broad_light else []))
    out: SceneDict = {}
    x0, x1, z0, z1 = area
    for i in range(int(rng.integers(2, 7))):
        bsdf = _material(rng, str(rng.choice(kinds, p=weights / weights.sum())), seed * 100 + i)
        x, z, s = float(rng.uniform(x0, x1)), float(rng.uniform(z0, z1)), float(rng.uniform(0.2, 0.7))
        shape = rng.choice(["sphere", "cube", "cylinder"])
        if shape == "sphere":
            out[f"obj{i}"] = sphere([x, s, z], s, bsdf)
        elif shape == "cube":
            h = s * float(rng.uniform(0.8, 3.0))
            out[f"obj{i}"] = cube([x, h / 2, z], [2 * s, h, 2 * s * float(rng.uniform(0.5, 1.5))], bsdf,
                                  float(rng.uniform(0, 90)))
        else:
            out[f"obj{i}"] = {"type": "cylinder", "radius": s * 0.6, "p0": [x, 0, z],
                              "p1": [x, s * float(rng.uniform(1, 4)), z], "bsdf": bsdf}
    return out


def _sky_map(rng: np.random.Generator, seed: int, width: int = 128) -> np.ndarray:
    """Equirectangular sky: horizon-to-zenith gradient, soft clouds and a bright sun blob."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * math.pi
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    zenith, horizon = np.array(_colour(rng, 0.2, 0.8)), np.array(_colour(rng, 0.4, 0.9))
    t = np.clip(np.cos(th), 0, 1)[..., None]
    img = horizon + (zenith - horizon) * t
    img = img * (0.6 + 0.4 * value_noise(width, 3, seed)[:h, :, None])
    img[th > math.pi / 2] *= 0.3                                 # below the horizon
    sun_th, sun_ph = rng.uniform(0.3, 1.3), rng.uniform(0, 2 * math.pi)
    size = rng.uniform(0.05, 0.4)
    d = np.hypot((ph - sun_ph) / size, (th - sun_th) / size)
    img += (rng.uniform(5, 60) * np.clip(1.0 - d, 0, 1) ** 2)[..., None]
    return img.astype(np.float32)


def _room_scene(rng: np.random.Generator, seed: int, resolution: int, gain: float) -> SceneDict:
    w, dep, h = float(rng.uniform(3, 6)), float(rng.uniform(4, 8)), float(rng.uniform(2.4, 3.5))
    front = dep / 2
    eye = [float(rng.uniform(-w / 4, w / 4)), float(rng.uniform(0.8, h - 0.5)), front - 0.3]
    target = [float(rng.uniform(-w / 4, w / 4)), float(rng.uniform(0.3, 1.2)), float(rng.uniform(-front, 0))]
    d = base(resolution, origin=tuple(eye), target=tuple(target), fov=float(rng.uniform(20, 65)))
    walls = _material(rng, str(rng.choice(["diffuse", "diffuse", "textured"])), seed * 100 + 90)
    floor = _material(rng, str(rng.choice(["diffuse", "textured", "glossy"])), seed * 100 + 91)
    d.update(room_box(w, dep, h, floor=floor, walls=walls, front=front, closed=bool(rng.random() < 0.5)))
    n_lights = int(rng.integers(1, 4))
    total_area = 0.0
    for i in range(n_lights):
        # half-size from tiny (3 cm) to large (1.5 m), log-uniform; constant power per light
        s = float(np.exp(rng.uniform(math.log(0.03), math.log(1.5))))
        total_area += s * s
        power = gain * float(rng.uniform(10, 40)) / n_lights
        colour = np.array(_colour(rng, 0.8, 1.0))
        if rng.random() < 0.65:
            sx, sz = s, s * float(rng.uniform(0.5, 1.5))
            rad = power / (4 * sx * sz) * colour
            d[f"light{i}"] = panel([float(rng.uniform(-w / 3, w / 3)), h - 0.01,
                                    float(rng.uniform(-front + 0.5, front - 1))], sx, sz, rad.tolist())
        else:
            r = min(s, 0.4)
            rad = power / (4 * math.pi * r * r) * colour
            d[f"light{i}"] = sphere_light([float(rng.uniform(-w / 3, w / 3)), float(rng.uniform(1.0, h - 0.5)),
                                           float(rng.uniform(-front + 0.8, front - 1.5))], r, rad.tolist())
    d.update(_objects(rng, seed, (-w / 2 + 0.6, w / 2 - 0.6, -front + 0.8, front - 2.0),
                      broad_light=total_area > 0.5))
    return d


def _open_scene(rng: np.random.Generator, seed: int, resolution: int, gain: float) -> SceneDict:
    dist = float(rng.uniform(4, 9))
    angle = float(rng.uniform(0, 2 * math.pi))
    eye = [dist * math.sin(angle), float(rng.uniform(0.8, 5.0)), dist * math.cos(angle)]
    d = base(resolution, origin=tuple(eye), target=(float(rng.uniform(-1, 1)), float(rng.uniform(0.2, 1.0)), 0.0),
             fov=float(rng.uniform(15, 55)))
    env = rng.choice(["constant", "map", "sunsky"], p=[0.35, 0.4, 0.25])
    if env == "constant":
        d["sky"] = {"type": "constant", "radiance": rgb((gain * np.array(_colour(rng, 0.5, 1.0))).tolist())}
    elif env == "map":
        d["sky"] = {"type": "envmap", "bitmap": require("mitsuba").Bitmap(_sky_map(rng, seed)), "scale": gain,
                    "to_world": T().rotate([0, 1, 0], float(rng.uniform(0, 360)))}
    else:
        d["sky"] = {"type": "sunsky", "hour": float(rng.uniform(8, 17.5)), "sun_scale": gain,
                    "sky_scale": gain, "to_world": T().rotate([0, 1, 0], float(rng.uniform(0, 360)))}
    ground = _material(rng, str(rng.choice(["diffuse", "textured", "glossy"])), seed * 100 + 91)
    d["ground"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(20), "bsdf": ground}
    if rng.random() < 0.3:      # an area light seen directly, e.g. a lamp on a pole
        r = float(np.exp(rng.uniform(math.log(0.05), math.log(0.4))))
        d["lamp"] = sphere_light([float(rng.uniform(-2, 2)), float(rng.uniform(1, 3)), float(rng.uniform(-2, 2))],
                                 r, gain * float(rng.uniform(2, 20)))
    d.update(_objects(rng, seed, (-2.5, 2.5, -2.5, 2.5), broad_light=True))
    return d


#: how many times larger than the rendered window the frame is, and how often
ZOOMS, ZOOM_WEIGHTS = (1, 2, 3, 4), (0.25, 0.35, 0.2, 0.2)


def procedural_scene(seed: int, resolution: int) -> SceneDict:
    """The ``mi.load_dict`` description of procedural scene `seed`: a resolution^2 window
    of a frame `zoom` times larger (module docstring)."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"procedural scene seed must be a non-negative integer, got {seed!r}")
    if not isinstance(resolution, (int, np.integer)) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    rng = np.random.default_rng([int(seed), 0x5EED])
    # exposure: dim to bright, log-uniform over 4 stops around a well-exposed frame
    gain = float(2.0 ** rng.uniform(-2.5, 1.5))
    zoom = int(rng.choice(ZOOMS, p=ZOOM_WEIGHTS))
    frame = int(resolution) * zoom
    build = _room_scene if rng.random() < 0.55 else _open_scene
    d = build(rng, int(seed), frame, gain)
    if zoom > 1:
        x, y = (int(rng.integers(0, frame - resolution + 1)) for _ in range(2))
        d["sensor"]["film"].update(crop_offset_x=x, crop_offset_y=y, crop_width=int(resolution),
                                   crop_height=int(resolution))
    return d
