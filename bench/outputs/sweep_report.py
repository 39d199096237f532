"""``results.csv`` and ``sweep.html``: a sweep's results per grid key and localizer —
localization error (median and spread), detection failures, calibration error — with its
figures in ``DIR/figures``."""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from ..files import write_text_atomic
from ..jobs.sweep import LOCALIZATION_METRICS, SweepPoint, SweepResult, SweepSpec
from ..tables import Column, Table, left
from .report import report_html

__all__ = [
    "median_table",
    "results_csv",
    "spread_table",
    "sweep_html",
    "sweep_table",
    "write_sweep",
]

_METRICS = {
    "localization_median_error_mm": "localization error, median over sweeps (mm)",
    "rejected_fraction": "sweeps without a detection (share)",
    "false_acceptances": "accepted centres > 1 mm from the truth (count)",
    "localization_max_error_mm": "localization error, worst accepted sweep (mm)",
    "calibration_image_mm": "calibration: true image error (mm)",
    "calibration_false_acceptances": "calibration: centres kept > 1 mm from the truth (count)",
    "calibration_dropped": "calibration: localizer-accepted centres it dropped (count)",
    "calibration_bound_image_mm": "calibration: 95 % bound on the image error (mm)",
    "calibration_bound_covers": "calibration: the bound covers the true image error",
    "calibration_verdict": "calibration: its verdict (accepted, suspect, rejected)",
    "calibration_verdict_reasons": "calibration: why (the verdict's reasons)",
}
#: The calibrate stage's figures, in the order ``results.csv`` lists them.
_CALIBRATION_METRICS = (
    "calibration_image_mm",
    "calibration_false_acceptances",
    "calibration_dropped",
    "calibration_bound_image_mm",
    "calibration_bound_covers",
    "calibration_verdict",
    "calibration_verdict_reasons",
)


def _points(points: Sequence[dict[str, Any] | SweepPoint]) -> list[SweepPoint]:
    """The grid's documents as :class:`~bench.jobs.sweep.SweepPoint`."""
    return [p if isinstance(p, SweepPoint) else SweepPoint.from_document(p) for p in points]


def sweep_table(points: Sequence[dict[str, Any] | SweepPoint], key: str, metric: str):
    """{method: (values, median, 25th, 75th percentile)} of ``metric`` against the grid
    key ``key``, pooling seeds and the other keys."""
    by: dict[str, dict[Any, list[float]]] = {}
    for point in _points(points):
        value = point.override(key)
        if not isinstance(value, (int, float, str, bool)):
            value = json.dumps(value)  # lists (e.g. protocol.spheres) as their text
        for row in point.rows:
            x = row.figure(metric)
            if x is None:
                continue
            by.setdefault(row.method, {}).setdefault(value, []).append(float(x))
    out = {}
    for method, groups in by.items():
        values = sorted(groups)
        stats = [
            np.nanpercentile(groups[v], [50, 25, 75]) if np.isfinite(groups[v]).any() else
            np.full(3, np.nan)
            for v in values
        ]  # fmt: skip
        out[method] = (values, *np.array(stats).T)
    return out


def _figure(points, key: str, metric: str, path: Path) -> None:
    fig = Figure(figsize=(5.2, 3.2), layout="constrained")
    ax = fig.subplots()
    table = sweep_table(points, key, metric)
    if not table:
        ax.text(0.5, 0.5, "no results (every point failed)", ha="center", transform=ax.transAxes)
    for method, (values, med, lo, hi) in table.items():
        x = np.asarray(values, dtype=float)
        ax.plot(x, med, "o-", label=method)
        ax.fill_between(x, lo, hi, alpha=0.2)
    ax.set_xlabel(key)
    ax.set_ylabel(_METRICS[metric])
    if metric == "localization_median_error_mm":
        ax.set_yscale("log")
    if table:
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


def _scatter(points, key: str, metric: str, path: Path) -> None:
    """``metric`` at every drawn point against its value of ``key``, per localizer."""
    fig = Figure(figsize=(5.2, 3.2), layout="constrained")
    ax = fig.subplots()
    by: dict[str, list[tuple[float, float]]] = {}
    for point in _points(points):
        value = point.override(key)
        for row in point.rows:
            x = row.figure(metric)
            if x is not None and isinstance(value, (int, float)):
                by.setdefault(row.method, []).append((float(value), float(x)))
    if not by:
        ax.text(0.5, 0.5, "no results (every point failed)", ha="center", transform=ax.transAxes)
    for method, xy in by.items():
        a = np.array(xy)
        ax.plot(a[:, 0], a[:, 1], "o", ms=4, alpha=0.7, label=method)
    ax.set_xlabel(key)
    ax.set_ylabel(_METRICS[metric])
    if metric == "localization_median_error_mm" and by:
        ax.set_yscale("log")
    if by:
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


