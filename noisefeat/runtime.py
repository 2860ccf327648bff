"""How torch work is run and timed, wherever it is: on a chosen number of threads, and the
median of repeated calls. One home for the render loop's decisions, the criteria, the
model comparisons and the benchmark lab."""
from __future__ import annotations

import contextlib
import statistics
import time
from collections.abc import Callable, Iterator
from typing import Any


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Torch on `n` threads inside the block, as before afterwards.

    Why one thread for decisions (measured, docs/benchmarks/speed.md "Passes"):
    right after a Dr.Jit kernel its worker threads still spin on both cores, and torch's
    OpenMP team stalled against them, 50x slower than one thread (features of 16 blocks
    of 64x64 took 47 ms per pass against 2 ms); a decision's few blocks gain nothing from
    threads anyway."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def median_s(fn: Callable[[], Any], repeats: int, warm: bool = True) -> float:
    """Median seconds of `repeats` calls of `fn`, after one untimed call unless `warm` is
    False (the caller has warmed it already)."""
    if warm:
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
