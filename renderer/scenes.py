"""Built-in scene library (Mitsuba 3 plugins only, no downloads) and XML scene loading.

Every built-in scene is a Python dict for ``mi.load_dict`` made by a function of the
image resolution alone (samples per pixel are chosen at render time, never here). The
library spans the cases a perceptual stopping rule must get right: diffuse rooms,
glossy and mirror inter-reflections, glass caustics, small and large lights,
indirect-only lighting, noise-masking high-frequency textures, dark and bright
exposures, plus two degenerate inputs (``allblack``, ``sky``).

Shared render settings, and why:

* Integrator ``path`` with ``max_depth = 8``: enough bounces for the mirror room and
  glass caustics to look right, short enough to keep every scene at about a second for
  128x128 at 64 spp on the llvm variant (2 cores).
* Film ``hdrfilm``, ``pixel_format = rgb``, float32, **``rfilter = box``**. Mitsuba
  splats every sample onto all pixels within the reconstruction filter's radius (the
  default Gaussian reaches 2 px). When only a crop window (one block) is rendered, only
  samples inside the crop exist, so with a wide filter the block's edge pixels would
  miss their neighbours' contributions and a block rendered alone would be a different
  estimator from the same block cut out of a full-frame render. The box filter (radius
  half a pixel) keeps each sample inside its own pixel: blocks are then exactly
  independent, and the stack builder and the adaptive loop may sample any subset.
* Sampler ``independent``: passes with distinct seeds are statistically independent,
  which the cumulative means and the Cycles-style half buffers rely on. Its
  ``sample_count`` is a placeholder; ``mi.render(spp=...)`` decides.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import heldout
from .procedural import procedural_scene, procedural_seed
from .scene_kit import SceneDict, T, base, checker_texture, diffuse, rgb
from learning.data.variant import select_variant

logger = logging.getLogger(__name__)

DEFAULT_SCENE = "cornell"


@dataclass(frozen=True)
class SceneSpec:
    """One built-in scene: a name, a one-line description and its dict builder."""

    name: str
    description: str
    builder: Callable[[int], SceneDict] = field(repr=False)
    tags: tuple[str, ...] = ()


CB_WHITE = [0.885809, 0.698859, 0.666422]
CB_RED = [0.570068, 0.0430135, 0.0443706]
CB_GREEN = [0.105421, 0.37798, 0.076425]
CB_LIGHT = [18.387, 13.9873, 6.75357]


def _room(
    floor: dict | None = None,
    ceiling: dict | None = None,
    back: dict | None = None,
    left: dict | None = None,
    right: dict | None = None,
) -> SceneDict:
    """The five walls of the [-1, 1]^3 Cornell room (open towards the camera at +z)."""
    return {
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
                  "bsdf": floor or diffuse(CB_WHITE)},
        "ceiling": {"type": "rectangle", "to_world": T().translate([0, 1, 0]).rotate([1, 0, 0], 90),
                    "bsdf": ceiling or diffuse(CB_WHITE)},
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


def _boxes(bsdf_small: dict | None = None, bsdf_tall: dict | None = None) -> SceneDict:
    return {
        "small_box": {"type": "cube",
                      "to_world": T().translate([0.335, -0.7, 0.38]).rotate([0, 1, 0], -17).scale(0.3),
                      "bsdf": bsdf_small or diffuse(CB_WHITE)},
        "tall_box": {"type": "cube",
                     "to_world": T().translate([-0.33, -0.4, -0.28]).rotate([0, 1, 0], 17.5).scale([0.3, 0.61, 0.3]),
                     "bsdf": bsdf_tall or diffuse(CB_WHITE)},
    }


def _cornell_like(resolution: int, light_scale: float = 1.0) -> SceneDict:
    d = base(resolution)
    d.update(_room())
    d["light"] = _ceiling_light([c * light_scale for c in CB_LIGHT])
    d.update(_boxes())
    return d


# ----------------------------------------------------------------------------- scenes


def cornell(resolution: int) -> SceneDict:
    return _cornell_like(resolution)


def cornell_dark(resolution: int) -> SceneDict:
    return _cornell_like(resolution, light_scale=0.04)


def cornell_bright(resolution: int) -> SceneDict:
    return _cornell_like(resolution, light_scale=12.0)


def large_light(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room())
    d["light"] = _ceiling_light([c * 0.075 for c in CB_LIGHT], sx=0.85, sz=0.85)
    d.update(_boxes())
    return d


def small_light(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room())
    d["light"] = {"type": "sphere", "center": [0.0, 0.85, 0.0], "radius": 0.025,
                  "emitter": {"type": "area", "radiance": rgb([1400.0, 1100.0, 700.0])}}
    d.update(_boxes())
    return d


def glossy(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room(back={"type": "roughplastic", "diffuse_reflectance": rgb(CB_WHITE), "alpha": 0.08}))
    d["light"] = _ceiling_light(CB_LIGHT)
    d["gold_sphere"] = {"type": "sphere", "center": [0.4, -0.6, 0.25], "radius": 0.4,
                        "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.15}}
    d["plastic_box"] = {"type": "cube",
                        "to_world": T().translate([-0.4, -0.45, -0.3]).rotate([0, 1, 0], 20).scale([0.3, 0.55, 0.3]),
                        "bsdf": {"type": "roughplastic", "diffuse_reflectance": rgb([0.1, 0.2, 0.6]), "alpha": 0.05}}
    return d


def mirrors(resolution: int) -> SceneDict:
    mirror = {"type": "conductor"}  # material 'none': a perfect mirror
    d = base(resolution)
    d.update(_room())
    d["light"] = _ceiling_light([c * 0.4 for c in CB_LIGHT], sx=0.4, sz=0.3)
    # Two facing mirror panels on the side walls: the spheres repeat down a hall of
    # reflections that changes with the view point.
    d["mirror_left"] = {"type": "rectangle", "bsdf": mirror,
                        "to_world": T().translate([-0.98, -0.2, -0.2]).rotate([0, 1, 0], 90).scale([0.7, 0.55, 1])}
    d["mirror_right"] = {"type": "rectangle", "bsdf": mirror,
                         "to_world": T().translate([0.98, -0.2, -0.2]).rotate([0, 1, 0], -90).scale([0.7, 0.55, 1])}
    d["diffuse_sphere"] = {"type": "sphere", "center": [-0.3, -0.65, 0.1], "radius": 0.35,
                           "bsdf": diffuse([0.2, 0.3, 0.8])}
    d["steel_sphere"] = {"type": "sphere", "center": [0.4, -0.7, -0.35], "radius": 0.3,
                         "bsdf": {"type": "roughconductor", "material": "Cr", "alpha": 0.05}}
    return d


def glass_caustic(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room())
    d["light"] = {"type": "sphere", "center": [0.0, 0.8, 0.0], "radius": 0.06,
                  "emitter": {"type": "area", "radiance": rgb([220.0, 180.0, 120.0])}}
    d["glass_sphere"] = {"type": "sphere", "center": [0.0, -0.55, 0.1], "radius": 0.45,
                         "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}}
    return d


def indirect(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room())
    # Cove lighting: an upward-facing light on top of a shelf; the camera only sees the
    # shelf's underside, the room is lit by the bounce off the ceiling.
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

    d = base(resolution)
    d.update(_room(floor=tex(0.1, 0.8, 12), back=tex([0.7, 0.7, 0.2], [0.2, 0.2, 0.6], 20),
                   left=tex(CB_RED, 0.8, 8), right=tex(CB_GREEN, 0.8, 8)))
    d["light"] = _ceiling_light(CB_LIGHT, sx=0.35, sz=0.3)
    d["sphere"] = {"type": "sphere", "center": [0.35, -0.6, 0.2], "radius": 0.4,
                   "bsdf": tex(0.05, 0.9, 24)}
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
    """Veach-style MIS test: four plates of falling roughness, four lights of rising size."""
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
        d[f"light{i}"] = {"type": "sphere", "center": [x, light_y, light_z], "radius": r,
                          "emitter": {"type": "area", "radiance": rgb(L)}}
    return d


def env_spheres(resolution: int) -> SceneDict:
    d = base(resolution, origin=(0.0, 1.2, 5.0), target=(0.0, 0.0, 0.0))
    d["sky"] = {"type": "constant", "radiance": rgb([0.6, 0.75, 1.0])}
    d["ground"] = {"type": "rectangle", "to_world": T().translate([0, -0.5, 0]).rotate([1, 0, 0], -90).scale(8),
                   "bsdf": diffuse(0.5)}
    d["s_diffuse"] = {"type": "sphere", "center": [-1.1, 0.0, 0.0], "radius": 0.5, "bsdf": diffuse([0.8, 0.3, 0.2])}
    d["s_glossy"] = {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.5,
                     "bsdf": {"type": "roughplastic", "diffuse_reflectance": rgb([0.2, 0.6, 0.3]), "alpha": 0.1}}
    d["s_glass"] = {"type": "sphere", "center": [1.1, 0.0, 0.0], "radius": 0.5,
                    "bsdf": {"type": "dielectric", "int_ior": 1.5}}
    return d


def allblack(resolution: int) -> SceneDict:
    d = base(resolution)
    d.update(_room())  # geometry but no emitter at all: every path carries zero radiance
    d.update(_boxes())
    return d


def sky(resolution: int) -> SceneDict:
    d = base(resolution)
    d["sky"] = {"type": "constant", "radiance": rgb(0.5)}  # nothing else: a flat, noise-free image
    return d


SCENES: dict[str, SceneSpec] = {
    s.name: s
    for s in (
        SceneSpec("cornell", "Cornell box, diffuse walls and boxes, small ceiling light", cornell, ("diffuse",)),
        SceneSpec("cornell_dark", "Cornell box lit 25x dimmer: dark exposure, noise near black", cornell_dark,
                  ("diffuse", "dark")),
        SceneSpec("cornell_bright", "Cornell box lit 12x brighter: overexposed, clipping hides noise",
                  cornell_bright, ("diffuse", "bright")),
        SceneSpec("large_light", "Cornell box under a ceiling-wide panel light: soft shadows, low noise",
                  large_light, ("diffuse", "large-light")),
        SceneSpec("small_light", "Cornell box lit by a tiny bright sphere light: hard shadows, fireflies",
                  small_light, ("diffuse", "small-light")),
        SceneSpec("glossy", "Rough gold sphere, rough plastic box and glossy back wall in a Cornell box",
                  glossy, ("glossy",)),
        SceneSpec("mirrors", "Two facing mirror walls: view-dependent inter-reflections of spheres", mirrors,
                  ("mirror", "glossy")),
        SceneSpec("glass_caustic", "Glass sphere on the floor under a small light: refractive caustic",
                  glass_caustic, ("dielectric", "caustic", "small-light")),
        SceneSpec("indirect", "Light hidden on top of a shelf: the room is lit only by ceiling bounce",
                  indirect, ("diffuse", "indirect")),
        SceneSpec("checker", "High-frequency checkerboard textures everywhere: texture masks noise", checker,
                  ("textured",)),
        SceneSpec("mis_plates", "Veach MIS plates: four roughness levels x four light sizes", mis_plates,
                  ("glossy", "small-light", "large-light")),
        SceneSpec("env_spheres", "Diffuse, glossy and glass spheres on a ground plane under a uniform sky",
                  env_spheres, ("environment", "dielectric", "glossy")),
        SceneSpec("allblack", "Closed geometry with no light at all: an all-zero image (degenerate input)",
                  allblack, ("degenerate",)),
        SceneSpec("sky", "Constant environment and nothing else: a flat image (degenerate input)", sky,
                  ("degenerate", "environment")),
        # held out: never used to train or calibrate anything (renderer/heldout.py)
        SceneSpec("studio_preview", "Material preview: three spheres on a plane under a studio environment map",
                  heldout.studio_preview, ("heldout", "environment", "glossy")),
        SceneSpec("sunlit_courtyard", "Pillars and blocks under sun and sky casting shadows on paving",
                  heldout.sunlit_courtyard, ("heldout", "outdoor", "textured")),
        SceneSpec("marble_hall", "Room with a marble floor, wood-grain back wall and a panel light",
                  heldout.marble_hall, ("heldout", "textured", "glossy")),
        SceneSpec("spot_stage", "Dark stage lit by one spot light: a pool of light in near-black",
                  heldout.spot_stage, ("heldout", "dark", "glossy")),
        SceneSpec("lamp_room", "Table under a hanging globe lamp in a warm room with a wooden floor",
                  heldout.lamp_room, ("heldout", "diffuse", "textured")),
        SceneSpec("corridor", "Long corridor with a row of ceiling lights and a glossy floor",
                  heldout.corridor, ("heldout", "glossy")),
        SceneSpec("pastel_blocks", "Grid of pastel blocks under an overcast sky (ambient occlusion look)",
                  heldout.pastel_blocks, ("heldout", "outdoor", "environment")),
        SceneSpec("window_light", "Room lit through one window: a sun patch, the rest bounce light",
                  heldout.window_light, ("heldout", "indirect")),
    )
}
HELDOUT = "heldout"


def list_scenes(heldout: bool | None = None) -> list[tuple[str, str]]:
    """(name, description) of the built-in scenes, in library order: all of them (None),
    only the held-out set (True) or only the training library (False)."""
    return [(s.name, s.description) for s in SCENES.values()
            if heldout is None or (HELDOUT in s.tags) == heldout]


def _unknown(name: str) -> ValueError:
    return ValueError(f"unknown scene {name!r}; built-in scenes: {', '.join(SCENES)}, procedural scenes "
                      "proc-0000, proc-0001, ... (or a Mitsuba 3 .xml file)")


def scene_dict(name: str, resolution: int) -> SceneDict:
    """The ``mi.load_dict`` description of built-in scene `name` at `resolution`^2 pixels."""
    seed = procedural_seed(name)
    if name not in SCENES and seed is None:
        raise _unknown(name)
    select_variant()  # transforms need a variant
    return SCENES[name].builder(resolution) if seed is None else procedural_scene(seed, resolution)


# ----------------------------------------------------------------------------- loading

Resolution = int | tuple[int, int]


def parse_resolution(text: str | int | Sequence[int]) -> Resolution:
    """`--resolution` as given: N (the long side; the film's aspect ratio is kept) or
    'WxH' (both sides). ValueError with the accepted forms otherwise."""
    if isinstance(text, (int, np.integer)) and not isinstance(text, bool):
        value: Resolution = int(text)
    elif isinstance(text, str):
        parts = text.lower().replace("×", "x").split("x")
        try:
            nums = [int(p) for p in parts]
        except ValueError:
            nums = []
        if len(nums) not in (1, 2):
            raise ValueError(f"resolution {text!r}: expected N (long side, aspect kept) or WxH, e.g. 512 or "
                             "1280x720")
        value = nums[0] if len(nums) == 1 else (nums[0], nums[1])
    elif isinstance(text, Sequence) and len(text) == 2:
        value = (int(text[0]), int(text[1]))
    else:
        raise ValueError(f"resolution {text!r}: expected N or WxH")
    sides = value if isinstance(value, tuple) else (value,)
    if any(v < 1 for v in sides):
        raise ValueError(f"resolution {text!r}: sides must be positive whole numbers")
    return value


def film_size_for(resolution: Resolution, width: int, height: int) -> tuple[int, int]:
    """(W, H) for a film of width x height: N scales the long side to N, keeping the aspect."""
    if isinstance(resolution, tuple):
        return resolution
    long_side = max(width, height)
    scale = resolution / long_side
    return (max(1, round(width * scale)), max(1, round(height * scale))) if width != height else \
        (resolution, resolution)


def resize_film(scene: Any, size: tuple[int, int]) -> None:
    """Set the first sensor's film to `size` (W, H), in place, as Mitsuba's own scene
    parameters do (``film.size``; the sensor recomputes its projection, keeping its
    horizontal field of view). A crop window set by the file is dropped, with a warning."""
    import mitsuba as mi

    sensor = scene.sensors()[0]
    film = sensor.film()
    if tuple(film.crop_size()) != tuple(film.size()) or tuple(film.crop_offset()) != (0, 0):
        logger.warning("the film's crop window is dropped: the frame is resized to %dx%d", *size)
    params = mi.traverse(sensor)
    params["film.size"] = mi.ScalarVector2u(*size)
    params["film.crop_size"] = mi.ScalarVector2u(*size)
    params["film.crop_offset"] = mi.ScalarPoint2u(0, 0)
    params.update()


def load_scene(name_or_path: str | os.PathLike[str], resolution: Resolution | str | None = None,
               defines: Mapping[str, str] | None = None) -> Any:
    """Load a built-in scene by name, or any Mitsuba 3 XML file, as an ``mi.Scene``.

    `resolution` None keeps the film's own size (built-ins: 256x256); N scales the long
    side to N keeping the aspect ratio; (W, H) or 'WxH' sets both (`resize_film`).
    `defines` are the file's `<default>` parameters set as `mitsuba -D key=value` sets them.
    """
    select_variant()
    import mitsuba as mi

    size = None if resolution is None else parse_resolution(resolution)
    name_or_path = os.fspath(name_or_path)
    if name_or_path in SCENES or procedural_seed(name_or_path) is not None:
        if defines:
            raise ValueError(f"-D sets parameters of an XML scene; {name_or_path!r} is built in")
        side = 256 if size is None else max(size) if isinstance(size, tuple) else size
        scene = mi.load_dict(scene_dict(name_or_path, side))
        if isinstance(size, tuple) and size != (side, side):
            resize_film(scene, size)
        return scene
    looks_like_file = name_or_path.lower().endswith(".xml") or os.sep in name_or_path
    if not looks_like_file and not os.path.exists(name_or_path):
        raise _unknown(name_or_path)
    path = os.path.abspath(name_or_path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{name_or_path}: scene file not found")
    try:
        scene = mi.load_file(path, **dict(defines or {}))
    except Exception as exc:  # Mitsuba raises RuntimeError with its parser message
        raise ValueError(f"{path}: Mitsuba could not load this scene: {exc}") from exc
    if not scene.sensors():
        raise ValueError(f"{path}: the scene has no <sensor> (camera) to render from; add one")
    film = scene.sensors()[0].film()
    own = (int(film.size()[0]), int(film.size()[1]))
    if size is not None:
        want = film_size_for(size, *own)
        if want != own:
            resize_film(scene, want)
        logger.info("loaded %s (film %dx%d, rendered at %dx%d)", path, own[0], own[1], *want)
    else:
        logger.info("loaded %s (%dx%d)", path, *own)
    return scene
