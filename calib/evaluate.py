"""The paper's evaluation protocol (paper, "Evaluation protocol", Tables I and II).

For each dataset, with the DH model refined from the *other* datasets' touches held fixed:

- four **single-marker** folds: calibrate on one sphere, test on the other three;
- four **three-marker** folds: calibrate on three spheres, test on the fourth.

Metrics, exactly as the paper defines them:

- **tool precision**: per cone vertex, the mean distance of its touch tip positions from
  their centroid (one sample per vertex: four per set);
- **sphere precision**: per test sphere, the mean distance of its retained reconstructed
  centres from their centroid;
- **sphere accuracy**: per test sphere, the distance of that centroid from the touch
  reference centre.

A single-marker fold contributes one sample per metric (the mean over its three test
spheres), a three-marker fold the result of its one test sphere: four samples per set,
twelve overall. Each set reports MAE ± SD (sample SD) and RMSE over its samples.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from . import se3
from .calibrate import AlternationResult, alternate, reconstruct, robust_inliers
from .errors import CalibrationError
from .localization import LocalizerConfig, SweepLocalization
from .localize import localize_sphere
from .records import Sweep

__all__ = [
    "METHOD_TITLES",
    "Fold",
    "FoldResult",
    "PaperTable",
    "Summary",
    "base_centres",
    "evaluate_fold",
    "folds",
    "format_table_iii_csv",
    "format_table_iii_markdown",
    "format_tables_csv",
    "format_tables_markdown",
    "localize_test_sphere",
    "sphere_metrics",
    "summarize",
    "table_iii",
    "tables_i_ii",
]

Array = NDArray[np.float64]
_MM = 1e3

Kind = Literal["single", "three"]


@dataclass(frozen=True)
class Fold:
    """One calibration/test split of a dataset's spheres."""

    dataset: str
    kind: Kind
    train: tuple[str, ...]
    test: tuple[str, ...]

    @property
    def name(self) -> str:
        return f"{self.dataset}/{self.kind}/{'+'.join(self.train)}"


def folds(dataset: str, spheres: Sequence[str]) -> list[Fold]:
    """The paper's complementary splits of one dataset: for n spheres, n single-marker
    folds (train one, test the rest) then n leave-one-out folds (train the rest, test one;
    "three-marker" for the paper's four spheres)."""
    spheres = tuple(spheres)
    if len(spheres) < 2:
        raise CalibrationError(f"the evaluation needs at least 2 spheres, got {len(spheres)}")
    out = []
    for s in spheres:
        out.append(Fold(dataset, "single", (s,), tuple(x for x in spheres if x != s)))
    for s in spheres:
        out.append(Fold(dataset, "three", tuple(x for x in spheres if x != s), (s,)))
    return out


@dataclass(frozen=True, eq=False)
class FoldResult:
    """A fold's calibration and its test-sphere metrics.

    ``centres[s]`` holds the retained reconstructed centres (n, 3) of test sphere s in the
    base frame (accepted by the localizer and passing the calibration's outlier test);
    ``precision_mm[s]`` / ``accuracy_mm[s]`` its metrics; ``precision`` and ``accuracy``
    are the fold's samples (means over its test spheres).
    """

    fold: Fold
    alternation: AlternationResult
    centres: dict[str, Array]
    precision_mm: dict[str, float]
    accuracy_mm: dict[str, float]
    test_localizations: dict[str, list[SweepLocalization]] = field(repr=False)

    @property
    def T_ee_us(self) -> Array:
        return self.alternation.result.T_ee_us

    @property
    def precision(self) -> float:
        return float(np.mean(list(self.precision_mm.values())))

    @property
    def accuracy(self) -> float:
        return float(np.mean(list(self.accuracy_mm.values())))


def base_centres(
    sweeps: Sequence[Sweep], locs: Sequence[SweepLocalization], T_ee_us: Array
) -> Array:
    """Base-frame centres (n, 3) of a sphere's sweeps under a calibration (NaN where the
    localization rejected the sweep)."""
    return np.array(
        [
            se3.apply(s.T_base_ee[s.reference_index] @ T_ee_us, loc.centre)
            for s, loc in zip(sweeps, locs, strict=True)
        ]
    ).reshape(-1, 3)


