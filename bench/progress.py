"""Progress counts of long stages, from the main process and from pool workers.

Stages call :func:`report` (``task``, done, total; :mod:`calib.progress`, which the
method's own stages use too) and never print; where the counts go is set by the caller:
:func:`reporting` in the main process (the CLI draws them as rich progress bars),
:func:`worker_initializer` in a pool worker (they travel through a queue, which the main
process empties with :func:`drain` while it waits). With neither, :func:`report` does
nothing.
"""

from __future__ import annotations

import queue as queue_module
from typing import Any

from calib.progress import Sink, report, reporting, set_sink

__all__ = ["Sink", "drain", "report", "reporting", "worker_initializer"]


def worker_initializer(q: Any) -> None:
    """Pool-worker initializer: this worker's reports go into ``q`` (a
    ``multiprocessing`` queue made by the pool's context)."""
    set_sink(lambda task, done, total: q.put((task, done, total)))


def drain(q: Any) -> None:
    """Forward the workers' queued reports to this process's sink."""
    while True:
        try:
            task, done, total = q.get_nowait()
        except queue_module.Empty:
            return
        report(task, done, total)
