"""The one criterion factory, on every door: it builds the criterion the registry declares
under a `RenderSpec`'s name, and knows none itself."""
from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from .contract import Criterion
from .registry import criterion_class

if TYPE_CHECKING:
    from ..spec import RenderSpec


def make_criterion(spec: RenderSpec, thresholds: Sequence[int | None] | None = None) -> Criterion:
    """The criterion `spec` names (or `spec.criterion` when it is one); `thresholds`: a
    labelled reference stack's true ones."""
    if isinstance(spec.criterion, Criterion):
        return spec.criterion
    return criterion_class(spec.criterion).from_spec(spec, thresholds)
