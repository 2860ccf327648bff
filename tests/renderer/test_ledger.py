"""A render's counters and timers have one owner, its ledger (`renderer.live.ledger`)."""
from __future__ import annotations

import numpy as np

from renderer.live.budget import Budget
from renderer.criteria import COUNTER_NAMES, TIMER_NAMES, VarianceCriterion
from renderer.live.ledger import RENDER_COUNTERS, RENDER_TIMERS, Ledger
from renderer.live.passloop import PassLoop, schedule


def test_a_resume_adds_the_process_costs_and_replaces_the_decisions() -> None:
    """What this attempt counted before it resumed: its Mitsuba calls and seconds add to the
    checkpoint's; its decisions (preparing the quick image again) are the checkpoint's
    already. Names the ledger does not keep are ignored."""
    ledger = Ledger(COUNTER_NAMES + RENDER_COUNTERS, TIMER_NAMES + RENDER_TIMERS)
    ledger.count("mitsuba_calls", 2)
    ledger.count("feature_rows", 16)
    ledger.time("setup_s", 0.5)
    ledger.time("features_s", 0.25)
    ledger.restore({"mitsuba_calls": 5, "feature_rows": 40, "stray": 1},
                   {"setup_s": 1.0, "features_s": 2.0, "wall_s": 4.0, "stray_s": 1.0})
    assert ledger.counters["mitsuba_calls"] == 7 and ledger.counters["feature_rows"] == 40
    assert ledger.timers["setup_s"] == 1.5 and ledger.timers["features_s"] == 2.0 and ledger.timers["wall_s"] == 4.0
    assert "stray" not in ledger.counters and "stray_s" not in ledger.timers
    assert list(ledger.counters) == [*COUNTER_NAMES, *RENDER_COUNTERS]      # the order the checkpoint lists


def test_the_loop_and_the_budget_report_into_the_ledger_they_are_given() -> None:
    """A loop and a budget made with a render's ledger keep no counts of their own; made
    alone, each has a ledger of its own."""
    ledger = Ledger(COUNTER_NAMES + RENDER_COUNTERS, TIMER_NAMES + RENDER_TIMERS)
    # a criterion that can stop judges every pass (no decide_skip); uniform is asked at the last pass only
    loop = PassLoop(VarianceCriterion(1e-6), (2, 2), (4, 4), schedule(4, 16), None, ledger=ledger)
    budget = Budget(spp_budget=8.0, ledger=ledger)
    loop.run_round([0, 1, 2, 3], [(np.full((4, 4, 4, 3), 0.5), 4)])
    budget.record(0.5, 16)
    assert ledger.counters["decide_calls"] == 1 and ledger.counters["units_asked"] == 4
    assert ledger.budget_cost == [0.5, 16.0] and budget.state(loop.ratios).cost == (0.5, 16.0)
    alone = PassLoop(VarianceCriterion(1e-6), (2, 2), (4, 4), schedule(4, 16), None)
    alone.run_round([0, 1], [(np.full((2, 4, 4, 3), 0.5), 4)])
    assert alone.ledger is not ledger and alone.ledger.counters["decide_calls"] == 1
    assert ledger.counters["decide_calls"] == 1 and Budget().ledger is not ledger
