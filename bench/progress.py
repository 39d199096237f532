"""Progress counts of long stages, from the main process and from pool workers.

Stages call :func:`report` (``task``, done, total) and never print; where the counts go
is set by the caller: :func:`reporting` in the main process (the CLI draws them as rich
progress bars), :func:`worker_initializer` in a pool worker (they travel through a
queue, which the main process empties with :func:`drain` while it waits). With neither,
:func:`report` does nothing.
"""

from __future__ import annotations

import contextlib
import queue as queue_module
from collections.abc import Callable, Iterator
from typing import Any

__all__ = ["Sink", "drain", "report", "reporting", "worker_initializer"]

Sink = Callable[[str, int, int], None]

_sink: Sink | None = None


def report(task: str, done: int, total: int) -> None:
    """``done`` of ``total`` units of ``task`` (e.g. "A: acquire", 12, 180)."""
    if _sink is not None:
        _sink(task, done, total)


@contextlib.contextmanager
def reporting(sink: Sink | None) -> Iterator[None]:
    """Send this process's reports to ``sink`` within the block."""
    global _sink
    previous, _sink = _sink, sink
    try:
        yield
    finally:
        _sink = previous


def worker_initializer(q: Any) -> None:
    """Pool-worker initializer: this worker's reports go into ``q`` (a
    ``multiprocessing`` queue made by the pool's context)."""
    global _sink
    _sink = lambda task, done, total: q.put((task, done, total))  # noqa: E731


def drain(q: Any) -> None:
    """Forward the workers' queued reports to this process's sink."""
    while True:
        try:
            task, done, total = q.get_nowait()
        except queue_module.Empty:
            return
        report(task, done, total)
