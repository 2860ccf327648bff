"""The criteria a render may name: the one list every door reads. A criterion declares
itself on its class (`renderer.criteria.Criterion` lists the declaration) and is added by
`declare`: from this package's modules, the entry points of ``noisestop.criteria``, or any
module imported before. Nothing heavy is imported: the command line builds its parser from it.
"""
from __future__ import annotations

import importlib
import logging
import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

logger = logging.getLogger(__name__)

#: the grains a criterion may declare (DESIGN "Decision grain")
TILE, BLOCK, BLOCK_ONLY = "tile", "block", "block-only"
GRAINS = (TILE, BLOCK, BLOCK_ONLY)
#: the entry-point group an installed package declares its criteria under
ENTRY_POINTS = "noisestop.criteria"

T = TypeVar("T", bound=type)


@dataclass(frozen=True)
class Setting:
    """How a criterion takes one row of `renderer.settings.ROWS`: its `default` and range
    [`low`, `high`] (None: the row's), its meaning for the help (`doc`), and whether giving
    it without a criterion chooses this one (`selects`: a model bundle means the model)."""

    default: Any = None
    low: float | None = None
    high: float | None = None
    doc: str = ""
    selects: bool = False


class Declared:
    """What a criterion declares on its class, all that the registry and the render spec read
    of it: the base of `renderer.criteria.Criterion`, here so that they need not import that."""

    name: str = "criterion"
    #: TILE (the tiles of blocks), BLOCK (whole blocks unless a tile is given) or BLOCK_ONLY
    grain: str = TILE
    #: the rows it takes beyond tau and exposure (a row no criterion names is every render's)
    settings: ClassVar[dict[str, Setting]] = {}
    #: it needs a labelled reference's true thresholds
    needs_thresholds: bool = False
    #: one line for the help
    summary: str = ""


_declared: dict[str, type] = {}
_loaded = False


def declare(cls: T) -> T:
    """Class decorator: register a criterion under its `name`, its declaration checked; a
    second class under a name is refused unless it is the same class re-imported."""
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{cls.__qualname__}: a criterion's name must be an identifier, got {name!r}")
    if getattr(cls, "grain", None) not in GRAINS:
        raise ValueError(f"criterion {name}: grain must be one of {', '.join(GRAINS)}, got {cls.grain!r}")
    settings = getattr(cls, "settings", None)
    if not isinstance(settings, Mapping) or not all(isinstance(k, str) and isinstance(s, Setting)
                                                    for k, s in settings.items()):
        raise ValueError(f"criterion {name}: settings must map row names to Setting, got {settings!r}")
    known = _declared.get(name)
    if known is not None and (known.__module__, known.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"criterion {name!r} is declared twice: {known.__module__}.{known.__qualname__} and "
                         f"{cls.__module__}.{cls.__qualname__}")
    _declared[name] = cls
    return cls


def declared() -> dict[str, type]:
    """Every criterion declared, by name (this package's first, in file order)."""
    _load()
    return dict(_declared)


def names() -> tuple[str, ...]:
    """The criteria's names, as ``--criterion`` and the plugin's ``criterion`` offer them."""
    return tuple(declared())


def criterion_class(name: str) -> type:
    """The class declared as `name`; ValueError naming the criteria there are."""
    found = declared().get(name)
    if found is None:
        raise ValueError(f"criterion must be one of {', '.join(names())} or a Criterion, got {name!r}")
    return found


def _load() -> None:
    """Import this package's modules and the entry points once (a broken entry point is logged, left out)."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    package = importlib.import_module(__package__)
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        importlib.import_module(f"{__package__}.{info.name}")
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINTS):
        try:
            found = ep.load()
        except Exception as exc:  # an installed package's bug must not break every render
            logger.warning("criterion entry point %s could not be loaded: %s", ep.name, exc)
            continue
        if isinstance(found, type) and found not in _declared.values():
            declare(found)
