"""``uscal budget``: which error source limits a rig, in mm.

Each source of :mod:`bench.error_sources` is run

- ``alone``: on top of an error-free rig (every source off, this one as the scenario sets
  it): what the source costs by itself;
- ``all_but``: the full scenario with this one source off: what removing it would buy;

next to ``all`` (the scenario as it is) and ``none`` (every source off: the floor set by
the measurement itself — beam, speckle, pixels), each over seeds. Each run is the whole
``uscal run`` of the scenario (the paper's evaluation when it has datasets), reduced to
the figures of the paper's tables and the errors against the truth. Runs go to the sweep
executor (local process pool or a Dask cluster); each is cached in ``DIR/points`` under a
hash of everything it depends on, so an interrupted budget resumes, and runs that come
out the same (a source the scenario has off) are computed once.

Outputs: ``DIR/budget.csv`` (one row per source, mode and seed), ``DIR/budget.md`` and
``DIR/budget.html`` with one tornado chart per figure (``DIR/figures``).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from calib.errors import UscalError

from . import progress as progress_report
from .error_sources import ERROR_SOURCES, ErrorSource, value_at
from .output import make_directory, write_text_atomic
from .report import report_html
from .scenario import Scenario, load_scenario
from .sweep import as_completed, code_version, executor

__all__ = [
    "FIGURES",
    "BudgetError",
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
    "image_mm": "T_ee_us true error over the image, single marker (mm)",
    "rotation_deg": "T_ee_us true rotation error, single marker (°)",
    "translation_mm": "T_ee_us true translation error, single marker (mm)",
    "cone_mae_mm": "cone MAE after ICP, single marker (mm)",
    "prism_mae_mm": "prism MAE after ICP, single marker (mm)",
}
MODES = ("none", "alone", "all_but", "all")


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
        doc = {
            "code": code_version(),
            "base": self.base_text,
            "base_overrides": list(self.base_overrides),
            "overrides": effective,
            "seed": run.seed,
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


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
    its true errors; no tool precision or reconstruction (NaN).
    """
    nan = float("nan")
    out = dict.fromkeys(FIGURES, nan)
    ev = metrics.get("evaluation", {})
    if "single" in ev:
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


def run_budget_point(
    base: str | None, base_overrides: Sequence[str], overrides: Sequence[tuple[str, Any]], seed: int
) -> dict[str, Any]:
    """One budget run (in a worker): the scenario with the overrides and seed, run whole
    (serially: the budget's executor is the parallelism), reduced to :data:`FIGURES`. A
    failure is recorded, not raised (a source may make a calibration impossible)."""
    from .run import run

    try:
        sets = [*base_overrides, *(f"{k}={json.dumps(v)}" for k, v in overrides), f"seed={seed}"]
        scenario = load_scenario(base, sets)
        scenario = replace(scenario, evaluation=replace(scenario.evaluation, workers=1))
        t0 = time.perf_counter()
        with progress_report.reporting(None):
            result = run(scenario)
        return {"figures": budget_figures(result.metrics), "seconds": time.perf_counter() - t0}
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}


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