def sphere_metrics(points: Array, reference: Array) -> tuple[float, float]:
    """(precision mm, accuracy mm) of one test sphere's retained base-frame centres
    against its reference centre."""
    pts = points
    if len(pts) == 0:
        return float("nan"), float("nan")
    centroid = pts.mean(axis=0)
    precision = float(np.mean(np.linalg.norm(pts - centroid, axis=1))) * _MM
    accuracy = float(np.linalg.norm(centroid - reference)) * _MM
    return precision, accuracy


def localize_test_sphere(
    sweeps: Sequence[Sweep],
    initial: Sequence[SweepLocalization],
    T_ee_us: Array,
    radius: float,
    localizer: LocalizerConfig,
    axial_scale: float,
    outlier_mm: float = 2.0,
) -> tuple[list[SweepLocalization], NDArray[np.bool_]]:
    """Re-stack and localize a test sphere's sweeps under a fold's calibration and
    decide which centres are retained (accepted and passing the calibration's outlier
    test about their centroid). Sweeps are searched around their first centres; those
    that end up outliers are searched again over the whole grid before the final
    decision, so a false first detection cannot stick."""
    locs = localize_sphere(sweeps, T_ee_us, radius, localizer, axial_scale, initial)

    def retained(locs: Sequence[SweepLocalization]) -> NDArray[np.bool_]:
        P = base_centres(sweeps, locs, T_ee_us)
        ok = np.array([loc.accepted for loc in locs])
        keep = np.zeros(len(locs), dtype=bool)
        if ok.any():
            keep[ok] = robust_inliers(P[ok], outlier_mm)
        return keep

    keep = retained(locs)
    if not keep.all():
        seeds = [loc if k else None for loc, k in zip(locs, keep, strict=True)]
        locs = localize_sphere(sweeps, T_ee_us, radius, localizer, axial_scale, seeds)
        keep = retained(locs)
    return locs, keep


def evaluate_fold(
    fold: Fold,
    sweeps: Mapping[str, Sequence[Sweep]],
    initial: Mapping[str, Sequence[SweepLocalization]],
    references: Mapping[str, Array],
    radius: float,
    localizer: LocalizerConfig,
    axial_scale: float,
    cad_centres: Mapping[str, Array],
    T_coarse: Array | None,
    max_iterations: int,
    layout_sigma_mm: float = 0.0,
) -> FoldResult:
    """Calibrate on the fold's training spheres (alternating localization and
    calibration, from the shared first localization ``initial``), then re-stack and
    localize its test spheres with the result and score them against ``references``
    (base-frame touch-reference centres). ``layout_sigma_mm``: the print tolerance the
    multi-marker folds estimate the printed layout with (0: the CAD layout as exact)."""
    alt = alternate(
        {t: sweeps[t] for t in fold.train},
        radius,
        localizer,
        axial_scale,
        cad_centres if len(fold.train) >= 2 else None,
        T_coarse,
        max_iterations,
        initial={t: initial[t] for t in fold.train},
        layout_sigma_mm=layout_sigma_mm,
    )
    T = alt.result.T_ee_us
    centres, precision, accuracy, test_locs = {}, {}, {}, {}
    for t in fold.test:
        locs, keep = localize_test_sphere(sweeps[t], initial[t], T, radius, localizer, axial_scale)
        test_locs[t] = locs
        centres[t] = base_centres(sweeps[t], locs, T)[keep]
        precision[t], accuracy[t] = sphere_metrics(centres[t], references[t])
    return FoldResult(fold, alt, centres, precision, accuracy, test_locs)


def training_precision(alt: AlternationResult) -> dict[str, float]:
    """Per training sphere: mean distance of its retained centres from their centroid."""
    X = reconstruct(alt.observations, alt.result.T_ee_us)
    keep = alt.result.retained
    out = {}
    for t in dict.fromkeys(o.target for o in alt.observations):
        idx = [i for i, o in enumerate(alt.observations) if o.target == t and keep[i]]
        out[t] = float(np.mean(np.linalg.norm(X[idx] - X[idx].mean(axis=0), axis=1))) * _MM
    return out


