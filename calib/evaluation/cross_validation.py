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

from .. import se3
from ..calibration.alternation import AlternationResult, AlternationSettings, alternate
from ..calibration.markers import centres_in_base, robust_inliers
from ..errors import CalibrationError
from ..localize import LocalizerConfig, SweepLocalization, localize_sphere
from ..records import Sweep

__all__ = [
    "METHOD_TITLES",
    "EvaluationConfig",
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
    "training_precision",
]

Array = NDArray[np.float64]
_MM = 1e3

Kind = Literal["single", "three"]


@dataclass(frozen=True)
class EvaluationConfig:
    """Touch reference, DH refinement and the paper's cross-validation (Tables I, II)."""

    datasets: tuple[str, ...] = field(
        default=("A", "B", "C"),
        metadata={
            "doc": "Independent acquisitions (touches + sweeps, new phantom placement "
            "each); each uses the DH model refined from the others' touches. Fewer than "
            "two: no touches and no evaluation, the controller's kinematics are used."
        },
    )
    touches_one_dataset: bool = field(
        default=False,
        metadata={
            "doc": "Simulation, one acquisition (fewer than two datasets): after the sweeps, "
            "touch the cone vertices with the stylus and refine the DH model from these "
            "touches before calibrating (the paper's experiment refines each dataset from "
            "the others' touches instead)."
        },
    )
    dh_regularizer: float = field(
        default=0.01, metadata={"doc": "Weight of ‖z‖² in the touch loss.", "ge": 0, "le": 100}
    )
    initialisations: int = field(
        default=12,
        metadata={"doc": "Deterministic initialisations of the DH fit.", "ge": 1, "le": 100},
    )
    dh_bound: float = field(
        default=10.0,
        metadata={
            "doc": "Bound of each scaled DH correction (° for Δθ, Δα; mm for Δd, Δa).",
            "gt": 0,
            "le": 90,
        },
    )
    stylus_tip_cad_mm: tuple[float, float, float] = field(
        default=(0.0, 0.0, 165.0),
        metadata={
            "doc": "Stylus tip offset in ee from the stylus drawing: the fit's start value "
            "(the fit estimates the true one)."
        },
    )
    placement_shift_mm: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: the phantom of each dataset after the first is put back "
            "up to ± this off (x, y) from the scenario's placement.",
            "ge": 0,
            "le": 50,
        },
    )
    placement_rotation_deg: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: and turned up to ± this about the vertical.",
            "ge": 0,
            "le": 45,
        },
    )
    session_shift_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Simulation: 1 σ per horizontal axis of the phantom's displacement "
            "between a dataset's touches and its sweeps (truth only; 0 = off): the tool "
            "exchange, stylus out and probe in, over a phantom standing in the tank, and "
            "the touches' own push. The touch reference then maps the CAD centres to "
            "where the phantom was, not where it is scanned. Est. 0–1 mm for a phantom "
            "held by weights or tape rather than clamped (no published figure; the paper "
            "lists stylus contact and remounting among its remaining errors, and its "
            "per-set accuracy varies 1.16–2.26 mm while its precision varies "
            "0.71–0.96 mm).",
            "ge": 0,
            "le": 10,
        },
    )
    workers: int = field(
        default=0,
        metadata={
            "doc": "Processes running the datasets and the reconstruction's tasks in "
            "parallel (0: one per core).",
            "ge": 0,
            "le": 64,
        },
    )


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
    *,
    axial_scale: float,
    outlier_mm: float = 2.0,
) -> tuple[list[SweepLocalization], NDArray[np.bool_]]:
    """Re-stack and localize a test sphere's sweeps under a fold's calibration and
    decide which centres are retained (accepted and passing the calibration's outlier
    test about their centroid). Sweeps are searched around their first centres; those
    that end up outliers are searched again over the whole grid before the final
    decision, so a false first detection cannot stick."""
    locs = localize_sphere(
        sweeps, T_ee_us, radius, localizer, axial_scale=axial_scale, previous=initial
    )

    def retained(locs: Sequence[SweepLocalization]) -> NDArray[np.bool_]:
        P = base_centres(sweeps, locs, T_ee_us)
        ok = np.array([loc.accepted for loc in locs])
        keep = np.zeros(len(locs), dtype=bool)
        if ok.any():
            keep[ok] = robust_inliers(P[ok], floor_mm=outlier_mm)
        return keep

    keep = retained(locs)
    if not keep.all():
        seeds = [loc if k else None for loc, k in zip(locs, keep, strict=True)]
        locs = localize_sphere(
            sweeps, T_ee_us, radius, localizer, axial_scale=axial_scale, previous=seeds
        )
        keep = retained(locs)
    return locs, keep


def evaluate_fold(
    fold: Fold,
    sweeps: Mapping[str, Sequence[Sweep]],
    initial: Mapping[str, Sequence[SweepLocalization]],
    references: Mapping[str, Array],
    radius: float,
    settings: AlternationSettings,
    *,
    cad_centres: Mapping[str, Array],
    T_coarse: Array | None,
) -> FoldResult:
    """Calibrate on the fold's training spheres (alternating localization and
    calibration, from the shared first localization ``initial``), then re-stack and
    localize its test spheres with the result and score them against ``references``
    (base-frame touch-reference centres). The multi-marker folds estimate the printed
    layout at ``settings.layout_sigma_mm`` (0: the CAD layout as exact)."""
    alt = alternate(
        {t: sweeps[t] for t in fold.train},
        radius,
        settings,
        cad_centres=cad_centres if len(fold.train) >= 2 else None,
        T_coarse=T_coarse,
        initial={t: initial[t] for t in fold.train},
    )
    T = alt.result.T_ee_us
    centres, precision, accuracy, test_locs = {}, {}, {}, {}
    for t in fold.test:
        locs, keep = localize_test_sphere(
            sweeps[t], initial[t], T, radius, settings.localizer, axial_scale=settings.axial_scale
        )
        test_locs[t] = locs
        centres[t] = base_centres(sweeps[t], locs, T)[keep]
        precision[t], accuracy[t] = sphere_metrics(centres[t], references[t])
    return FoldResult(fold, alt, centres, precision, accuracy, test_locs)


def training_precision(alt: AlternationResult) -> dict[str, float]:
    """Per training sphere: mean distance of its retained centres from their centroid."""
    X = centres_in_base(alt.observations, alt.result.T_ee_us)
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
    *,
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
    *,
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> str:
    """Tables I and II (:func:`tables_i_ii`) as Markdown."""
    return "\n".join(t.markdown() for t in tables_i_ii(tables, fmt=fmt))


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
    *,
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
    *,
    fmt: Callable[[float], str] = lambda v: f"{v:.2f}",
) -> str:
    """Table III (:func:`table_iii`) as Markdown."""
    return "\n".join(t.markdown() for t in table_iii(stats, sets, fmt=fmt))


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