def run_budget(
    spec: BudgetSpec,
    out: str | os.PathLike[str],
    scheduler: str | None = None,
    workers: int | None = None,
) -> BudgetResult:
    """Run what is not cached in ``out/points`` (local pool of ``workers``, default one
    per core, or the Dask cluster at ``scheduler``), then write ``budget.csv``,
    ``budget.md``, ``budget.html`` and the tornado charts."""
    t0 = time.perf_counter()
    out = Path(out)
    make_directory(out / "points")
    runs = spec.runs()
    keys = [spec.run_key(r) for r in runs]
    done: dict[str, dict[str, Any]] = {}
    todo: dict[str, BudgetRun] = {}
    for run, key in zip(runs, keys, strict=True):
        cached = out / "points" / f"{key}.json"
        if key in done or key in todo:
            continue
        if cached.is_file():
            done[key] = json.loads(cached.read_text(encoding="utf-8"))
        else:
            todo[key] = run
    n_cached = len(done)
    total = n_cached + len(todo)
    progress_report.report("budget runs", n_cached, total)
    if todo:
        submit, close = executor(scheduler, workers)
        base = None if spec.base is None else str(spec.base)
        try:
            futures = {
                submit(run_budget_point, base, spec.base_overrides, run.overrides, run.seed): key
                for key, run in todo.items()
            }
            for future in as_completed(futures, scheduler is not None):
                key = futures[future]
                run = todo[key]
                doc = {"overrides": [[k, v] for k, v in run.overrides], "seed": run.seed}
                doc.update(future.result())
                write_text_atomic(out / "points" / f"{key}.json", json.dumps(doc, indent=1))
                done[key] = doc
                progress_report.report("budget runs", len(done), total)
        finally:
            close()
    ordered = [(r, done[k]) for r, k in zip(runs, keys, strict=True)]
    write_text_atomic(out / "budget.csv", budget_csv(ordered))
    md = budget_markdown(spec, ordered, out)
    write_text_atomic(out / "budget.md", md)
    write_text_atomic(out / "budget.html", report_html(md, "uscal error budget"))
    failed = sum("error" in d for d in done.values())
    return BudgetResult(spec, ordered, len(todo), n_cached, failed, time.perf_counter() - t0)


def budget_csv(runs: Sequence[tuple[BudgetRun, dict[str, Any]]]) -> str:
    """One row per (source, mode, seed): the figures, and the error of a failed run."""
    lines = [",".join(["source", "mode", "seed", *FIGURES, "error"])]
    for run, doc in runs:
        figs = doc.get("figures", {})
        cells = [run.source, run.mode, str(run.seed)]
        cells += [_fmt(figs.get(f)) for f in FIGURES]
        error = doc.get("error", "")
        cells.append('"' + error.replace('"', "'") + '"' if error else "")
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def _fmt(v: Any) -> str:
    if v is None or not np.isfinite(v):
        return "nan"
    return f"{v:.6g}"


def budget_medians(
    runs: Sequence[tuple[BudgetRun, dict[str, Any]]],
) -> dict[tuple[str, str], dict[str, float]]:
    """Median over seeds of each figure, per (source, mode)."""
    groups: dict[tuple[str, str], list[dict[str, float]]] = {}
    for run, doc in runs:
        if "figures" in doc:
            groups.setdefault((run.source, run.mode), []).append(doc["figures"])
    out = {}
    for key, docs in groups.items():
        out[key] = {}
        for f in FIGURES:
            x = np.array([d[f] for d in docs], dtype=float)
            out[key][f] = float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else np.nan
    return out


def tornado_rows(
    spec: BudgetSpec, med: dict[tuple[str, str], dict[str, float]], figure: str
) -> list[tuple[str, float, float]]:
    """Per source present in the scenario: (name, what it adds alone to the error-free
    rig, what removing it from the full scenario saves), in the figure's unit, largest
    first."""
    none = med.get(("-", "none"), {}).get(figure, np.nan)
    full = med.get(("-", "all"), {}).get(figure, np.nan)
    rows = []
    for s in spec.sources:
        if not s.present_in(spec.scenario):
            continue
        alone = med.get((s.name, "alone"), {}).get(figure, np.nan) - none
        saved = full - med.get((s.name, "all_but"), {}).get(figure, np.nan)
        rows.append((s.name, alone, saved))
    return sorted(rows, key=lambda r: -np.nanmax([abs(r[1]), abs(r[2]), 0.0]))


