"""Stopping criteria: the contract and the factory (`contract`), what a criterion reads
(`batch`), one module per criterion and the registry. A new criterion is one file: a
`Criterion` subclass decorated with `declare` (here, in any module imported before the
render, or an installed package's entry point in the group ``noisestop.criteria``)."""
from .batch import UnitBatch, UnitView
from .contract import (COUNTER_NAMES, EXTERNAL_COUNTER_NAMES, TIMER_NAMES, Criterion, Decision, Tally,
                       external_counters, internal_counters, make_criterion)
from .estimate import EstimateCriterion
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