def spread_table(points: Sequence[dict[str, Any] | SweepPoint], metric: str) -> Table | None:
    """``metric``'s spread over the points per localizer (rows): the points with a value,
    its minimum, 10th percentile, median, 90th percentile, maximum (and the total of a
    count): what a sweep of drawn conditions reports."""
    by: dict[str, list[float]] = {}
    for point in _points(points):
        for row in point.rows:
            x = row.figure(metric)
            if x is not None:
                by.setdefault(row.method, []).append(float(x))
    if not by:
        return None
    heads = ("points", "min", "10th", "median", "90th", "max")
    count = metric in ("false_acceptances", "calibration_false_acceptances")
    rows = []
    for method, xs in by.items():
        a = np.array(xs)
        ok = a[np.isfinite(a)]
        q = np.percentile(ok, [0, 10, 50, 90, 100]) if len(ok) else np.full(5, np.nan)
        rows.append(
            (
                method,
                str(len(ok)),
                *(f"{v:.3g}" for v in q),
                *((f"{ok.sum():.0f}",) if count else ()),
            )
        )
    columns = (
        *left("method"),
        *(Column(h, "right") for h in (*heads, *(("total",) if count else ()))),
    )
    return Table(columns, tuple(rows), f"{_METRICS[metric]}, over the points")


def median_table(points: Sequence[SweepPoint], key: str, metric: str) -> Table | None:
    """The median of ``metric`` per localizer (rows) and value of the grid key ``key``
    (columns); None when no point measured it."""
    table = sweep_table(points, key, metric)
    if not table:
        return None
    values = next(iter(table.values()))[0]
    rows = tuple((method, *(f"{m:.3g}" for m in med)) for method, (_, med, _, _) in table.items())
    columns = (*left("method"), *(Column(str(v), "right") for v in values))
    return Table(columns, rows, f"{_METRICS[metric]}, median")


