"""A budget's files: ``budget.csv`` (one row per run), ``budget.md`` / ``budget.html``
(the medians per source and mode, the failures) and the tornado charts in
``figures/``."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from ..config.error_sources import value_at
from ..files import write_text_atomic
from ..jobs.budget import FIGURES, BudgetOutcome, BudgetResult, BudgetRun, BudgetSpec
from ..tables import Table, left, right
from .report import report_html

__all__ = [
    "budget_csv",
    "budget_markdown",
    "budget_medians",
    "declared_mount_error",
    "sources_table",
    "tornado_rows",
    "tornado_table",
    "write_budget",
]


Runs = Sequence[tuple[BudgetRun, dict[str, Any] | BudgetOutcome]]


def _outcomes(runs: Runs) -> list[tuple[BudgetRun, BudgetOutcome]]:
    """The grid's documents as :class:`~bench.jobs.budget.BudgetOutcome`."""
    return [
        (r, d if isinstance(d, BudgetOutcome) else BudgetOutcome.from_document(d)) for r, d in runs
    ]


def budget_csv(runs: Runs) -> str:
    """One row per (source, mode, seed): the figures, and the error of a failed run."""
    lines = [",".join(["source", "mode", "seed", *FIGURES, "error"])]
    for run, outcome in _outcomes(runs):
        cells = [run.source, run.mode, str(run.seed)]
        cells += [_fmt(outcome.figure(f)) for f in FIGURES]
        error = outcome.error or ""
        cells.append('"' + error.replace('"', "'") + '"' if error else "")
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def _fmt(v: Any) -> str:
    if v is None or not np.isfinite(v):
        return "nan"
    return f"{v:.6g}"


def budget_medians(runs: Runs) -> dict[tuple[str, str], dict[str, float]]:
    """Median over seeds of each figure, per (source, mode)."""
    groups: dict[tuple[str, str], list[BudgetOutcome]] = {}
    for run, outcome in _outcomes(runs):
        if outcome.figures is not None:
            groups.setdefault((run.source, run.mode), []).append(outcome)
    out = {}
    for key, outcomes in groups.items():
        out[key] = {}
        for f in FIGURES:
            x = np.array([o.figure(f) for o in outcomes], dtype=float)
            out[key][f] = float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else np.nan
    return out


def declared_mount_error(runs: Runs) -> tuple[float, float] | None:
    """The rig's own mount error a budget measures, as ``calibration.mount_error_mm`` and
    ``mount_error_deg`` declare it (1 σ per axis, mm and degrees): per seed, the true
    translation and rotation errors of ``T_ee_us`` the scenario's sources add to the
    error-free rig, √(scenario² − every source off²); their rms over the seeds, over √3
    (three axes). An upper estimate of what no view shows: it holds the part the data's
    own scatter shows too. None without a seed that ran both."""
    by_seed: dict[int, dict[str, BudgetOutcome]] = {}
    for run, outcome in _outcomes(runs):
        if run.source == "-" and outcome.figures is not None:
            by_seed.setdefault(run.seed, {})[run.mode] = outcome
    pairs = [d for d in by_seed.values() if {"all", "none"} <= d.keys()]

    def added(figure: str) -> float:
        a = np.array([d["all"].figure(figure) for d in pairs])
        n = np.array([d["none"].figure(figure) for d in pairs])
        ok = np.isfinite(a) & np.isfinite(n)
        return float(np.sqrt(np.mean(np.maximum(a[ok] ** 2 - n[ok] ** 2, 0.0)) / 3.0))

    if not pairs:
        return None
    mm, deg = added("translation_mm"), added("rotation_deg")
    return (mm, deg) if np.isfinite(mm) and np.isfinite(deg) else None


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


def sources_table(spec: BudgetSpec) -> Table:
    """The error sources: what each is, the keys that switch it off (their value in the
    scenario → off) and whether the scenario has it on."""
    rows = []
    for s in spec.sources:
        keys = "; ".join(
            f"`{k}` {json.dumps(_plain(value_at(spec.scenario, k)))} → {json.dumps(v)}"
            for k, v in s.off
        )
        rows.append((s.name, s.title, keys, "on" if s.present_in(spec.scenario) else "off"))
    columns = left("source", "what", "keys (value in the scenario → off)", "in the scenario")
    return Table(columns, tuple(rows), "error sources")


def tornado_table(rows: list[tuple[str, float, float]], label: str) -> Table:
    """:func:`tornado_rows` of one figure: per source what it adds alone and what
    removing it saves (the figure's unit), largest first."""
    columns = (
        *left("source"),
        *right("alone: added to the error-free rig", "all but: saved by removing it"),
    )
    cells = tuple((n, f"{a:+.3g}", f"{s:+.3g}") for n, a, s in rows)
    return Table(columns, cells, label)


def budget_markdown(spec: BudgetSpec, runs: Runs, out: Path) -> str:
    """The budget page (its tornado charts written into ``out/figures``)."""
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    runs = _outcomes(runs)
    med = budget_medians(runs)
    failed = [(r, o) for r, o in runs if o.error is not None]
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
        sources_table(spec).markdown(),
        "",
    ]
    declare = declared_mount_error(runs)
    if declare is not None:
        lines += [
            f"**Declare `calibration.mount_error_mm: {declare[0]:.2f}` and `mount_error_deg: "
            f"{declare[1]:.2f}`** for this rig: the true translation and rotation errors of "
            "`T_ee_us` its sources add to the error-free rig (rms over the seeds of "
            "√(scenario² − every source off²), per axis). They are the same in every sweep "
            "and no view shows them; declared, the calibrations' 95 % bounds carry them (an "
            "upper estimate: it holds the part their own scatter shows too).",
            "",
        ]
    if failed:
        lines += [f"**{len(failed)} run(s) failed** (their figures are left out):", ""]
        lines += [f"- {r.source} / {r.mode} / seed {r.seed}: {o.error}" for r, o in failed]
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
            tornado_table(rows, label).markdown(),
            "",
        ]
    return "\n".join(lines)


def write_budget(out: str | Path, result: BudgetResult) -> list[Path]:
    """``budget.csv``, ``budget.md``, ``budget.html`` and the tornado charts of a
    finished budget."""
    out = Path(out)
    write_text_atomic(out / "budget.csv", budget_csv(result.runs))
    md = budget_markdown(result.spec, result.runs, out)
    write_text_atomic(out / "budget.md", md)
    write_text_atomic(out / "budget.html", report_html(md, "uscal error budget"))
    return [out / "budget.csv", out / "budget.md", out / "budget.html"]


def _plain(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v
