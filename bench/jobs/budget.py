"""``uscal budget``: which error source limits a rig, in mm.

Each source of :mod:`bench.config.error_sources` is run

- ``alone``: on top of an error-free rig (every source off, this one as the scenario sets
  it): what the source costs by itself;
- ``all_but``: the full scenario with this one source off: what removing it would buy;

next to ``all`` (the scenario as it is) and ``none`` (every source off: the floor set by
the measurement itself — beam, speckle, pixels), each over seeds. Each run is the whole
``uscal run`` of the scenario (the paper's evaluation when it has datasets), reduced to
the figures of the paper's tables and the errors against the truth; the caller passes
that run (``uscal budget``: :func:`bench.jobs.single.run`, as ``uscal run``), so that a
job does not import another. Runs go to the grid executor (:mod:`bench.grid`: a local
process pool or a Dask cluster); each is cached in ``DIR/points`` under a hash of
everything it depends on, so an interrupted budget resumes, and runs that come out the
same (a source the scenario has off) are computed once.

Outputs: ``DIR/budget.csv`` (one row per source, mode and seed), ``DIR/budget.md`` and
``DIR/budget.html`` with one tornado chart per figure (``DIR/figures``).
"""

from __future__ import annotations

import functools
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.errors import UscalError

from .. import progress as progress_report
from ..config.error_sources import ERROR_SOURCES, ErrorSource, value_at
from ..config.scenario import Scenario, load_scenario
from ..grid import GridPoint, cache_key, run_grid
from ..results import RunResult

__all__ = [
    "FIGURES",
    "BudgetError",
    "BudgetOutcome",
    "BudgetResult",
    "BudgetSpec",
    "budget_figures",
    "plan_budget",
    "run_budget",
    "run_budget_point",
]

#: The budget's figures (CSV columns) and what each is, in the report's words.
FIGURES: dict[str, str] = {
    "sphere_precision_mm": "sphere precision, single marker (mm)",
    "sphere_accuracy_mm": "sphere accuracy, single marker (mm)",
    "tool_precision_mm": "tool precision (mm)",
    "image_mm": "T_ee_us true error over the image, single marker or the target (mm)",
    "rotation_deg": "T_ee_us true rotation error, single marker or the target (°)",
    "translation_mm": "T_ee_us true translation error, single marker or the target (mm)",
    "cone_mae_mm": "cone MAE after ICP, single marker (mm)",
    "prism_mae_mm": "prism MAE after ICP, single marker (mm)",
}
MODES = ("none", "alone", "all_but", "all")


#: The calibrations of targets other than spheres (``metrics.json``'s
#: ``dataset.target``): the wires' and the cone's tip.
TARGET_KINDS = ("nwire", "wire", "cone_tip")


class BudgetError(UscalError):
    """A budget that cannot be run (unknown source, bad option)."""


@dataclass(frozen=True)
class BudgetRun:
    """One run of the budget: which source and mode it stands for, the overrides that
    make it, and its seed."""

    source: str  # a source name, or "-" for the modes none and all
    mode: str
    overrides: tuple[tuple[str, Any], ...]
    seed: int


@dataclass(frozen=True)
class BudgetSpec:
    """A validated budget: the base scenario (file and ``--set`` overrides), the sources
    to budget, the seeds."""

    base: Path | None
    base_text: str
    base_overrides: tuple[str, ...]
    scenario: Scenario
    sources: tuple[ErrorSource, ...]
    seeds: tuple[int, ...]

    def runs(self) -> list[BudgetRun]:
        """Every run: none and all, then each source alone and all-but, per seed."""
        all_off = [kv for s in ERROR_SOURCES for kv in s.overrides()]
        out = []
        for seed in self.seeds:
            out.append(BudgetRun("-", "none", tuple(all_off), seed))
            out.append(BudgetRun("-", "all", (), seed))
            for s in self.sources:
                keys = {k for k, _ in s.off}
                # Alone: every other source off; this one as the scenario has it.
                alone = [kv for kv in all_off if kv[0] not in keys]
                out.append(BudgetRun(s.name, "alone", tuple(alone), seed))
                out.append(BudgetRun(s.name, "all_but", tuple(s.overrides()), seed))
        return out

    def run_key(self, run: BudgetRun) -> str:
        """Cache key: the code, the base scenario's text and overrides, the run's
        *effective* overrides (those that change a value), and the seed — two runs that
        configure the same rig share one key."""
        effective = sorted(
            [k, v] for k, v in run.overrides if not _same(value_at(self.scenario, k), v)
        )
        return cache_key(
            base=self.base_text,
            base_overrides=list(self.base_overrides),
            overrides=effective,
            seed=run.seed,
        )


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def plan_budget(
    path: str | os.PathLike[str] | None,
    overrides: Sequence[str] = (),
    sources: Sequence[str] | None = None,
    seeds: int = 3,
) -> BudgetSpec:
    """Validate a budget: the scenario loads (with ``overrides``), the named sources
    exist, and the scenario with every source off loads too."""
    if seeds < 1:
        raise BudgetError(f"--seeds {seeds}: a budget needs at least one seed")
    scenario = load_scenario(path, overrides)
    known = {s.name: s for s in ERROR_SOURCES}
    if sources is None:
        chosen = ERROR_SOURCES
    else:
        unknown = [n for n in sources if n not in known]
        if unknown:
            raise BudgetError(
                f"--sources: unknown source(s) {', '.join(unknown)}; known: {', '.join(known)}"
            )
        chosen = tuple(known[n] for n in dict.fromkeys(sources))
    all_off = [f"{k}={json.dumps(v)}" for s in ERROR_SOURCES for k, v in s.overrides()]
    load_scenario(path, [*overrides, *all_off], check_reach=False)
    text = "" if path is None else Path(path).read_text(encoding="utf-8")
    return BudgetSpec(
        None if path is None else Path(path).resolve(),
        text,
        tuple(overrides),
        scenario,
        chosen,
        tuple(scenario.seed + i for i in range(seeds)),
    )


