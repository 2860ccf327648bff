"""Seeded procedural training scenes: the same scene from the same seed on every machine,
different scenes from different seeds, names and ranges parsed strictly."""
from __future__ import annotations

import json

import numpy as np
import pytest

from renderer.scenes.procedural import (expand_procedural, procedural_name, procedural_scene,
                                 procedural_seed)
from renderer.scenes.catalog import load_scene, scene_dict
from learning.data.variant import select_variant


def _plain(d):
    """A scene dict as comparable JSON (transforms and bitmaps by their numbers)."""
    def conv(o):
        if isinstance(o, dict):
            return {k: conv(v) for k, v in o.items()}
        if hasattr(o, "matrix"):
            return np.asarray(o.matrix).round(9).tolist()
        if type(o).__name__ == "Bitmap":
            return np.asarray(o).round(6).tolist()
        return o
    return json.dumps(conv(d), sort_keys=True, default=str)


def test_names_and_ranges():
    assert procedural_name(42) == "proc-0042" and procedural_seed("proc-0042") == 42
    assert procedural_seed("cornell") is None and procedural_seed("proc-") is None
    assert expand_procedural("procedural:3") == ["proc-0000", "proc-0001", "proc-0002"]
    assert expand_procedural("procedural:5-7") == ["proc-0005", "proc-0006"]
    assert expand_procedural("cornell") is None
    for bad in ("procedural:", "procedural:x", "procedural:7-5", "procedural:0"):
        with pytest.raises(ValueError, match="procedural"):
            expand_procedural(bad)


def test_same_seed_same_scene_other_seed_other_scene():
    select_variant()
    a, b = _plain(procedural_scene(7, 64)), _plain(procedural_scene(7, 64))
    assert a == b
    others = {_plain(procedural_scene(s, 64)) for s in range(8, 14)}
    assert a not in others and len(others) == 6
    assert _plain(scene_dict("proc-0007", 64)) == a


def test_the_family_spans_rooms_open_scenes_and_materials():
    select_variant()
    kinds, lights = set(), set()
    for s in range(40):
        d = procedural_scene(s, 32)
        kinds.add("open" if "sky" in d else "room")
        for v in d.values():
            if isinstance(v, dict):
                bsdf = v.get("bsdf") or {}
                kinds.add(bsdf.get("type", ""))
                if "emitter" in v:
                    lights.add(v["type"])
            if isinstance(v, dict) and v.get("type") in ("constant", "envmap", "sunsky"):
                lights.add(v["type"])
    assert {"room", "open", "diffuse", "roughplastic", "roughconductor"} <= kinds
    assert {"dielectric", "roughdielectric"} & kinds and "conductor" in kinds
    assert {"rectangle", "sphere", "constant", "envmap", "sunsky"} <= lights


def test_bad_seed_is_refused():
    with pytest.raises(ValueError, match="seed"):
        procedural_scene(-1, 64)


@pytest.mark.slow
def test_a_procedural_scene_loads_and_renders():
    """A zoomed scene (seed 1: zoom 2) renders its 32x32 window, not the whole frame."""
    from renderer.live.blocks import BlockRenderer

    assert procedural_scene(1, 32)["sensor"]["film"]["width"] == 64
    br = BlockRenderer(load_scene("proc-0001", resolution=32), grid=(1, 1))
    assert (br.width, br.height) == (32, 32)
    img = br.render_full(4, 0)
    assert img.shape == (32, 32, 3) and np.isfinite(img).all() and img.mean() > 0


def test_a_zoomed_scene_is_a_window_of_a_larger_frame():
    """Content scale: some scenes are an R x R crop window of a frame 2-4x larger, the
    window inside the frame; the others are the whole R x R frame."""
    select_variant()
    zooms = set()
    for s in range(30):
        film = procedural_scene(s, 16)["sensor"]["film"]
        zoom = film["width"] // 16
        zooms.add(zoom)
        assert film["width"] == film["height"] == 16 * zoom
        if zoom == 1:
            assert "crop_width" not in film
        else:
            assert film["crop_width"] == film["crop_height"] == 16
            assert 0 <= film["crop_offset_x"] <= film["width"] - 16
            assert 0 <= film["crop_offset_y"] <= film["height"] - 16
    assert zooms == {1, 2, 3, 4}
    with pytest.raises(ValueError, match="resolution"):
        procedural_scene(1, 0)
