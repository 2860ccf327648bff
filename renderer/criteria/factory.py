"""The one criterion factory: a `RenderSpec` in, a `Criterion` out, on every door (the API,
the command line, the plugin, the simulation and the evaluation). It knows no criterion:
it builds the one the registry declares under the spec's name (`renderer.criteria.registry`)."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from .contract import Criterion
from .registry import criterion_class

if TYPE_CHECKING:
    from ..spec import RenderSpec


def make_criterion(spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
    """The criterion `spec` names, built by its declaration (`Criterion.from_spec`), or
    `spec.criterion` itself when it is already one. `thresholds`: the true thresholds of a
    labelled reference stack (what a criterion that `needs_thresholds` reads)."""
    if isinstance(spec.criterion, Criterion):
        return spec.criterion
    return criterion_class(spec.criterion).from_spec(spec, thresholds)
