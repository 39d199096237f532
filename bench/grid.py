"""Grids of runs: the executor of ``uscal sweep`` (:mod:`bench.jobs.sweep`) and ``uscal
budget`` (:mod:`bench.jobs.budget`).

A grid is a list of points, each a run of a base scenario with some overrides and a seed
(:class:`GridPoint`), all running one task, ``task(overrides, seed) -> dict`` (a
picklable function: a module-level one, or a :func:`functools.partial` of one). The
points run on a local process pool or a Dask cluster (:func:`bench.parallel.executor`);
each point's document (its overrides, seed and the task's result, or the error it
raised) is written to ``DIR/points/<key>.json`` as it finishes, and a point whose file
exists is not run again: an interrupted grid resumes, and points that come out the same
(one key) run once. The key hashes everything a point's result depends on, the code
included (:func:`cache_key`, :func:`code_version`), so a result of other code is never
reused.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calib.errors import CollisionError, UnreachablePoseError

from . import progress as progress_report
from .files import make_directory, write_text_atomic
from .parallel import as_completed, executor

__all__ = ["GridOutcome", "GridPoint", "cache_key", "code_version", "run_grid"]

#: What a grid's task is: ``(overrides, seed)`` → the point's result (JSON-able).
Task = Callable[[tuple[tuple[str, Any], ...], int], dict[str, Any]]


@functools.cache
def code_version() -> str:
    """A hash of the source of the packages a point runs (calib, sim_us, twin, bench):
    a cached result computed by other code is not reused."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for package in ("calib", "sim_us", "twin", "bench"):
        for path in sorted((root / package).rglob("*.py")):
            h.update(str(path.relative_to(root)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def cache_key(**parts: Any) -> str:
    """A point's cache key: a hash of :func:`code_version` and ``parts``, everything else
    its result depends on (JSON-able: the base scenario's text, the overrides, the
    seed, ...)."""
    doc = {"code": code_version(), **parts}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class GridPoint:
    """One point of a grid: the scenario overrides (key path, value) and the seed its
    task runs with, and its cache key (:func:`cache_key`)."""

    overrides: tuple[tuple[str, Any], ...]
    seed: int
    key: str


@dataclass(frozen=True)
class GridOutcome:
    """Every point's document, in the points' order (``overrides``, ``seed``, then the
    task's result, ``error`` and ``traceback``, or ``refused``), and how the distinct runs
    went: computed now, read from the cache, failed, refused (the plan collides or is out
    of reach: refused before anything moved); the wall time."""

    documents: list[dict[str, Any]]
    computed: int
    cached: int
    failed: int
    seconds: float
    refused: int = 0


def _guarded(task: Task, overrides: tuple[tuple[str, Any], ...], seed: int) -> dict[str, Any]:
    """The task of a point, its failure recorded instead of raised (the grid goes on). A
    plan refused before anything moved (a pose that would collide or is out of reach: the
    condition cannot be run on this rig, nothing went wrong) is a ``refused`` point, not
    a failed one."""
    try:
        return task(overrides, seed)
    except (CollisionError, UnreachablePoseError) as exc:
        return {"refused": f"{type(exc).__name__}: {exc}"}
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


def run_grid(
    task: Task,
    points: Sequence[GridPoint],
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    label: str = "points",
) -> GridOutcome:
    """Run ``task`` at every point whose ``out/points/<key>.json`` does not exist yet, on
    a local pool of ``workers`` processes (default one per core) or the Dask cluster at
    ``scheduler``, writing each document as it comes; progress is reported as
    ``label``. Points sharing a key run once (the file records the last of them)."""
    t0 = time.perf_counter()
    directory = make_directory(Path(out) / "points")
    runs = {p.key: p for p in points}
    done: dict[str, dict[str, Any]] = {}
    todo: dict[str, GridPoint] = {}
    for key, point in runs.items():
        cached = directory / f"{key}.json"
        if cached.is_file():
            done[key] = json.loads(cached.read_text(encoding="utf-8"))
        else:
            todo[key] = point
    n_cached = len(done)
    progress_report.report(label, n_cached, len(runs))
    if todo:
        submit, close = executor(scheduler, workers)
        try:
            futures = {submit(_guarded, task, p.overrides, p.seed): key for key, p in todo.items()}
            for future in as_completed(futures, scheduler is not None):
                key = futures[future]
                point = todo[key]
                doc: dict[str, Any] = {
                    "overrides": [[k, v] for k, v in point.overrides],
                    "seed": point.seed,
                }
                doc.update(future.result())
                write_text_atomic(directory / f"{key}.json", json.dumps(doc, indent=1))
                done[key] = doc
                progress_report.report(label, len(done), len(runs))
        finally:
            close()
    failed = sum("error" in doc for doc in done.values())
    refused = sum("refused" in doc for doc in done.values())
    return GridOutcome(
        [done[p.key] for p in points],
        len(runs) - n_cached,
        n_cached,
        failed,
        time.perf_counter() - t0,
        refused,
    )
