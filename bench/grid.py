"""Grids of runs: the executor of ``uscal sweep`` (:mod:`bench.jobs.sweep`) and ``uscal
budget`` (:mod:`bench.jobs.budget`).

A grid is a list of points, each a run of a base scenario with some overrides and a seed
(:class:`GridPoint`), all running one task, ``task(overrides, seed) -> dict`` (a
picklable function: a module-level one, or a :func:`functools.partial` of one); points
of one batch (:attr:`GridPoint.batch`: the same seed and settings but for one that a
single run can serve, such as the display gain) run one batch task together. The
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

__all__ = ["GridOutcome", "GridPoint", "cache_key", "code_version", "guarded", "run_grid"]

Overrides = tuple[tuple[str, Any], ...]
#: What a grid's task is: ``(overrides, seed)`` → the point's result (JSON-able).
Task = Callable[[Overrides, int], dict[str, Any]]
#: A task over a batch of points: ``(each point's overrides, seed)`` → their results, in
#: order (each guarded alone: :func:`guarded`).
BatchTask = Callable[[list[Overrides], int], list[dict[str, Any]]]


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

    overrides: Overrides
    seed: int
    key: str
    #: Points of a grid with the same ``batch`` (not None) and seed run together, by the
    #: grid's batch task (:func:`run_grid`).
    batch: Any = None


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


def guarded(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    """A point's result ``fn(*args)``, its failure recorded instead of raised (the grid
    goes on). A plan refused before anything moved (a pose that would collide or is out
    of reach: the condition cannot be run on this rig, nothing went wrong) is a
    ``refused`` point, not a failed one."""
    try:
        return fn(*args)
    except (CollisionError, UnreachablePoseError) as exc:
        return {"refused": f"{type(exc).__name__}: {exc}"}
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


def _guarded_batch(task: BatchTask, overrides: list[Overrides], seed: int) -> list[dict[str, Any]]:
    """A batch's results; what its points share failing (their acquisition: a refused
    plan, an error), each of them records that."""
    outcome = guarded(lambda: {"results": task(overrides, seed)})
    if "results" in outcome:
        return outcome["results"]
    return [dict(outcome) for _ in overrides]


def run_grid(
    task: Task,
    points: Sequence[GridPoint],
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    label: str = "points",
    batch_task: BatchTask | None = None,
) -> GridOutcome:
    """Run ``task`` at every point whose ``out/points/<key>.json`` does not exist yet, on
    a local pool of ``workers`` processes (default one per core) or the Dask cluster at
    ``scheduler``, writing each document as it comes; progress is reported as
    ``label``. Points sharing a key run once (the file records the last of them). With
    ``batch_task``, the points still to run that share a :attr:`GridPoint.batch` and seed
    run as one call of it (a point alone in its batch, or without one, runs ``task``);
    their documents are written when it ends."""
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
        batches: dict[Any, list[str]] = {}
        for key, p in todo.items():
            together = p.batch is not None and batch_task is not None
            batches.setdefault(("batch", p.batch, p.seed) if together else key, []).append(key)
        submit, close = executor(scheduler, workers)
        try:
            futures = {}
            for keys in batches.values():
                first = todo[keys[0]]
                if len(keys) == 1:
                    future = submit(guarded, task, first.overrides, first.seed)
                else:
                    overrides = [todo[k].overrides for k in keys]
                    future = submit(_guarded_batch, batch_task, overrides, first.seed)
                futures[future] = keys
            for future in as_completed(futures, scheduler is not None):
                keys = futures[future]
                results = future.result()
                for key, result in zip(keys, results if len(keys) > 1 else [results], strict=True):
                    point = todo[key]
                    doc: dict[str, Any] = {
                        "overrides": [[k, v] for k, v in point.overrides],
                        "seed": point.seed,
                    }
                    doc.update(result)
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
