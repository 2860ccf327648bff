"""Stopping criteria: the contract (`contract`), one module per criterion, and the factory.

* `ModelCriterion` (`model`): a learned model, in this process or on a verdict server;
  at tile grain `GatedCriterion` (`gated`): its block verdict gates flip's tile verdicts.
* `FlipCriterion` (`flip`): training-free FLIP between the two half buffers.
* `VarianceCriterion` (`variance`): Blender Cycles' adaptive-sampling pixel test.
* `OracleCriterion` (`oracle`): a labelled stack's true thresholds (the best stops).
* `UniformCriterion` (`uniform`): never stops (the baseline).

`make_criterion(spec)` builds the one a `renderer.spec.RenderSpec` names.
"""
from ..names import CRITERIA
from .contract import COUNTER_NAMES, TIMER_NAMES, BlockBatch, BlockView, Criterion, Decision, Tally
from .factory import make_criterion
from .flip import FlipCriterion
from .gated import GatedCriterion
from .model import ModelCriterion, ScoresBlocks
from .oracle import OracleCriterion
from .uniform import UniformCriterion
from .variance import VarianceCriterion

__all__ = ["CRITERIA", "COUNTER_NAMES", "TIMER_NAMES", "BlockBatch", "BlockView", "Criterion", "Decision",
           "Tally", "make_criterion", "FlipCriterion", "GatedCriterion", "ModelCriterion", "ScoresBlocks", "OracleCriterion",
           "UniformCriterion", "VarianceCriterion"]
