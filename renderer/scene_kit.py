"""Parts every scene description is built from: transforms, colours, materials, the skeleton.

Shared by the training library (`renderer.scenes`) and the held-out set
(`renderer.heldout`), so that both render with the same integrator, film and sampler
settings (see `renderer.scenes` for why each setting is what it is).
"""
from __future__ import annotations

from typing import Any

MAX_DEPTH = 8

SceneDict = dict[str, Any]

def T() -> Any:
    import mitsuba as mi

    return mi.ScalarTransform4f()


def rgb(v: float | list[float]) -> dict:
    vals = [float(v)] * 3 if isinstance(v, (int, float)) else [float(x) for x in v]
    return {"type": "rgb", "value": vals}


def diffuse(v: float | list[float]) -> dict:
    return {"type": "diffuse", "reflectance": rgb(v)}


def checker_texture(c0: float | list[float], c1: float | list[float], scale: float) -> dict:
    import mitsuba as mi

    return {
        "type": "checkerboard",
        "color0": rgb(c0),
        "color1": rgb(c1),
        "to_uv": mi.ScalarTransform3f().scale([scale, scale]),
    }


def base(
    resolution: int,
    origin: tuple[float, float, float] = (0.0, 0.0, 3.9),
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
    up: tuple[float, float, float] = (0.0, 1.0, 0.0),
    fov: float = 39.3077,
) -> SceneDict:
    """Scene skeleton: path integrator, perspective camera, box-filtered hdrfilm."""
    if not isinstance(resolution, int) or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH},
        "sensor": {
            "type": "perspective",
            "fov_axis": "smaller",
            "fov": fov,
            "near_clip": 0.001,
            "far_clip": 100.0,
            "to_world": T().look_at(origin=list(origin), target=list(target), up=list(up)),
            "sampler": {"type": "independent", "sample_count": 16},
            "film": {
                "type": "hdrfilm",
                "width": resolution,
                "height": resolution,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
                "component_format": "float32",
            },
        },
    }
