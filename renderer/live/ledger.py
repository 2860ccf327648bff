"""A render's counters and timers, in one place: its ledger.

The session makes one per render and hands it to the parts that spend (the loop, the renderer
and its tracer, the budget); the checkpoint and report.json read it. A part made alone (in a
test, a simulation, a benchmark) keeps a ledger of its own.
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
    """Counters (whole numbers) and timers (seconds) by name, in the order first named (the checkpoint's and the
    report's). `budget_cost`: a budget render's rounds, [seconds, unit-spp traced]."""

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
        """Go on from a checkpoint's counters and timers: the process's costs (`RENDER_COUNTERS`,
        `RENDER_TIMERS`) add up over attempts; the decisions' are the render's so far, so the checkpoint's
        replace this attempt's (its quick image, counted already). Names this ledger does not keep are ignored."""
        for kept, given, summed, kind in ((self.counters, counters, RENDER_COUNTERS, int),
                                          (self.timers, timers, RENDER_TIMERS, float)):
            for k, v in given.items():
                if k in kept:
                    kept[k] = (kept[k] if k in summed else kind(0)) + kind(v)
