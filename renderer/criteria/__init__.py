"""Stopping criteria: the contract (`contract`) and what it reads (`batch`), one module per
criterion, each declaring itself (`registry`), and the factory.

* `ModelCriterion` (`model`): a learned model, in this process or on a verdict server;
  at tile grain `GatedCriterion` (`gated`): its block verdict gates flip's tile verdicts.
* `FlipCriterion` (`flip`): training-free FLIP between the two half buffers.
* `EstimateCriterion` (`estimate`): flip's history corrected per tile by a learned
  estimate of the observer's error.
* `VarianceCriterion` (`variance`): Blender Cycles' adaptive-sampling pixel test.
* `OracleCriterion` (`oracle`): a labelled stack's true thresholds (the best stops).
* `UniformCriterion` (`uniform`): never stops (the baseline).

A new criterion is one file: a `Criterion` subclass with its declaration, decorated with
`declare` (in this package, or anywhere imported before the render, or an installed
package's entry point in the group ``noisestop.criteria``). `make_criterion(spec)` builds
the one a `renderer.spec.RenderSpec` names; `criterion_names()` lists them.
"""
from .batch import UnitBatch, UnitView
from .contract import (COUNTER_NAMES, EXTERNAL_COUNTER_NAMES, TIMER_NAMES, Criterion, Decision, Tally,
                       external_counters, internal_counters)
from .estimate import EstimateCriterion
from .factory import make_criterion
from .flip import FlipCriterion
from .gated import GatedCriterion
from .model import ModelCriterion, ScoresBlocks
from .oracle import OracleCriterion
from .registry import BLOCK, BLOCK_ONLY, TILE, Setting, declare
from .registry import names as criterion_names
from .uniform import UniformCriterion
from .variance import VarianceCriterion

__all__ = ["COUNTER_NAMES", "EXTERNAL_COUNTER_NAMES", "external_counters", "internal_counters", "TIMER_NAMES",
           "UnitBatch", "UnitView", "Criterion", "Decision", "Tally", "make_criterion", "EstimateCriterion",
           "FlipCriterion", "GatedCriterion", "ModelCriterion", "ScoresBlocks", "OracleCriterion",
           "UniformCriterion", "VarianceCriterion", "BLOCK", "BLOCK_ONLY", "TILE", "Setting", "declare",
           "criterion_names"]