def _tornado(name: str, rows: list[tuple[str, float, float]], none: float, full: float, path):
    """Tornado chart: per source, a bar from the error-free rig's value to the value with
    the source alone (right of the floor line), and one from the full scenario's value
    down to the value without the source; sources sorted by effect, largest on top."""
    fig = Figure(figsize=(6.4, 1.1 + 0.36 * max(len(rows), 1)), layout="constrained")
    ax = fig.subplots()
    if not rows:
        ax.text(0.5, 0.5, "no source present in this scenario", ha="center",
                transform=ax.transAxes)  # fmt: skip
    y = np.arange(len(rows))[::-1]
    for yi, (_, alone, saved) in zip(y, rows, strict=True):
        if np.isfinite(alone):
            ax.barh(yi + 0.18, alone, left=none, height=0.34, color="#4c72b0")
        if np.isfinite(saved):
            ax.barh(yi - 0.18, -saved, left=full, height=0.34, color="#dd8452")
    ax.axvline(none, color="#4c72b0", lw=1, ls="--")
    ax.axvline(full, color="#dd8452", lw=1, ls="--")
    ax.set_yticks(y, [r[0] for r in rows])
    ax.set_xlabel(FIGURES[name])
    handles = [
        Patch(color="#4c72b0", label=f"source alone, from every source off ({none:.3g}, dashed)"),
        Patch(
            color="#dd8452", label=f"scenario without the source, from the scenario ({full:.3g})"
        ),
    ]
    fig.legend(handles=handles, fontsize=7, loc="outside upper center", ncols=1)
    fig.savefig(path, dpi=100)


def budget_markdown(
    spec: BudgetSpec, runs: Sequence[tuple[BudgetRun, dict[str, Any]]], out: Path
) -> str:
    """The budget page (its tornado charts written into ``out/figures``)."""
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    med = budget_medians(runs)
    failed = [(r, d) for r, d in runs if "error" in d]
    name = spec.base.name if spec.base is not None else "the built-in scenario"
    sets = f" with `{' '.join(spec.base_overrides)}`" if spec.base_overrides else ""
    lines = [
        "# Error budget",
        "",
        f"Scenario `{name}`{sets}; seeds {', '.join(map(str, spec.seeds))}. Each source is "
        "run *alone* on an error-free rig (every other source off) and left out of the full "
        "scenario (*all but*). Figures are medians over the seeds; every run is in "
        "`budget.csv`."
        + (
            " With one seed there is no spread to judge by: differences of the order of the "
            "figure's seed-to-seed spread are noise (`--seeds 3` shows it)."
            if len(spec.seeds) == 1
            else ""
        ),
        "",
        "| source | what | keys (value in the scenario → off) | in the scenario |",
        "|---|---|---|---|",
    ]
    for s in spec.sources:
        keys = "; ".join(
            f"`{k}` {json.dumps(_plain(value_at(spec.scenario, k)))} → {json.dumps(v)}"
            for k, v in s.off
        )
        lines.append(
            f"| {s.name} | {s.title} | {keys} | {'on' if s.present_in(spec.scenario) else 'off'} |"
        )
    lines.append("")
    if failed:
        lines += [f"**{len(failed)} run(s) failed** (their figures are left out):", ""]
        lines += [f"- {r.source} / {r.mode} / seed {r.seed}: {d['error']}" for r, d in failed]
        lines.append("")
    none = med.get(("-", "none"), {})
    full = med.get(("-", "all"), {})
    for figure, label in FIGURES.items():
        if not (np.isfinite(none.get(figure, np.nan)) or np.isfinite(full.get(figure, np.nan))):
            continue  # not measured by this scenario (e.g. no reconstruction)
        rows = tornado_rows(spec, med, figure)
        png = f"tornado_{figure}.png"
        _tornado(figure, rows, none.get(figure, np.nan), full.get(figure, np.nan), fig_dir / png)
        lines += [f"## {label}", ""]
        lines += [
            f"Every source off: **{none.get(figure, np.nan):.3g}**; the scenario: "
            f"**{full.get(figure, np.nan):.3g}**."
            + (f" Largest: **{rows[0][0]}**." if rows else ""),
            "",
            f"![tornado chart of {label}](figures/{png})",
            "",
            "| source | alone: added to the error-free rig | all but: saved by removing it |",
            "|---|---:|---:|",
        ]
        lines += [f"| {n} | {a:+.3g} | {s:+.3g} |" for n, a, s in rows]
        lines.append("")
    return "\n".join(lines)


def _plain(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v
