"""Parallel execution: the paper run's process pool (its workers' initializer, one BLAS
thread per process, memory given back after each task), and the local-pool-or-Dask
executor that grids of runs use (:func:`executor`, :func:`as_completed`; the grids
themselves, with their per-point cache, are :mod:`bench.grid`). The only module that
imports Dask."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import gc
import multiprocessing
import os
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from threadpoolctl import threadpool_limits

from calib.errors import UscalError
from twin.printing import forget_parts, use_disk_cache

from . import progress as progress_report
from .config.scenario import Scenario

__all__ = [
    "SchedulerError",
    "as_completed",
    "executor",
    "exit_with_parent",
    "one_blas_thread",
    "pool_task",
    "release_memory",
    "start_worker",
    "worker_initializer",
    "workers_for",
]


class SchedulerError(UscalError):
    """The Dask scheduler cannot be used."""


def one_blas_thread() -> threadpool_limits:
    """Limit this process's BLAS (OpenBLAS) to one thread, until the returned limiter
    is exited (a ``with`` block) or for good.

    For a process that shares the cores with a pool's workers, or is one of them: an
    OpenBLAS thread per core in each process oversubscribes the cores, and its threads
    spin waiting for each other on the tiny matrices of the pipeline (the DH
    refinement's SVDs took 9.7 s of a paper run instead of 1 s)."""
    return threadpool_limits(1, user_api="blas")


def exit_with_parent(poll_s: float = 1.0) -> None:
    """In a pool worker: exit as soon as the process that started it is gone.

    A run stopped by SIGTERM (``kill``, a job scheduler) ends without shutting its pool
    down, and a spawned worker then runs its current task to the end (minutes of a core:
    found beside later runs) before it reads the closed pipe. Polling the parent's pid
    from a daemon thread works however the worker was started and from whichever thread
    (the kernel's parent-death signal follows the thread that forked).

    The parent is the one ``multiprocessing`` recorded at the spawn, not the parent at
    the time of the call: a run killed while its worker was still importing (seconds on
    a loaded machine) has already left the worker to init by then, and a worker that
    took init for its parent ran its whole task (found in CI)."""
    spawner = multiprocessing.parent_process()
    parent = spawner.pid if spawner is not None else os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def release_memory() -> None:
    """Collect garbage and give the heap's freed pages back to the system (glibc
    ``malloc_trim``).

    A pool worker's frames are freed when its task ends, but glibc keeps freed heap
    memory for reuse, so an idle worker went on holding ≈ 0.3-0.9 GB (measured) until
    the pool closed; with three workers that decided the run's peak memory."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def pool_task(fn: Callable[..., Any], *args: Any) -> Any:
    """Run a pool task, then release the memory it freed (its printed parts included:
    a worker's next task reads them back from the run's disk cache)."""
    try:
        return fn(*args)
    finally:
        forget_parts()
        release_memory()


def start_worker() -> None:
    """A no-op task: submitting it starts a worker process."""


def worker_initializer(counts: Any, parts: Path) -> None:
    """A pool worker: report progress to the run, share the run's printed parts, one
    BLAS thread (:func:`one_blas_thread`); it exits with the run (:func:`exit_with_parent`)."""
    exit_with_parent()
    progress_report.worker_initializer(counts)
    use_disk_cache(parts)
    one_blas_thread()


def _grid_worker_initializer() -> None:
    """A grid's local worker: it exits with the grid (:func:`exit_with_parent`), one BLAS
    thread (n processes on the cores)."""
    exit_with_parent()
    one_blas_thread()


def workers_for(scenario: Scenario, n_tasks: int) -> int:
    """Worker processes: the scenario's number, or one per core (at most one per task).
    Since the reconstruction's tasks queue behind the datasets, a third worker on two
    cores no longer fills an idle core: it only adds a dataset's frames to the memory
    (paper.yaml, 2 cores: 89.6 s and 2.7 GB with two workers, 94.2 s and 3.9 GB with
    three)."""
    w = scenario.evaluation.workers or (os.cpu_count() or 1)
    return max(1, min(w, n_tasks))


def executor(scheduler: str | None, workers: int | None):
    """(submit, wait-for-any, close) on a local process pool or a Dask cluster."""
    if scheduler is None:
        n = workers or os.cpu_count() or 1
        pool = cf.ProcessPoolExecutor(
            max_workers=n,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_grid_worker_initializer,
        )
        return pool.submit, pool.shutdown
    try:
        from distributed import Client
    except ImportError:
        raise SchedulerError(
            "--scheduler needs Dask distributed: pip install 'uscal[dist]'"
        ) from None
    _refused(scheduler)
    try:
        client = Client(scheduler, timeout="10s")
    except OSError as exc:
        raise SchedulerError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    return client.submit, client.close


def _refused(scheduler: str) -> None:
    """Fail at once where nothing listens at a ``tcp://host:port`` scheduler address (the
    client would retry for its whole timeout); a host that does not answer is left to the
    client's timeout."""
    address = scheduler.removeprefix("tcp://")
    host, _, port = address.rpartition(":")
    if scheduler == address or not host or not port.isdigit():
        return  # another protocol, or no port: the client knows its defaults
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
            return
    except ConnectionRefusedError as exc:
        raise SchedulerError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    except OSError:
        return


def as_completed(futures, dask: bool):
    """The futures as they finish (a local pool's or a Dask cluster's)."""
    if dask:
        from distributed import as_completed

        return as_completed(list(futures))
    return cf.as_completed(futures)
