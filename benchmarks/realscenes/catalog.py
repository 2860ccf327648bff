"""The real-scene suite: published Mitsuba 3 scenes, scaled to fit the repository.

Each scene is a folder beside this module holding ``scene.xml`` (Mitsuba 3, 256x256
``hdrfilm``, ``path`` integrator, ``independent`` sampler) and the files it names, all by
paths relative to that folder. `SCENES` says what each one covers (its `SceneInfo.kinds`);
SOURCES.md says where each comes from, under which terms, and what was changed to fit.

No Mitsuba import here: the catalogue is plain data, read before any render.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: the folder holding the scenes' folders
ROOT = Path(__file__).resolve().parent

#: the kinds a scene may be tagged with
KINDS = frozenset({
    "converges",          # most tiles are expected to meet a tight threshold by 4096 spp
    "nothing-converges",  # almost no tile does by 4096 spp (light reaching the scene through glass)
    "dark",               # most of the frame is near black
    "textured",           # bitmap textures carry visible detail
    "glossy",             # rough conductors or glossy plastics dominate
    "envmap",             # lit by an environment map
    "small-emitters",     # small, very bright luminaires
    "caustics",           # light paths through (rough) glass: specular-diffuse-specular
    "diffuse",            # diffuse walls and boxes
})


@dataclass(frozen=True)
class SceneInfo:
    """One scene of the suite: its `name`, its `folder` (beside this module), the `kinds`
    of content it covers (`KINDS`) and a one-line `description`."""

    name: str
    folder: str
    kinds: tuple[str, ...]
    description: str

    @property
    def path(self) -> Path:
        """The scene's ``scene.xml``."""
        return ROOT / self.folder / "scene.xml"


SCENES: dict[str, SceneInfo] = {
    s.name: s
    for s in (
        SceneInfo("cbox", "cbox", ("converges", "diffuse"),
                  "Mitsuba's own Cornell box: diffuse walls and boxes under a ceiling light, spectral reflectances"),
        SceneInfo("leaves_status", "leaves_status", ("converges", "envmap", "glossy", "textured"),
                  "Gold ginkgo-leaf sculpture (rough conductor) on a marble plinth under a studio environment map"),
        SceneInfo("layered_shoes", "layered_shoes", ("converges", "envmap", "glossy"),
                  "A pair of glossy high-heeled shoes on a rough silver backdrop under a studio environment map"),
        SceneInfo("shelf_conductor", "shelf_conductor", ("envmap", "glossy", "textured"),
                  "Metallic fruit, elephant and tulips (rough conductors of many roughnesses) on a shelf, "
                  "textured map and marble wall"),
        SceneInfo("layered_kitchen", "layered_kitchen", ("envmap", "textured", "glossy"),
                  "Kitchen corner: textured concrete wall, wooden shelf, cups, plates and a jar, lit by a studio map"),
        SceneInfo("chandelier_cbox", "chandelier_cbox", ("nothing-converges", "caustics", "dark", "small-emitters"),
                  "Glass chandelier in a Cornell box: every light sits inside rough glass, the walls are lit "
                  "only through it (fireflies on black)"),
        SceneInfo("starlight_cbox", "starlight_cbox", ("nothing-converges", "small-emitters", "caustics"),
                  "Star-shaped glass luminaire in a Cornell box: a bright bulb behind glass over a dim glowing shell"),
        SceneInfo("flower_cbox", "flower_cbox", ("nothing-converges", "small-emitters", "caustics", "dark"),
                  "Flower-shaped glass luminaire in a Cornell box: a tiny very bright emitter inside rough glass"),
    )
}


def scene_path(name: str) -> Path:
    """The ``scene.xml`` of suite scene `name` (KeyError naming the scenes if unknown)."""
    try:
        return SCENES[name].path
    except KeyError:
        raise KeyError(f"unknown real scene {name!r}; the suite has {', '.join(SCENES)}") from None
