"""renderer: Mitsuba scene library, block rendering, stack building, the adaptive loop, farm."""
from .blocks import BlockRenderer
from .scenes import DEFAULT_SCENE, list_scenes, load_scene
from .variant import select_variant

__all__ = ["BlockRenderer", "DEFAULT_SCENE", "list_scenes", "load_scene",
           "select_variant"]