# ----------------------------------------------------------------------------- tables


@dataclass(frozen=True)
class Summary:
    """MAE ± SD and RMSE of one metric's samples; ``n`` samples."""

    mae: float
    sd: float
    rmse: float
    n: int

    def as_dict(self) -> dict[str, float]:
        return {"mae": self.mae, "sd": self.sd, "rmse": self.rmse, "n": self.n}


def _summary(samples: Sequence[float]) -> Summary:
    x = np.asarray([v for v in samples if np.isfinite(v)], dtype=float)
    if len(x) == 0:
        return Summary(float("nan"), float("nan"), float("nan"), 0)
    sd = float(np.std(x, ddof=1)) if len(x) > 1 else float("nan")
    return Summary(float(np.mean(np.abs(x))), sd, float(np.sqrt(np.mean(x**2))), len(x))


def summarize(samples: Mapping[str, Sequence[float]]) -> dict[str, Summary]:
    """Per set and ``overall`` (all samples pooled), in the sets' order."""
    out = {k: _summary(v) for k, v in samples.items()}
    out["overall"] = _summary([x for v in samples.values() for x in v])
    return out


#: Rows of the paper's tables: (metrics.json key, label).
TABLE_ROWS: dict[str, tuple[tuple[str, str], ...]] = {
    "single": (
        ("tool_precision_mm", "Tool prec."),
        ("sphere_precision_mm", "Sphere prec."),
        ("sphere_accuracy_mm", "Sphere acc."),
    ),
    "three": (
        ("sphere_precision_mm", "Sphere prec."),
        ("sphere_accuracy_mm", "Sphere acc."),
    ),
}
TABLE_TITLES = {
    "single": "Table I. Single-marker calibration errors (mm).",
    "three": "Table II. Three-marker calibration errors (mm).",
}


