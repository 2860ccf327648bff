"""The training library of built-in scenes (`catalog.SCENES` lists and describes them)."""
from __future__ import annotations

from .scene_kit import SceneDict, T, base, checker_texture, diffuse, rgb, sphere, sphere_light


CB_WHITE = [0.885809, 0.698859, 0.666422]
CB_RED = [0.570068, 0.0430135, 0.0443706]
CB_GREEN = [0.105421, 0.37798, 0.076425]
CB_LIGHT = [18.387, 13.9873, 6.75357]


def _room(resolution: int, floor: dict | None = None, back: dict | None = None, left: dict | None = None,
          right: dict | None = None) -> SceneDict:
    """`base` and the five walls of the [-1, 1]^3 Cornell room (open towards the camera at +z)."""
    return {
        **base(resolution),
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
                  "bsdf": floor or diffuse(CB_WHITE)},
        "ceiling": {"type": "rectangle", "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], 90),
                    "bsdf": diffuse(CB_WHITE)},
        "back": {"type": "rectangle", "to_world": T().translate([0, 0, -1]),
                 "bsdf": back or diffuse(CB_WHITE)},
        "left": {"type": "rectangle", "to_world": T().translate([-1, 0, 0]).rotate([0, 1, 0], 90),
                 "bsdf": left or diffuse(CB_RED)},
        "right": {"type": "rectangle", "to_world": T().translate([1, 0, 0]).rotate([0, 1, 0], -90),
                  "bsdf": right or diffuse(CB_GREEN)},
    }


def _ceiling_light(radiance: float | list[float], sx: float = 0.23, sz: float = 0.19) -> dict:
    """Downward-facing rectangular area light just under the ceiling."""
    return {
        "type": "rectangle",
        "to_world": T().translate([0, 0.99, 0.01]).rotate([1, 0, 0], 90).scale([sx, sz, 1]),
        "bsdf": diffuse(CB_WHITE),
        "emitter": {"type": "area", "radiance": rgb(radiance)},
    }


def _boxes() -> SceneDict:
    return {
        "small_box": {"type": "cube",
                      "to_world": T().translate([0.335, -0.7, 0.38]).rotate([0, 1, 0], -17).scale(0.3),
                      "bsdf": diffuse(CB_WHITE)},
        "tall_box": {"type": "cube",
                     "to_world": T().translate([-0.33, -0.4, -0.28]).rotate([0, 1, 0], 17.5).scale([0.3, 0.61, 0.3]),
                     "bsdf": diffuse(CB_WHITE)},
    }


def _cornell_like(resolution: int, light: dict) -> SceneDict:
    """The Cornell room and its two boxes under `light`."""
    return {**_room(resolution), "light": light, **_boxes()}


def cornell(resolution: int) -> SceneDict:
    return _cornell_like(resolution, _ceiling_light(CB_LIGHT))


def cornell_dark(resolution: int) -> SceneDict:
    return _cornell_like(resolution, _ceiling_light([c * 0.04 for c in CB_LIGHT]))


def cornell_bright(resolution: int) -> SceneDict:
    return _cornell_like(resolution, _ceiling_light([c * 12.0 for c in CB_LIGHT]))


def large_light(resolution: int) -> SceneDict:
    return _cornell_like(resolution, _ceiling_light([c * 0.075 for c in CB_LIGHT], sx=0.85, sz=0.85))


def small_light(resolution: int) -> SceneDict:
    return _cornell_like(resolution, sphere_light([0.0, 0.85, 0.0], 0.025, [1400.0, 1100.0, 700.0]))


def glossy(resolution: int) -> SceneDict:
    d = _room(resolution, back={"type": "roughplastic", "diffuse_reflectance": rgb(CB_WHITE), "alpha": 0.08})
    d["light"] = _ceiling_light(CB_LIGHT)
    d["gold_sphere"] = sphere([0.4, -0.6, 0.25], 0.4, {"type": "roughconductor", "material": "Au", "alpha": 0.15})
    d["plastic_box"] = {"type": "cube",
                        "to_world": T().translate([-0.4, -0.45, -0.3]).rotate([0, 1, 0], 20).scale([0.3, 0.55, 0.3]),
                        "bsdf": {"type": "roughplastic", "diffuse_reflectance": rgb([0.1, 0.2, 0.6]), "alpha": 0.05}}
    return d


def mirrors(resolution: int) -> SceneDict:
    mirror = {"type": "conductor"}  # material 'none': a perfect mirror
    d = _room(resolution)
    d["light"] = _ceiling_light([c * 0.4 for c in CB_LIGHT], sx=0.4, sz=0.3)
    # facing mirrors on the side walls: the spheres repeat down a view-dependent hall of reflections
    d["mirror_left"] = {"type": "rectangle", "bsdf": mirror,
                        "to_world": T().translate([-0.98, -0.2, -0.2]).rotate([0, 1, 0], 90).scale([0.7, 0.55, 1])}
    d["mirror_right"] = {"type": "rectangle", "bsdf": mirror,
                         "to_world": T().translate([0.98, -0.2, -0.2]).rotate([0, 1, 0], -90).scale([0.7, 0.55, 1])}
    d["diffuse_sphere"] = sphere([-0.3, -0.65, 0.1], 0.35, diffuse([0.2, 0.3, 0.8]))
    d["steel_sphere"] = sphere([0.4, -0.7, -0.35], 0.3, {"type": "roughconductor", "material": "Cr", "alpha": 0.05})
    return d


