"""The built-in scene library (`SCENES`: ``mi.load_dict`` dicts made from the resolution alone,
with `scene_kit`'s shared settings) and the loading of built-in scenes and XML files."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from . import heldout
from . import training_scenes as training
from .framing import Resolution, dict_sensor_props, film_size_for, framing_fov, resize_film, xml_sensor_props
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
    """One built-in scene: a name, a one-line description, its dict builder, and whether it is
    held out (never used to train or calibrate anything)."""

    name: str
    description: str
    builder: Callable[[int], SceneDict] = field(repr=False)
    heldout: bool = False


#: (name, description); the builder is the function of that name
_TRAINING = (
    ("cornell", "Cornell box, diffuse walls and boxes, small ceiling light"),
    ("cornell_dark", "Cornell box lit 25x dimmer: dark exposure, noise near black"),
    ("cornell_bright", "Cornell box lit 12x brighter: overexposed, clipping hides noise"),
    ("large_light", "Cornell box under a ceiling-wide panel light: soft shadows, low noise"),
    ("small_light", "Cornell box lit by a tiny bright sphere light: hard shadows, fireflies"),
    ("glossy", "Rough gold sphere, rough plastic box and glossy back wall in a Cornell box"),
    ("mirrors", "Two facing mirror walls: view-dependent inter-reflections of spheres"),
    ("glass_caustic", "Glass sphere on the floor under a small light: refractive caustic"),
    ("indirect", "Light hidden on top of a shelf: the room is lit only by ceiling bounce"),
    ("checker", "High-frequency checkerboard textures everywhere: texture masks noise"),
    ("mis_plates", "Veach MIS plates: four roughness levels x four light sizes"),
    ("env_spheres", "Diffuse, glossy and glass spheres on a ground plane under a uniform sky"),
    ("allblack", "Closed geometry with no light at all: an all-zero image (degenerate input)"),
    ("sky", "Constant environment and nothing else: a flat image (degenerate input)"),
)
#: never used to train or calibrate anything (`heldout`)
_HELDOUT = (
    ("studio_preview", "Material preview: three spheres on a plane under a studio environment map"),
    ("sunlit_courtyard", "Pillars and blocks under sun and sky casting shadows on paving"),
    ("marble_hall", "Room with a marble floor, wood-grain back wall and a panel light"),
    ("spot_stage", "Dark stage lit by one spot light: a pool of light in near-black"),
    ("lamp_room", "Table under a hanging globe lamp in a warm room with a wooden floor"),
    ("corridor", "Long corridor with a row of ceiling lights and a glossy floor"),
    ("pastel_blocks", "Grid of pastel blocks under an overcast sky (ambient occlusion look)"),
    ("window_light", "Room lit through one window: a sun patch, the rest bounce light"),
)
SCENES: dict[str, SceneSpec] = {
    **{n: SceneSpec(n, d, getattr(training, n)) for n, d in _TRAINING},
    **{n: SceneSpec(n, d, getattr(heldout, n), heldout=True) for n, d in _HELDOUT},
}


def list_scenes(heldout: bool | None = None) -> list[tuple[str, str]]:
    """(name, description) of the built-in scenes in library order: all (None), the held-out
    set (True) or the training library (False)."""
    return [(s.name, s.description) for s in SCENES.values() if heldout is None or s.heldout == heldout]


def is_builtin(name: str | os.PathLike) -> bool:
    """Whether `name` names a built-in scene (the library's or a procedural one), not a file."""
    name = os.fspath(name)
    return name in SCENES or procedural_seed(name) is not None


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


def load_scene(name_or_path: str | os.PathLike[str], resolution: Resolution | None = None,
               defines: Mapping[str, str] | None = None) -> Any:
    """Load a built-in scene by name, or any Mitsuba 3 XML file, as an ``mi.Scene``.

    `resolution` (checked by its render spec row): None keeps the film's own size (built-ins:
    256x256); N scales the long side to N keeping the aspect; (W, H) sets both, framed as
    Mitsuba frames a film of that size (`framing_fov`). `defines`: the file's `<default>`
    parameters, set as ``mitsuba -D key=value`` sets them.
    """
    select_variant()
    mi = require("mitsuba")
    preload()          # Mitsuba's plugin libraries from its own folder, before any scene names one

    name_or_path = os.fspath(name_or_path)
    if is_builtin(name_or_path):
        if defines:
            raise ValueError(f"-D sets parameters of an XML scene; {name_or_path!r} is built in")
        side = 256 if resolution is None else max(resolution) if isinstance(resolution, tuple) else resolution
        d = scene_dict(name_or_path, side)
        scene = mi.load_dict(d)
        if isinstance(resolution, tuple) and resolution != (side, side):
            resize_film(scene, resolution, framing_fov(dict_sensor_props(d), scene, resolution))
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
    if resolution is None:
        logger.info("loaded %s (%dx%d)", path, *own)
        return scene
    want = film_size_for(resolution, *own)
    if want != own:
        resize_film(scene, want, framing_fov(xml_sensor_props(path, defines), scene, want))
    logger.info("loaded %s (film %dx%d, rendered at %dx%d)", path, own[0], own[1], *want)
    return scene
