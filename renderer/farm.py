"""Run per-scene jobs on a local process pool or an existing Dask cluster.

Both are Dask: a `LocalCluster` of process workers with one thread each (Mitsuba keeps
per-process global state, so scenes are isolated in processes) runs the very code a farm
`Client("tcp://host:8786")` runs. Callers see a `concurrent.futures.Executor`. On a farm,
the output directory must be on storage every worker can write (a shared filesystem).
"""
from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from concurrent.futures import Executor

from noisefeat.extras import require

log = logging.getLogger(__name__)


def default_workers() -> int:
    return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def executor(workers: int | None = None, scheduler: str | None = None) -> Iterator[Executor]:
    """An Executor on a Dask LocalCluster (`workers` processes) or on `scheduler`."""
    require("distributed")
    from dask.distributed import Client, LocalCluster

    if scheduler:
        log.info("connecting to Dask scheduler %s", scheduler)
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise ValueError(f"cannot reach Dask scheduler {scheduler}: {exc}") from exc
        with client:
            log.info("Dask cluster: %d workers", len(client.scheduler_info().get("workers", {})))
            yield client.get_executor()
        return
    n = workers or default_workers()
    if n < 1:
        raise ValueError(f"--workers must be >= 1, got {n}")
    threads = max(1, (os.cpu_count() or 1) // n)
    log.info("local Dask pool: %d process workers", n)
    env = {"NOISESTOP_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}  # OMP: FLIP
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                      env=env) as cluster, Client(cluster) as client:
        yield client.get_executor()


def configure_worker_threads() -> None:
    """Inside a worker: give torch the worker's share of the cores.

    Dr.Jit's pool is deliberately left alone: `drjit.set_thread_count(1)` makes Mitsuba's
    `Bitmap.write` of an EXR wait forever on OpenEXR's thread-pool semaphore (seen with
    mitsuba 3.9.1; tests/renderer/test_dataset_build.py guards it), so the renderer keeps its own
    pool and the OS shares the cores.
    """
    from noisefeat.bounds import env_int

    threads = env_int(os.environ, "NOISESTOP_THREADS", 0, minimum=1)   # unset or blank: 0, left alone
    if threads:
        import torch
        torch.set_num_threads(threads)