# ----------------------------------------------------------------------------- a run


def budget_figures(metrics: dict[str, Any]) -> dict[str, float]:
    """The budget's figures from a run's ``metrics.json`` content.

    With the paper's evaluation: the overall MAE of Tables I–III (single marker) and the
    true errors of ``T_ee_us`` averaged over the single-marker folds. One acquisition:
    the single-marker calibration's precision, its accuracy against the true centres, and
    its true errors; no tool precision or reconstruction (NaN). A wire, N-wire or cone-tip
    scenario: its calibration's true errors (no sphere figures).
    """
    nan = float("nan")
    out = dict.fromkeys(FIGURES, nan)
    ev = metrics.get("evaluation", {})
    target = metrics.get("dataset", {}).get("target")
    if target in TARGET_KINDS:
        for key in ("image_mm", "rotation_deg", "translation_mm"):
            out[key] = metrics["calibration"][target]["true_error"][key]
    elif "single" in ev:
        table = ev["single"]
        out["sphere_precision_mm"] = table["sphere_precision_mm"]["overall"]["mae"]
        out["sphere_accuracy_mm"] = table["sphere_accuracy_mm"]["overall"]["mae"]
        out["tool_precision_mm"] = table["tool_precision_mm"]["overall"]["mae"]
        folds = [f["true"] for f in ev.get("folds", []) if f["kind"] == "single"]
        for key in ("image_mm", "rotation_deg", "translation_mm"):
            out[key] = float(np.mean([f[key] for f in folds])) if folds else nan
    else:
        single = metrics["calibration"]["single"]
        out["sphere_precision_mm"] = single["precision_mm"]
        out["sphere_accuracy_mm"] = single["accuracy_mm"]
        for key in ("image_mm", "rotation_deg", "translation_mm"):
            out[key] = single["true_error"][key]
    recon = metrics.get("reconstruction", {})
    for kind in ("cone", "prism"):
        if kind in recon:
            out[f"{kind}_mae_mm"] = recon[kind]["single"]["overall"]["mae"]
    return {k: float(v) for k, v in out.items()}


#: What a budget runs at each point: a whole scenario, as ``uscal run`` does.
Runner = Callable[[Scenario], RunResult]


def run_budget_point(
    run: Runner,
    base: str | None,
    base_overrides: Sequence[str],
    overrides: Sequence[tuple[str, Any]],
    seed: int,
) -> dict[str, Any]:
    """One budget run (in a worker): the scenario with the overrides and seed, run whole
    by ``run`` (serially: the budget's executor is the parallelism), reduced to
    :data:`FIGURES`. A failure raises; the grid records it (a source may make a
    calibration impossible) and goes on."""
    sets = [*base_overrides, *(f"{k}={json.dumps(v)}" for k, v in overrides), f"seed={seed}"]
    scenario = load_scenario(base, sets)
    scenario = replace(scenario, evaluation=replace(scenario.evaluation, workers=1))
    t0 = time.perf_counter()
    with progress_report.reporting(None):
        result = run(scenario)
    return {"figures": budget_figures(result.metrics), "seconds": time.perf_counter() - t0}


@dataclass(frozen=True)
class BudgetOutcome:
    """What became of one budget run, as the grid records it
    (:func:`bench.grid.run_grid`): its :data:`FIGURES`, or the error it failed with."""

    figures: dict[str, float] | None = None
    error: str | None = None

    @classmethod
    def from_document(cls, doc: dict[str, Any]) -> BudgetOutcome:
        """``{overrides, seed, figures, seconds}`` (:func:`run_budget_point`), or
        ``{overrides, seed, error, traceback}`` for a run that failed (no figures)."""
        figures = doc.get("figures")
        refused = doc.get("refused")
        return cls(
            None if figures is None else {k: float(v) for k, v in figures.items()},
            doc.get("error") or (None if refused is None else f"refused: {refused}"),
        )

    def figure(self, name: str) -> float:
        """One of :data:`FIGURES` (NaN: failed, or not measured by this scenario)."""
        return (self.figures or {}).get(name, float("nan"))


# ----------------------------------------------------------------------------- the budget


@dataclass(frozen=True)
class BudgetResult:
    """Every run's figures (or error), in the spec's order, and what was computed anew."""

    spec: BudgetSpec
    runs: list[tuple[BudgetRun, dict[str, Any]]]
    computed: int
    cached: int
    failed: int
    seconds: float
    refused: int = 0


def run_budget(
    spec: BudgetSpec,
    out: str | os.PathLike[str],
    run: Runner,
    scheduler: str | None = None,
    workers: int | None = None,
) -> BudgetResult:
    """Run, with ``run`` (a picklable function: ``uscal budget`` passes
    :func:`bench.jobs.single.run`), what is not cached in ``out/points`` (local pool of
    ``workers``, default one per core, or the Dask cluster at ``scheduler``;
    :func:`bench.grid.run_grid`); :func:`bench.outputs.budget_report.write_budget` writes
    the tables and charts."""
    runs = spec.runs()
    base = None if spec.base is None else str(spec.base)
    task = functools.partial(run_budget_point, run, base, spec.base_overrides)
    points = [GridPoint(r.overrides, r.seed, spec.run_key(r)) for r in runs]
    grid = run_grid(task, points, out, scheduler, workers, "budget runs")
    return BudgetResult(
        spec,
        list(zip(runs, grid.documents, strict=True)),
        grid.computed,
        grid.cached,
        grid.failed,
        grid.seconds,
        grid.refused,
    )
