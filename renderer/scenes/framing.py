"""A loaded scene's film resized, framed as Mitsuba frames a film of that size (`load_scene`'s
(W, H) resolutions): the first sensor's field of view read from its properties."""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from noisefeat.extras import require

from .scene_kit import SceneDict

logger = logging.getLogger(__name__)

Resolution = int | tuple[int, int]


def film_size_for(resolution: Resolution, width: int, height: int) -> tuple[int, int]:
    """(W, H) for a film of width x height: N scales the long side to N, keeping the aspect."""
    if isinstance(resolution, tuple):
        return resolution
    scale = resolution / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def resize_film(scene: Any, size: tuple[int, int], x_fov: float | None = None) -> None:
    """Set the first sensor's film to `size` (W, H) in place through its scene parameters,
    framed with horizontal field `x_fov` (degrees; None keeps the sensor's). A crop window
    set by the file is dropped, with a warning."""
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
    """The horizontal field of view Mitsuba's ``parse_fov`` gives the first sensor (properties
    `sensor_props`) for a film of `size`: a ``fov`` is measured along its ``fov_axis``. None
    (kept) for a sensor without one, or properties that do not give its field for its own film."""
    mi = require("mitsuba")

    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    if sensor_props is None or "x_fov" not in params:
        return None
    own = sensor.film().size()
    try:
        loaded = float(np.asarray(params["x_fov"]).ravel()[0])
        if abs(mi.parse_fov(sensor_props, float(own[0]) / float(own[1])) - loaded) > 1e-3 * max(1.0, loaded):
            logger.warning("cannot tell the first sensor's field-of-view axis: its horizontal field is kept")
            return None
        return float(mi.parse_fov(sensor_props, size[0] / size[1]))
    except (RuntimeError, ValueError) as exc:        # Mitsuba throws for out-of-range fields
        raise ValueError(f"a {size[0]}x{size[1]} film: {' '.join(str(exc).split())}") from None


def xml_sensor_props(path: str, defines: Mapping[str, str] | None) -> Any:
    """The first sensor's properties in an XML file, `<default>`s and -D applied (None without
    Mitsuba's parser API or a sensor)."""
    mi = require("mitsuba")

    parser = getattr(mi, "parser", None)
    if parser is None or not hasattr(mi, "parse_fov"):
        return None
    # with mi.load_file's search folders (the file's own first), on a copy: a <path> in the file
    # would otherwise join Mitsuba's global ones for good
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


def dict_sensor_props(d: SceneDict) -> Any:
    """A built-in scene dict's sensor field-of-view properties, as Mitsuba reads them."""
    mi = require("mitsuba")

    props = mi.Properties("perspective")
    sensor = d.get("sensor", {})
    for key in ("fov", "fov_axis", "focal_length"):
        if key in sensor:
            props[key] = float(sensor[key]) if key == "fov" else str(sensor[key])
    return props
