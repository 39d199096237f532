"""What ``uscal sweep`` and ``uscal budget`` print: the workload before it runs, and how
its points went (computed, from the cache, failed) with the files written."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

__all__ = ["print_cached_run", "print_workload"]


def print_workload(
    points: str, acquisitions: int, hours: float, workers: int, cluster: bool, console
):
    """What a sweep is about to run, before it runs: its points (in words:
    :meth:`bench.jobs.sweep.SweepSpec.describe`), the acquisitions they take (points that
    differ in the gain alone share one) and the time it should take."""
    where = (
        f"≈ {_duration(hours)} of worker time on the cluster"
        if cluster
        else f"≈ {_duration(hours / workers)} on {workers} local worker(s)"
    )
    console.print(
        f"{points}, {acquisitions:,} acquisitions; {where} (cached points are not recomputed)"
    )


def _duration(hours: float) -> str:
    return f"{hours:.1f} h" if hours >= 1.0 else f"{max(1, round(60 * hours))} min"


def print_cached_run(what: str, n: int, result, files: Sequence[Path], console) -> None:
    """How a sweep's or budget's points went, and its files."""
    refused = result.refused
    console.print(
        f"{n} {what}: {result.computed} computed, {result.cached} from the cache, "
        f"{result.failed} failed"
        + (
            f", {refused} refused before anything moved (the plan collides or is out of "
            "reach at that condition)"
            if refused
            else ""
        )
        + f", in {result.seconds:.0f} s"
    )
    console.print(f"wrote {', '.join(str(f) for f in files[:-1])} and {files[-1]}")
