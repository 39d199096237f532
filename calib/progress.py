"""Progress counts of the method's long stages (calibrations, folds).

A stage calls :func:`report` (``task``, done, total) and never prints; where the counts
go is the caller's choice: :func:`reporting` sends them to a sink within a block (the
command line draws them as progress bars; a pool worker forwards them to its parent).
With no sink, :func:`report` does nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

__all__ = ["Sink", "report", "reporting", "set_sink"]

#: Receives (task, done, total).
Sink = Callable[[str, int, int], None]

_sink: Sink | None = None


def report(task: str, done: int, total: int) -> None:
    """``done`` of ``total`` units of ``task`` (e.g. "A: folds", 3, 8)."""
    if _sink is not None:
        _sink(task, done, total)


def set_sink(sink: Sink | None) -> Sink | None:
    """Send this process's reports to ``sink`` from now on; returns the previous sink."""
    global _sink
    previous, _sink = _sink, sink
    return previous


@contextlib.contextmanager
def reporting(sink: Sink | None) -> Iterator[None]:
    """Send this process's reports to ``sink`` within the block."""
    previous = set_sink(sink)
    try:
        yield
    finally:
        set_sink(previous)