def sweep_html(spec, points: Sequence[dict[str, Any] | SweepPoint], out: Path) -> str:
    """The page (and its figures, written into ``out/figures``)."""
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    metrics = ["localization_median_error_mm", "rejected_fraction", "false_acceptances"]
    if "calibrate" in spec.stages:
        metrics.append("calibration_image_mm")
    points = _points(points)
    failed = [p for p in points if p.error is not None]
    refused = [p for p in points if p.refused is not None]
    false_total = {
        m: sum(r.false_acceptances or 0 for p in points for r in p.rows if r.method == m)
        for m in spec.methods
    }
    drawn = spec.draws is not None
    what = (
        f"{spec.describe()}; each figure shows every point against one key"
        if drawn
        else f"{len(points)} points "
        f"({' × '.join(f'{len(v)} {k}' for k, v in spec.grid.items()) or 'no grid'}, "
        f"{len(spec.seeds)} seeds)"
    )
    lines = [
        "# uscal sweep",
        "",
        f"`{spec.source}`: base `{spec.base.name}`, {what}, stages {', '.join(spec.stages)}, "
        f"localizers {', '.join(spec.methods)}."
        + (
            ""
            if drawn
            else " Lines: median over seeds and the other keys; bands: 25th-75th percentile."
        )
        + " Every row is in `results.csv`.",
        "",
        "Accepted centres more than 1 mm from the truth, over the whole grid: "
        + ", ".join(f"{m} **{n}**" for m, n in false_total.items())
        + ".",
        "",
    ]
    if "calibrate" in spec.stages:
        kept = {
            m: sum(
                r.calibration_false_acceptances or 0
                for p in points
                for r in p.rows
                if r.method == m
            )
            for m in spec.methods
        }
        lines += [
            "Centres the calibrations kept (the localizer with the estimated mount) more "
            "than 1 mm from the truth: " + ", ".join(f"{m} **{n}**" for m, n in kept.items()) + ".",
            "",
        ]
        verdicts = {
            m: Counter(
                r.calibration_verdict
                for p in points
                for r in p.rows
                if r.method == m and r.calibration_verdict
            )
            for m in spec.methods
        }
        bounds = {
            m: [
                r.calibration_bound_covers
                for p in points
                for r in p.rows
                if r.method == m and r.calibration_bound_covers is not None
            ]
            for m in spec.methods
        }
        if any(bounds.values()):
            lines += [
                "95 % bounds on the image error that cover the true error: "
                + ", ".join(f"{m} **{sum(b)} of {len(b)}**" for m, b in bounds.items() if b)
                + ".",
                "",
            ]
        if any(verdicts.values()):
            lines += [
                "The calibrations' verdicts (on their 95 % bounds): "
                + "; ".join(
                    f"{m}: " + ", ".join(f"{n} {v}" for v, n in sorted(c.items()))
                    for m, c in verdicts.items()
                    if c
                )
                + ".",
                "",
            ]
    if refused:
        lines += [
            f"{len(refused)} point(s) refused before anything moved (the plan collides or "
            "is out of reach at that condition):",
            "",
        ]
        lines += [
            f"- {[list(o) for o in p.overrides]}, seed {p.seed}: {p.refused}" for p in refused
        ]
        lines.append("")
    if failed:
        lines += [f"**{len(failed)} point(s) failed**:", ""]
        # The overrides as the point's document lists them: [[key, value], ...].
        lines += [f"- {[list(o) for o in p.overrides]}, seed {p.seed}: {p.error}" for p in failed]
        lines.append("")
    if drawn:
        # Drawn conditions: the spread over the points is the result.
        lines += ["## The spread over the drawn points", ""]
        for metric in [*metrics, "localization_max_error_mm"]:
            table = spread_table(points, metric)
            if table is not None:
                lines += [f"{table.title}:", "", table.markdown(), ""]
    for entry, values in spec.varied().items():
        if len(set(map(json.dumps, values))) < 2:
            continue  # a fixed setting, not a varied one
        # Linked keys (set together) are shown against the first.
        key = entry.split(",")[0].strip()
        values = [v[0] if "," in entry else v for v in values]
        lines += [f"## {entry}", ""]
        numeric = all(isinstance(v, (int, float)) for v in values)
        for metric in metrics if numeric else []:
            name = f"{key.replace('.', '_')}__{metric}.png"
            (_scatter if drawn else _figure)(points, key, metric, fig_dir / name)
            lines += [f"![{_METRICS[metric]} vs {key}](figures/{name})", ""]
        for metric in [] if drawn and numeric else metrics:
            table = median_table(points, key, metric)
            if table is not None:
                lines += [f"{table.title}:", "", table.markdown(), ""]
    return report_html("\n".join(lines), "uscal sweep")


def results_csv(spec: SweepSpec, points: Sequence[dict[str, Any] | SweepPoint]) -> str:
    """One row per point, seed and method: the grid keys (named by key path), then
    seed, method and the metrics; a failed point gives one row per method with the
    error."""
    keys = spec.override_keys()
    metrics = list(LOCALIZATION_METRICS)
    if "calibrate" in spec.stages:
        metrics += _CALIBRATION_METRICS
    lines = [",".join([*keys, "seed", "method", *metrics, "error"])]
    for point in _points(points):
        values = [json.dumps(v) if not isinstance(v, str) else v for _, v in point.overrides]
        # A failed point: one row per method, its figures empty.
        rows = [(r.method, r) for r in point.rows] or [(m, None) for m in spec.methods]
        for method, row in rows:
            cells = [*values, str(point.seed), method]
            cells += [_fmt(row.figure(m) if row is not None else None) for m in metrics]
            error = (
                point.error
                or (f"refused: {point.refused}" if point.refused else None)
                or (row.calibration_error if row is not None else None)
                or ""
            )
            cells.append(_quoted(error) if error else "")
            lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if not np.isfinite(v) else f"{v:.6g}"
    if isinstance(v, str) and ("," in v or '"' in v):
        return _quoted(v)  # a verdict's reasons: one cell
    return str(v)


def _quoted(text: str) -> str:
    """``text`` as one CSV cell (its own double quotes made single)."""
    return '"' + text.replace('"', "'") + '"'


def write_sweep(out: str | Path, result: SweepResult) -> list[Path]:
    """``results.csv`` and ``sweep.html`` (with its figures) of a finished sweep."""
    out = Path(out)
    write_text_atomic(out / "results.csv", results_csv(result.spec, result.points))
    write_text_atomic(out / "sweep.html", sweep_html(result.spec, result.points, out))
    return [out / "results.csv", out / "sweep.html"]