@dataclass(frozen=True)
class PaperTable:
    """One of the paper's tables as data, rendered alike to ``tables.md`` (and from it
    the HTML report), the console and the report: its title, column names and rows of
    formatted cells. :func:`tables_i_ii` and :func:`table_iii` build them from the
    figures as ``metrics.json`` holds them; ``tables.csv`` writes the same figures
    unrounded (:func:`format_tables_csv`)."""

    title: str
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]

    def markdown(self) -> str:
        lines = [f"**{self.title}**", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join([*lines, ""])


def _figure(v: Any, key: str) -> float:
    """A summary's figure, from a :class:`Summary` or its ``metrics.json`` mapping."""
    return float(v[key] if isinstance(v, Mapping) else getattr(v, key))


def tables_i_ii(
    tables: Mapping[str, Mapping[str, Mapping[str, Any]]],
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> list[PaperTable]:
    """Tables I and II in the paper's layout: per metric a MAE ± SD row and a RMSE row,
    columns the sets and Overall. ``tables[kind][metric][set]`` (a :class:`Summary` or
    its ``metrics.json`` mapping); kinds other than single and three are ignored."""
    out = []
    for kind in ("single", "three"):
        if kind not in tables:
            continue
        sets = list(next(iter(tables[kind].values())).keys())
        columns = ("Metric", "Statistic", *[s if s != "overall" else "Overall" for s in sets])
        rows = []
        for key, label in TABLE_ROWS[kind]:
            row = tables[kind].get(key)
            if row is None:
                continue
            rows.append(
                (
                    label,
                    "MAE ± SD",
                    *[
                        f"{fmt(_figure(row[s], 'mae'))} ± {fmt(_figure(row[s], 'sd'))}"
                        for s in sets
                    ],
                )
            )
            rows.append(("", "RMSE", *[fmt(_figure(row[s], "rmse")) for s in sets]))
        out.append(PaperTable(TABLE_TITLES[kind], columns, tuple(rows)))
    return out


def format_tables_markdown(
    tables: Mapping[str, Mapping[str, Mapping[str, Any]]],
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> str:
    """Tables I and II (:func:`tables_i_ii`) as Markdown."""
    return "\n".join(t.markdown() for t in tables_i_ii(tables, fmt))


def format_tables_csv(tables: Mapping[str, Mapping[str, Mapping[str, Summary]]]) -> str:
    """The same tables, one row per (table, metric, set): mae, sd, rmse, n (``max_mm``,
    for Table III's rows, is empty here)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["table", "metric", "set", "mae_mm", "sd_mm", "rmse_mm", "n", "max_mm"])
    for kind, metrics in tables.items():
        for key, by_set in metrics.items():
            for s, v in by_set.items():
                mae, sd, rmse = (_figure(v, k) for k in ("mae", "sd", "rmse"))
                n = int(_figure(v, "n"))
                w.writerow([kind, key, s, f"{mae:.6f}", f"{sd:.6f}", f"{rmse:.6f}", n, ""])
    return buf.getvalue()


#: Table III's phantoms, in the paper's order and wording.
PHANTOM_TITLES = {"cone": "Cone", "prism": "Triangular prism"}
#: The calibration methods as reports name them.
METHOD_TITLES = {"single": "single-marker (sphere 1)", "three": "three-marker (spheres 1–3)"}


def _stats_cells(v: Mapping[str, float], fmt: Callable[[float], str]) -> list[str]:
    return [f"{fmt(v['mae'])} ± {fmt(v['sd'])}", fmt(v["rmse"]), fmt(v["max"])]


#: Table III's calibration methods: (name, spheres used).
TABLE_III_METHODS = {"single": ("sphere_1",), "three": ("sphere_1", "sphere_2", "sphere_3")}


#: Table III's two tables: (title, which figures of a cell: after ICP, or the same
#: distances through the true placement).
TABLE_III_TITLES = (
    ("Table III. Single- and three-marker point-to-surface errors after ICP (mm).", None),
    (
        "Table III (twin only). The same without ICP, through the true phantom placement "
        "(calibration and kinematic error included) (mm).",
        "without_icp",
    ),
)


def table_iii(
    stats: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Any]]]],
    sets: Sequence[str],
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> list[PaperTable]:
    """Table III in the paper's layout: per phantom and set (and Overall, pooled), the
    single- and three-marker point-to-surface errors after ICP — MAE ± SD, RMSE, Max.
    ``stats[phantom][method][set]``; a ``without_icp`` entry per cell (the same
    distances through the true placement) gives a second table."""
    columns = (
        "Phantom",
        "Set",
        "Single MAE ± SD",
        "Single RMSE",
        "Single Max",
        "Three MAE ± SD",
        "Three RMSE",
        "Three Max",
    )
    out = []
    for title, pick in TABLE_III_TITLES:
        rows = []
        for kind, by_method in stats.items():
            for s in [*sets, "overall"]:
                cells = []
                for method in ("single", "three"):
                    v = by_method[method][s]
                    cells += _stats_cells(v[pick] if pick else v, fmt)
                label = "Overall" if s == "overall" else s
                rows.append((PHANTOM_TITLES.get(kind, kind), label, *cells))
        out.append(PaperTable(title, columns, tuple(rows)))
    return out


def format_table_iii_markdown(
    stats: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Any]]]],
    sets: Sequence[str],
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> str:
    """Table III (:func:`table_iii`) as Markdown."""
    return "\n".join(t.markdown() for t in table_iii(stats, sets, fmt))


def format_table_iii_csv(
    stats: Mapping[str, Mapping[str, Mapping[str, Mapping[str, Any]]]], sets: Sequence[str]
) -> str:
    """Table III as rows to append to :func:`format_tables_csv`'s: ``table`` is
    ``reconstruction``, ``metric`` ``{phantom}_{method}`` (``_without_icp`` for the
    through-the-truth figures), ``n`` the number of points."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    for kind, by_method in stats.items():
        for method in ("single", "three"):
            for suffix, pick in (("", None), ("_without_icp", "without_icp")):
                for s in [*sets, "overall"]:
                    v = by_method[method][s]
                    n = v["n"]
                    v = v[pick] if pick else v
                    w.writerow(
                        [
                            "reconstruction",
                            f"{kind}_{method}{suffix}",
                            s,
                            *(f"{v[k]:.6f}" for k in ("mae", "sd", "rmse")),
                            n,
                            f"{v['max']:.6f}",
                        ]
                    )
    return buf.getvalue()
