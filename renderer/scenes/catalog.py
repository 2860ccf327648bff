"""Built-in scene library (Mitsuba 3 plugins only, no downloads) and XML scene loading.

The library: the training scenes (`training_scenes`), the held-out ones (`heldout`) and the
procedural family (`procedural`), listed in `SCENES`. Every built-in scene is a Python dict
for ``mi.load_dict`` made by a function of the image resolution alone (samples per pixel
are chosen at render time, never here). The library spans the cases a perceptual stopping
rule must get right: diffuse rooms, glossy and mirror inter-reflections, glass caustics,
small and large lights, indirect-only lighting, noise-masking high-frequency textures,
dark and bright exposures, plus two degenerate inputs (``allblack``, ``sky``).

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
from . import training_scenes as training
from .procedural import procedural_scene, procedural_seed
from .scene_kit import SceneDict
from .plugin_libs import mitsuba_folder, preload
from .scenefiles import check_scene_files, mitsuba_search_paths
from learning.data.variant import select_variant
from noisefeat.extras import require

logger = logging.getLogger(__name__)

DEFAULT_SCENE = "cornell"


@dataclass(frozen=True)
class SceneSpec:
    """One built-in scene: a name, a one-line description and its dict builder."""

    name: str
    description: str
    builder: Callable[[int], SceneDict] = field(repr=False)
    tags: tuple[str, ...] = ()


SCENES: dict[str, SceneSpec] = {
    s.name: s
    for s in (
        SceneSpec("cornell", "Cornell box, diffuse walls and boxes, small ceiling light", training.cornell,
                  ("diffuse",)),
        SceneSpec("cornell_dark", "Cornell box lit 25x dimmer: dark exposure, noise near black", training.cornell_dark,
                  ("diffuse", "dark")),
        SceneSpec("cornell_bright", "Cornell box lit 12x brighter: overexposed, clipping hides noise",
                  training.cornell_bright, ("diffuse", "bright")),
        SceneSpec("large_light", "Cornell box under a ceiling-wide panel light: soft shadows, low noise",
                  training.large_light, ("diffuse", "large-light")),
        SceneSpec("small_light", "Cornell box lit by a tiny bright sphere light: hard shadows, fireflies",
                  training.small_light, ("diffuse", "small-light")),
        SceneSpec("glossy", "Rough gold sphere, rough plastic box and glossy back wall in a Cornell box",
                  training.glossy, ("glossy",)),
        SceneSpec("mirrors", "Two facing mirror walls: view-dependent inter-reflections of spheres", training.mirrors,
                  ("mirror", "glossy")),
        SceneSpec("glass_caustic", "Glass sphere on the floor under a small light: refractive caustic",
                  training.glass_caustic, ("dielectric", "caustic", "small-light")),
        SceneSpec("indirect", "Light hidden on top of a shelf: the room is lit only by ceiling bounce",
                  training.indirect, ("diffuse", "indirect")),
        SceneSpec("checker", "High-frequency checkerboard textures everywhere: texture masks noise", training.checker,
                  ("textured",)),
        SceneSpec("mis_plates", "Veach MIS plates: four roughness levels x four light sizes", training.mis_plates,
                  ("glossy", "small-light", "large-light")),
        SceneSpec("env_spheres", "Diffuse, glossy and glass spheres on a ground plane under a uniform sky",
                  training.env_spheres, ("environment", "dielectric", "glossy")),
        SceneSpec("allblack", "Closed geometry with no light at all: an all-zero image (degenerate input)",
                  training.allblack, ("degenerate",)),
        SceneSpec("sky", "Constant environment and nothing else: a flat image (degenerate input)", training.sky,
                  ("degenerate", "environment")),
        # held out: never used to train or calibrate anything (renderer/scenes/heldout.py)
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


def is_builtin(name: str | os.PathLike) -> bool:
    """Whether `name` names a built-in scene (the library's or a procedural one), not a file."""
    name = os.fspath(name)
    return name in SCENES or procedural_seed(name) is not None


def is_scene_file(scene: Any) -> bool:
    """Whether `scene` is a scene file's path: a name, not a built-in one nor a loaded scene
    (what loading may need the ``noisestop`` integrator registered for)."""
    return isinstance(scene, (str, os.PathLike)) and not is_builtin(scene)


def scene_label(scene: str | os.PathLike) -> str:
    """Directory name of a scene: the built-in name, or an XML file's stem."""
    s = os.fspath(scene)
    return os.path.splitext(os.path.basename(s))[0] if s.lower().endswith(".xml") else s


def _unknown(name: str) -> ValueError:
    return ValueError(f"unknown scene {name!r}; built-in scenes: {', '.join(SCENES)}, procedural scenes "
                      "proc-0000, proc-0001, ... (or a Mitsuba 3 .xml file)")


def scene_dict(name: str, resolution: int) -> SceneDict:
    """The ``mi.load_dict`` description of built-in scene `name` at `resolution`^2 pixels."""
    seed = None if name in SCENES else procedural_seed(name)
    if name not in SCENES and seed is None:
        raise _unknown(name)
    select_variant()  # transforms need a variant
    return SCENES[name].builder(resolution) if seed is None else procedural_scene(seed, resolution)


# ----------------------------------------------------------------------------- loading

Resolution = int | tuple[int, int]


def film_size_for(resolution: Resolution, width: int, height: int) -> tuple[int, int]:
    """(W, H) for a film of width x height: N scales the long side to N, keeping the aspect."""
    if isinstance(resolution, tuple):
        return resolution
    long_side = max(width, height)
    scale = resolution / long_side
    return (max(1, round(width * scale)), max(1, round(height * scale))) if width != height else \
        (resolution, resolution)


def resize_film(scene: Any, size: tuple[int, int], x_fov: float | None = None) -> None:
    """Set the first sensor's film to `size` (W, H), in place, as Mitsuba's own scene
    parameters do (``film.size``; the sensor recomputes its projection). `x_fov`: the
    horizontal field of view (degrees) to frame the new size with (`framing_fov`); None
    keeps the sensor's. A crop window set by the file is dropped, with a warning."""
    mi = require("mitsuba")

    sensor = scene.sensors()[0]
    film = sensor.film()
    if tuple(film.crop_size()) != tuple(film.size()) or tuple(film.crop_offset()) != (0, 0):
        logger.warning("the film's crop window is dropped: the frame is resized to %dx%d", *size)
    params = mi.traverse(sensor)
    params["film.size"] = mi.ScalarVector2u(*size)
    params["film.crop_size"] = mi.ScalarVector2u(*size)
    params["film.crop_offset"] = mi.ScalarPoint2u(0, 0)
    if x_fov is not None and "x_fov" in params:
        params["x_fov"] = float(x_fov)
    params.update()


def framing_fov(sensor_props: Any, scene: Any, size: tuple[int, int]) -> float | None:
    """The horizontal field of view Mitsuba gives the first sensor for a film of `size`.

    A perspective sensor's ``fov`` is measured along its ``fov_axis`` (x, y, diagonal,
    smaller, larger; a ``focal_length`` along the diagonal) *for the film it has*, so
    changing the film's aspect changes the horizontal field unless the axis is x.
    `sensor_props` are the sensor's properties as the scene description gives them;
    Mitsuba's own ``parse_fov`` turns them into the horizontal field for the new aspect.
    None when the sensor has no field of view (orthographic, ...) or when the properties
    are not the loaded sensor's (checked on its own film size): its field is then kept.
    """
    mi = require("mitsuba")

    params = mi.traverse(scene.sensors()[0])
    if sensor_props is None or "x_fov" not in params:
        return None
    own = scene.sensors()[0].film().size()
    try:
        loaded = float(np.asarray(params["x_fov"]).ravel()[0])
        if abs(mi.parse_fov(sensor_props, float(own[0]) / float(own[1])) - loaded) > 1e-3 * max(1.0, loaded):
            logger.warning("cannot tell the first sensor's field-of-view axis: its horizontal field is kept")
            return None
        return float(mi.parse_fov(sensor_props, size[0] / size[1]))
    except (RuntimeError, ValueError) as exc:        # Mitsuba throws for out-of-range fields
        raise ValueError(f"a {size[0]}x{size[1]} film: {' '.join(str(exc).split())}") from None


def _xml_sensor_props(path: str, defines: Mapping[str, str] | None) -> Any:
    """The first sensor's properties in an XML file, `<default>`s and -D applied (None if
    Mitsuba's parser API is missing or the file declares no sensor of its own)."""
    mi = require("mitsuba")

    parser = getattr(mi, "parser", None)
    if parser is None or not hasattr(mi, "parse_fov"):
        return None
    # the search folders mi.load_file parsed it with (the file's own first); <path> in the file
    # would otherwise be added to Mitsuba's global ones for good
    previous = mi.file_resolver()
    resolver = mi.FileResolver(previous)
    resolver.prepend(os.path.dirname(path))
    mi.set_file_resolver(resolver)
    try:
        state = parser.parse_file(parser.ParserConfig(mi.variant()), path, **dict(defines or {}))
    except RuntimeError as exc:       # mi.load_file read it, so this is unexpected: keep the field
        logger.warning("%s: cannot read the sensor's field of view (%s): its horizontal field is kept",
                       path, " ".join(str(exc).split()))
        return None
    finally:
        mi.set_file_resolver(previous)
    sensors = [n for n in state.nodes if n.type == mi.ObjectType.Sensor]
    return sensors[0].props if sensors else None


def _dict_sensor_props(d: SceneDict) -> Any:
    """A built-in scene dict's sensor field-of-view properties, as Mitsuba reads them."""
    mi = require("mitsuba")

    props = mi.Properties("perspective")
    sensor = d.get("sensor", {})
    for key in ("fov", "fov_axis", "focal_length"):
        if key in sensor:
            props[key] = float(sensor[key]) if key == "fov" else str(sensor[key])
    return props


def load_scene(name_or_path: str | os.PathLike[str], resolution: Resolution | None = None,
               defines: Mapping[str, str] | None = None) -> Any:
    """Load a built-in scene by name, or any Mitsuba 3 XML file, as an ``mi.Scene``.

    `resolution` None keeps the film's own size (built-ins: 256x256); N scales the long
    side to N keeping the aspect ratio; (W, H) sets both (`resize_film`), framed
    as Mitsuba frames a film of that size under the sensor's ``fov_axis`` (`framing_fov`).
    `defines` are the file's `<default>` parameters set as `mitsuba -D key=value` sets them.
    """
    select_variant()
    mi = require("mitsuba")
    preload()          # Mitsuba's plugin libraries from its own folder, before any scene names one

    size = resolution      # checked by the render spec's row (`renderer.settings.ROW["resolution"]`)
    name_or_path = os.fspath(name_or_path)
    if is_builtin(name_or_path):
        if defines:
            raise ValueError(f"-D sets parameters of an XML scene; {name_or_path!r} is built in")
        side = 256 if size is None else max(size) if isinstance(size, tuple) else size
        d = scene_dict(name_or_path, side)
        scene = mi.load_dict(d)
        if isinstance(size, tuple) and size != (side, side):
            resize_film(scene, size, framing_fov(_dict_sensor_props(d), scene, size))
        return scene
    looks_like_file = name_or_path.lower().endswith(".xml") or os.sep in name_or_path
    if not looks_like_file and not os.path.exists(name_or_path):
        raise _unknown(name_or_path)
    path = os.path.abspath(name_or_path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"{name_or_path}: scene file not found")
    # Mitsuba reads it and every file it names: a FIFO, a device, a file over its cap is refused first
    check_scene_files(path, defines, mitsuba_search_paths(), mitsuba_folder())
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
            resize_film(scene, want, framing_fov(_xml_sensor_props(path, defines), scene, want))
        logger.info("loaded %s (film %dx%d, rendered at %dx%d)", path, own[0], own[1], *want)
    else:
        logger.info("loaded %s (%dx%d)", path, *own)
    return scene