def glass_caustic(resolution: int) -> SceneDict:
    d = _room(resolution)
    d["light"] = sphere_light([0.0, 0.8, 0.0], 0.06, [220.0, 180.0, 120.0])
    d["glass_sphere"] = sphere([0.0, -0.55, 0.1], 0.45, {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0})
    return d


def indirect(resolution: int) -> SceneDict:
    d = _room(resolution)
    # cove lighting: a light facing up on a shelf the camera sees from below; the ceiling's bounce lights the room
    d["shelf"] = {"type": "rectangle",
                  "to_world": T().translate([0, 0.6, -0.2]).rotate([1, 0, 0], 90).scale([0.75, 0.55, 1]),
                  "bsdf": diffuse(0.7)}
    d["light"] = {"type": "rectangle",
                  "to_world": T().translate([0, 0.605, -0.2]).rotate([1, 0, 0], -90).scale([0.7, 0.5, 1]),
                  "emitter": {"type": "area", "radiance": rgb([5.0, 4.2, 3.2])}}
    d.update(_boxes())
    return d


def checker(resolution: int) -> SceneDict:
    def tex(c0: float | list[float], c1: float | list[float], scale: float) -> dict:
        return {"type": "diffuse", "reflectance": checker_texture(c0, c1, scale)}

    d = _room(resolution, floor=tex(0.1, 0.8, 12), back=tex([0.7, 0.7, 0.2], [0.2, 0.2, 0.6], 20),
              left=tex(CB_RED, 0.8, 8), right=tex(CB_GREEN, 0.8, 8))
    d["light"] = _ceiling_light(CB_LIGHT, sx=0.35, sz=0.3)
    d["sphere"] = sphere([0.35, -0.6, 0.2], 0.4, tex(0.05, 0.9, 24))
    d["box"] = {"type": "cube",
                "to_world": T().translate([-0.4, -0.45, -0.3]).rotate([0, 1, 0], 20).scale([0.3, 0.55, 0.3]),
                "bsdf": tex([0.9, 0.5, 0.1], 0.1, 6)}
    return d


def _facing(p: list[float], a: list[float], b: list[float]) -> list[float]:
    """Point a plate at `p` would look at so that it mirrors `a` into `b` (half vector)."""
    def unit(v: list[float]) -> list[float]:
        n = sum(x * x for x in v) ** 0.5
        return [x / n for x in v]
    ua = unit([ai - pi for ai, pi in zip(a, p)])
    ub = unit([bi - pi for bi, pi in zip(b, p)])
    h = unit([x + y for x, y in zip(ua, ub)])
    return [pi + hi for pi, hi in zip(p, h)]


def mis_plates(resolution: int) -> SceneDict:
    cam = [0.0, 2.0, 15.0]
    d = base(resolution, origin=tuple(cam), target=(0.0, -1.8, 2.0), fov=30.0)
    d["floor"] = {"type": "rectangle", "to_world": T().translate([0, -4.5, 0]).rotate([1, 0, 0], -90).scale(20),
                  "bsdf": diffuse(0.3)}
    d["backdrop"] = {"type": "rectangle", "to_world": T().translate([0, 0, -4]).scale(20), "bsdf": diffuse(0.3)}
    light_y, light_z = 2.5, -1.5
    plates = [(-3.6, 3.9, 0.20), (-2.5, 2.7, 0.08), (-1.4, 1.5, 0.03), (-0.3, 0.3, 0.005)]
    for i, (y, z, alpha) in enumerate(plates):
        centre = [0.0, y, z]
        aim = _facing(centre, cam, [0.0, light_y, light_z])
        d[f"plate{i}"] = {"type": "rectangle",
                          "to_world": T().look_at(origin=centre, target=aim, up=[0, 1, 0]).scale([4.0, 0.5, 1]),
                          "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": alpha}}
    lights = [(-3.0, 0.04, 600.0), (-1.0, 0.12, 70.0), (1.0, 0.35, 8.0), (3.0, 0.8, 1.5)]
    for i, (x, r, L) in enumerate(lights):
        d[f"light{i}"] = sphere_light([x, light_y, light_z], r, L)
    return d


def env_spheres(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.2, 5.0), target=(0.0, 0.0, 0.0))
    d["sky"] = {"type": "constant", "radiance": rgb([0.6, 0.75, 1.0])}
    d["ground"] = {"type": "rectangle", "to_world": T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(8),
                   "bsdf": diffuse(0.5)}
    d["s_diffuse"] = sphere([-1.1, 0.0, 0.0], 0.5, diffuse([0.8, 0.3, 0.2]))
    d["s_glossy"] = sphere([0.0, 0.0, 0.0], 0.5,
                           {"type": "roughplastic", "diffuse_reflectance": rgb([0.2, 0.6, 0.3]), "alpha": 0.1})
    d["s_glass"] = sphere([1.1, 0.0, 0.0], 0.5, {"type": "dielectric", "int_ior": 1.5})
    return d


def allblack(resolution: int) -> SceneDict:
    # geometry but no emitter at all: every path carries zero radiance
    return {**_room(resolution), **_boxes()}


def sky(resolution: int) -> SceneDict:
    # nothing else: a flat, noise-free image
    return {**base(resolution), "sky": {"type": "constant", "radiance": rgb(0.5)}}
