"""renderer: Mitsuba scenes, block rendering, stack building, the adaptive loop, farm.

Names load on first use (PEP 562), so `renderer.spec` and the command line do not import Mitsuba;
`register` adds the ``noisestop`` integrator (importing `renderer` does not: it chooses a variant).
"""
from __future__ import annotations

import importlib
from typing import Any

_HOMES = {"BlockRenderer": "live.blocks", "DEFAULT_SCENE": "scenes.catalog", "list_scenes": "scenes.catalog",
          "load_scene": "scenes.catalog", "adaptive_render": "live.adaptive", "render": "api",
          "RenderResult": "live.result", "register": "plugin"}
__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'renderer' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
