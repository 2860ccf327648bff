"""The real-scene suite of `bench realscenes`: published Mitsuba 3 scenes in folders beside
this package, listed with what they cover in `catalog` (SOURCES.md: origin, terms, changes)."""
from .catalog import KINDS, ROOT, SCENES, SceneInfo, scene_path

__all__ = ["KINDS", "ROOT", "SCENES", "SceneInfo", "scene_path"]
