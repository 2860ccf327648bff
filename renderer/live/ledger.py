"""A render's counters and timers, in one place: its ledger.

One `Ledger` per render. The session makes it (`renderer.live.session.RenderSession`) and hands
it to the parts that spend: the loop (`renderer.live.passloop.PassLoop`: what its decisions
cost, `renderer.criteria`'s COUNTER_NAMES and TIMER_NAMES), the renderer
(`renderer.live.blocks.BlockRenderer` and its `WavefrontTracer`: Mitsuba calls, kernel launches,
lanes and compilations, samples traced) and the budget (`renderer.live.budget.Budget`: the
seconds and unit-samples of its rounds, its time limit's rate); the session adds the
checkpoints it writes and the setup, render and wall seconds. Each reports into it; the
checkpoint (`RenderSession.progress`) and report.json (`renderer.live.report`) read it, nothing
else. A part made alone (a `BlockRenderer`, `PassLoop` or `Budget` of a test, a
simulation or a benchmark) keeps a ledger of its own.

A resume (`restore`): the process's costs (`RENDER_COUNTERS`, `RENDER_TIMERS`) add up over
every attempt; the decisions' are the render's so far, so the checkpoint's replace what
this attempt counted before it resumed (preparing the quick image again, which the first
attempt counted already).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

#: what a render cost in Mitsuba, over every attempt (report.json "render_calls"); like the
#: timings these depend on the process (a resumed run compiles its kernel again)
RENDER_COUNTERS = ("mitsuba_calls", "kernel_launches", "kernel_lanes", "kernel_compiles", "checkpoints",
                   "samples_traced")
#: the session's seconds, over every attempt (report.json "timing" and "wall_s"); wall_s
#: holds the earlier attempts' only: the running attempt's is added when read
RENDER_TIMERS = ("render_s", "setup_s", "wall_s")


class Ledger:
    """Counters (whole numbers) and timers (seconds) by name, in the order first named.

    `counters` and `timers` start at 0 for the names given (the order the checkpoint and
    the report list them in); a name reported later is added. `budget_cost`: a budget
    render's rounds, [seconds (tracing and judging), unit-spp traced]."""

    def __init__(self, counters: Iterable[str] = (), timers: Iterable[str] = ()) -> None:
        self.counters: dict[str, int] = dict.fromkeys(counters, 0)
        self.timers: dict[str, float] = dict.fromkeys(timers, 0.0)
        self.budget_cost = [0.0, 0.0]

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + int(n)

    def time(self, key: str, seconds: float) -> None:
        self.timers[key] = self.timers.get(key, 0.0) + float(seconds)

    def add(self, counts: Mapping[str, Any], timers: Mapping[str, float]) -> None:
        """A call's counts and seconds (a criterion's `Decision`, its `prepare`)."""
        for k, v in counts.items():
            self.count(k, v)
        for k, v in timers.items():
            self.time(k, v)

    def get(self, key: str) -> int:
        """A counter, 0 if nothing reported it yet."""
        return self.counters.get(key, 0)

    def restore(self, counters: Mapping[str, Any], timers: Mapping[str, float]) -> None:
        """Go on from a checkpoint's counters and timers (the module docstring: the
        process's costs added, the decisions' replaced); names this ledger does not keep
        are ignored."""
        for k, v in counters.items():
            if k in self.counters:
                self.counters[k] = (self.counters[k] if k in RENDER_COUNTERS else 0) + int(v)
        for k, v in timers.items():
            if k in self.timers:
                self.timers[k] = (self.timers[k] if k in RENDER_TIMERS else 0.0) + float(v)
