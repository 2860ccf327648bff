"""The ``noisestop`` integrator as a render sees it: its name, channels, properties, and whether
an integrator is one (`noisestop_of`); the loop reads it here, as `renderer.plugin` imports the loop."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from .settings import PLUGIN_ROWS

PLUGIN = "noisestop"
#: the channels mi.render returns, after R, G, B
AOVS = ("spp", "converged")
#: the properties it reads: the render spec's rows it offers, and whether to show progress
PROPERTIES = (*(r.name for r in PLUGIN_ROWS), "progress")
#: the integrator's class for each Mitsuba variant (`renderer.plugin.integrator_class` makes them)
CLASSES: dict[str, type] = {}


class Noisestop(Protocol):
    """What a render reads of a ``noisestop`` integrator."""

    #: the properties set (the render spec's rows, as given)
    settings: Mapping[str, Any]
    #: the integrator the samples come from
    nested: Any

    def check(self) -> None:
        """ValueError (one line) if a property was bad."""


def noisestop_of(integrator: Any) -> Noisestop | None:
    """`integrator` if it is a ``noisestop`` integrator (of any variant), else None."""
    return integrator if CLASSES and isinstance(integrator, tuple(CLASSES.values())) else None
