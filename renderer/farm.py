"""Per-scene jobs on a Dask `LocalCluster` of one-thread process workers (Mitsuba keeps
per-process global state) or on a farm's scheduler: the same code, seen as an Executor.
On a farm the output directory must be on storage every worker can write.
"""
from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, as_completed
from typing import Any

from tqdm import tqdm

from noisefeat.extras import require

log = logging.getLogger(__name__)


@contextlib.contextmanager
def executor(workers: int | None = None, scheduler: str | None = None) -> Iterator[Executor]:
    """An Executor on a Dask LocalCluster (`workers` processes, default one per core) or on `scheduler`."""
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
    cpus = os.cpu_count() or 1
    n = workers or cpus
    if n < 1:
        raise ValueError(f"--workers must be >= 1, got {n}")
    threads = max(1, cpus // n)
    log.info("local Dask pool: %d process workers", n)
    env = {"NOISESTOP_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}  # OMP: FLIP
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                      env=env) as cluster, Client(cluster) as client:
        yield client.get_executor()


def configure_worker_threads() -> None:
    """Inside a worker: give torch its share of the cores (NOISESTOP_THREADS). Dr.Jit's pool is
    left alone: `drjit.set_thread_count(1)` makes Mitsuba's EXR `Bitmap.write` hang on OpenEXR's
    thread-pool semaphore (mitsuba 3.9.1; tests/renderer/test_dataset_build.py guards it)."""
    from noisefeat.bounds import env_int

    threads = env_int(os.environ, "NOISESTOP_THREADS", 0, minimum=1)   # unset or blank: 0, left alone
    if threads:
        import torch
        torch.set_num_threads(threads)


def _in_worker(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    configure_worker_threads()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return fn(*args)


def run_tasks(fn: Callable[..., Any], tasks: Iterable[tuple[str, tuple[Any, ...]]], workers: int | None = None,
              scheduler: str | None = None, progress: bool = True) -> Iterator[tuple[str, Any, str | None]]:
    """`fn(*args)` for each (label, args), one task each on `executor`; yields (label, result,
    None) as each finishes, or (label, None, "Type: message") if it failed: one bad scene must
    not lose the others' work."""
    with executor(workers, scheduler) as pool:
        futures = {pool.submit(_in_worker, fn, args): label for label, args in tasks}
        for fut in tqdm(as_completed(futures), total=len(futures), desc="scenes", unit="scene",
                        disable=not progress):
            try:
                result, error = fut.result(), None
            except Exception as exc:
                result, error = None, f"{type(exc).__name__}: {exc}"
                log.error("scene %s failed: %s", futures[fut], error)
            yield futures[fut], result, error
