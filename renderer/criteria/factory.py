"""The one criterion factory: a `RenderSpec` in, a `Criterion` out, on every door (the API,
the command line, the plugin, the simulation and the evaluation)."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .contract import Criterion


def make_criterion(spec: Any, thresholds: Sequence[int | None] | None = None) -> Criterion:
    """The criterion `spec` names, built with its parameters (threshold, quantile, offset,
    model or server, exposure, tau), or `spec.criterion` itself when it is already one.
    `thresholds`: the true thresholds of a labelled reference stack (the oracle's)."""
    kind = spec.criterion
    if isinstance(kind, Criterion):
        return kind
    if kind == "uniform":
        from .uniform import UniformCriterion

        return UniformCriterion()
    if kind == "variance":
        from .variance import VarianceCriterion

        given = {} if spec.threshold is None else {"threshold": spec.threshold}   # else the criterion's own
        return VarianceCriterion(**given, quantile=spec.quantile, exposure=spec.exposure)
    if kind == "flip":
        from .flip import FlipCriterion

        return FlipCriterion(spec.threshold, exposure=spec.exposure, tau=spec.tau, tile=spec.tile_grain())
    if kind == "oracle":
        from .oracle import OracleCriterion

        if thresholds is None:
            raise ValueError("the oracle criterion needs true thresholds: give a labelled dataset or stack "
                             "of this scene as the reference")
        return OracleCriterion(thresholds)
    from .model import ModelCriterion

    if spec.server is not None:
        from ..client import RemoteModel

        url, _, name = spec.server.partition("#")
        scorer: Any = RemoteModel(url, model=name or "default", tau=spec.tau)
        if not scorer.ready():             # unreachable: ConnectionError; refused: ValueError
            raise ConnectionError(f"{spec.server}: the server answers but model {scorer.model!r} is not ready")
    else:
        from learning.models.bundle import load_model

        scorer = load_model(spec.model)
    model = ModelCriterion(scorer, exposure=spec.exposure, offset=spec.offset, tau=spec.tau)
    if spec.tile_grain() is None:
        return model
    from .flip import FlipCriterion
    from .gated import GatedCriterion

    return GatedCriterion(model, FlipCriterion(exposure=spec.exposure, tau=spec.tau, tile=spec.tile_grain()))
