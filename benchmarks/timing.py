"""Timing tools of the lab: medians over repeats after a warm-up, the machine's load meanwhile,
and the multiply-add count of the feature base by its definition.
"""
from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable
from typing import Any

from noisefeat.runtime import median_s  # noqa: F401  (the lab's benches import it from here)

log = logging.getLogger(__name__)


def direct_macs(n: int, h: int, w: int, wavelet_taps: int = 2) -> int:
    """Multiply-adds of the feature base computed by its definition, spatially.

    12 convolutions (3x3, 5x5 alternating: 204 per pixel) plus the wavelet layer's
    analysis and synthesis (taps per axis, both axes, for the approximation band only).
    """
    per_pixel = sum(k * k for k in (3, 5) * 6) + 2 * wavelet_taps
    return n * h * w * per_pixel


class MachineLoad:
    """CPU time other processes used while a measurement ran, as a share of all CPUs
    (Linux /proc/stat less this process and the processes in `mine`, e.g. a server under
    test): BENCHMARKS says when a figure was taken on a busy machine. None without /proc."""

    def __init__(self, mine: tuple[int, ...] = ()) -> None:
        self.mine = mine
        self.share: float | None = None

    def __enter__(self) -> "MachineLoad":
        self._t0, self._busy0, self._own0 = time.perf_counter(), _busy_jiffies(), self._own()
        return self

    def _own(self) -> float:
        return time.process_time() + sum(_process_cpu(p) or 0.0 for p in self.mine)

    def __exit__(self, *exc: Any) -> None:
        busy1 = _busy_jiffies()
        if self._busy0 is None or busy1 is None:
            return
        import os
        wall = time.perf_counter() - self._t0
        others = (busy1 - self._busy0) / os.sysconf("SC_CLK_TCK") - (self._own() - self._own0)
        self.share = max(0.0, others / (wall * (os.cpu_count() or 1)))


def _busy_jiffies() -> int | None:
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return sum(v) - v[3] - v[4]          # all but idle and iowait


def _process_cpu(pid: int) -> float | None:
    """CPU seconds (user + system) of a process, all its threads (Linux)."""
    import os
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def interleaved_medians(fast: Callable[[], Any], slow: Callable[[], Any], repeats: int,
                         slow_repeats: int) -> tuple[float, float]:
    """Median seconds of `fast` (repeats) and `slow` (slow_repeats), their runs interleaved
    so that both see the same load when other work shares the machine."""
    fast(), slow()
    every = max(1, repeats // slow_repeats)
    t_fast, t_slow = [], []
    for i in range(repeats):
        t0 = time.perf_counter()
        fast()
        t_fast.append(time.perf_counter() - t0)
        if i % every == 0 and len(t_slow) < slow_repeats:
            t0 = time.perf_counter()
            slow()
            t_slow.append(time.perf_counter() - t0)
    return statistics.median(t_fast), statistics.median(t_slow)
