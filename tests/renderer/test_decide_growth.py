"""decide_growth: a unit's spp grows by at least that fraction between two of its
decisions, so a unit of thousands of spp near its target is not judged at every pass of 16;
a budget render skips and spaces decisions as the unbudgeted one does."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from renderer.live.adaptive import adaptive_render
from renderer.live.passloop import next_decision
from renderer.criteria import VarianceCriterion

TINY = {"resolution": 32, "grid": (4, 4), "step": 4, "min_spp": 4, "max_spp": 64, "progress": False}


def test_the_next_decision_is_the_later_of_the_prediction_and_the_growth_floor() -> None:
    spp = np.array([1024, 1024, 1024, 1024, 1024, 16])
    ratio = np.array([1.2, 4.0, np.nan, np.inf, 0.5, 1.0])
    # skip 0.5: 1.2 -> (0.6)^2 < 1, the floor; 4 -> (2)^2 = 4x; no estimate or infinite: the next pass
    assert next_decision(spp, ratio, 0.5, 1 / 16).tolist() == [1088, 4096, 1024, 1024, 1088, 17]
    assert next_decision(spp, ratio, 0.5, 0.0).tolist() == [1024, 4096, 1024, 1024, 1024, 16]
    assert next_decision(spp, ratio, 0.0, 0.0).tolist() == spp.tolist()            # every pass
    assert next_decision(spp, ratio, 0.0, 0.25).tolist() == [1280, 1280, 1024, 1024, 1280, 20]
    with warnings.catch_warnings():
        warnings.simplefilter("error")                  # a huge ratio reaches the clip's top quietly
        assert next_decision(np.array([2]), np.array([1e300]), 1.0, 0.5).tolist() == [2 << 20]


def _decisions(report: dict) -> list[list[int]]:
    return [[s for s, _ in b["history"]] for b in report["blocks"]]


def test_a_units_decisions_are_at_least_the_growth_apart(tmp_path) -> None:
    """With growth 1/2 every unit's next decision comes at 1.5x its spp or later (or at the
    last pass); fewer decisions than with growth 0, and the render still stops units."""
    every = adaptive_render("cornell", tmp_path / "every", VarianceCriterion(0.3), decide_skip=0.0,
                            decide_growth=0.0, **TINY)
    sparse = adaptive_render("cornell", tmp_path / "sparse", VarianceCriterion(0.3), decide_skip=0.0,
                             decide_growth=0.5, **TINY)
    assert (sparse["decide_skip"], sparse["decide_growth"]) == (0.0, 0.5)
    for spp in _decisions(sparse):
        for a, b in zip(spp, spp[1:]):
            assert b >= 1.5 * a or b == TINY["max_spp"], spp
    assert sum(map(len, _decisions(sparse))) < sum(map(len, _decisions(every)))
    assert any(b["converged"] for b in sparse["blocks"])
    # a unit stops no earlier than without the floor: the floor only delays a decision
    for b, e in zip(sparse["blocks"], every["blocks"]):
        if b["converged"] and e["converged"]:
            assert b["stop_spp"] >= e["stop_spp"]


@pytest.mark.parametrize("growth", [0.0, 0.5])
def test_a_roomy_budget_keeps_the_skip_and_growth_of_its_decisions(tmp_path, growth) -> None:
    """A budget that does not bind decides when the unbudgeted render decides, growth and
    skip included (it used to judge every unit it rendered: another render)."""
    a = adaptive_render("cornell", tmp_path / f"b{growth}", VarianceCriterion(0.3), spp_budget=64, decide_growth=growth,
                        **TINY)
    ref = adaptive_render("cornell", tmp_path / f"p{growth}", VarianceCriterion(0.3), decide_growth=growth, **TINY)
    assert _decisions(a) == _decisions(ref) and [b["spp"] for b in a["blocks"]] == [b["spp"] for b in ref["blocks"]]
    if growth:
        assert sum(map(len, _decisions(a))) < len(a["blocks"]) * 15     # decisions were skipped
