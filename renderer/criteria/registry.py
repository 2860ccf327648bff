"""The criteria a render may name: each declares itself in its own file, and this registry
is the one list the render spec, the command line, the plugin and the factory read.

A criterion is a `renderer.criteria.Criterion` subclass decorated with `declare`; its
declaration is on the class, as scikit-learn keeps an estimator's `_parameter_constraints`
on the estimator: `name` (what ``--criterion`` and the plugin's ``criterion`` property
say), `grain` (`TILE`: it judges the tiles of blocks; `BLOCK`: whole blocks unless a tile
is given; `BLOCK_ONLY`: whole blocks always), `settings` (the render spec's rows it takes,
each a `Setting`: its default and range for this criterion, where the row's own do not
do), `needs_thresholds` (a labelled reference's true thresholds), `summary` (one line for
the help) and `from_spec` (how it is built from a resolved `renderer.spec.RenderSpec`).
Nothing else knows what criteria there are.

Where the declarations come from: every module of this package (found by listing it, so
a new one is one file), the entry points of the group ``noisestop.criteria`` (an
installed package's criterion, for every door, the command line included), and any module
that declares one when it is imported (a test's). This module imports nothing heavy:
the command line builds its parser from it.
"""
from __future__ import annotations

import importlib
import logging
import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

logger = logging.getLogger(__name__)

#: the grains a criterion may declare (DESIGN "Decision grain")
TILE, BLOCK, BLOCK_ONLY = "tile", "block", "block-only"
GRAINS = (TILE, BLOCK, BLOCK_ONLY)
#: the entry-point group an installed package declares its criteria under
ENTRY_POINTS = "noisestop.criteria"

T = TypeVar("T", bound=type)


@dataclass(frozen=True)
class Setting:
    """How a criterion takes one render setting (a row of `renderer.settings.ROWS`, by name):
    its `default` for this criterion (None: the row's), a narrower range [`low`, `high`]
    (None: the row's), what the setting means to it (`doc`, for the help), and whether
    giving the setting without a criterion chooses this criterion (`selects`: a model
    bundle means the model criterion)."""

    default: Any = None
    low: float | None = None
    high: float | None = None
    doc: str = ""
    selects: bool = False


class Declared(Protocol):
    """What the render spec reads of a criterion, a class or an object given ready-made
    (`renderer.criteria.Criterion`): its declaration."""

    name: str
    grain: str
    settings: Mapping[str, Setting]
    needs_thresholds: bool


_declared: dict[str, type] = {}
_loaded = False


def declare(cls: T) -> T:
    """Class decorator: add a criterion class to the registry under its `name`, its
    declaration checked (ValueError naming what is wrong). Declaring again under the same
    name replaces the earlier class only when it is the same class re-imported."""
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
    if known is not None and known is not cls and \
            (known.__module__, known.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"criterion {name!r} is declared twice: {_where(known)} and {_where(cls)}")
    _declared[name] = cls
    return cls


def _where(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


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
    """Import this package's modules (each declares its own criteria) and the entry points'
    once; an entry point that fails to load is logged and left out."""
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
