"""The paper experiment's part of ``metrics.json``, typed: the cross-validation against
the twin's ground truth with Tables I and II (:class:`PaperEvaluation`), and the
reconstruction with Table III (:class:`Reconstruction`). Each is built from the metrics
in one place, its ``from_metrics``, which says which keys are optional and why. The
paper's tables themselves are :class:`calib.evaluation.cross_validation.PaperTable` (made by
:func:`calib.evaluation.cross_validation.tables_i_ii` and
:func:`calib.evaluation.cross_validation.table_iii` from the same figures)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calib.evaluation.cross_validation import PaperTable, table_iii, tables_i_ii

from ..tables import Table, left, right
from .calibration import ErrorFigures

__all__ = [
    "DHChange",
    "DistanceStats",
    "FoldTruth",
    "KinematicsTruth",
    "PaperEvaluation",
    "PhantomStats",
    "Reconstruction",
]


# ----------------------------------------------------------------------------- evaluation


@dataclass(frozen=True)
class FoldTruth:
    """One fold of the paper's cross-validation against the twin's truth: the mean
    error of its ``T_ee_us`` over the image and its accuracy against the true centres,
    and the verdict the pipeline gave it (:mod:`calib.calibration.verdict`)."""

    fold: str
    dataset: str
    kind: str  # single | three
    image_mm: float
    accuracy_true_mm: float
    verdict: str | None = None  # accepted | suspect | rejected (metrics before: none)


@dataclass(frozen=True)
class KinematicsTruth:
    """One dataset's DH model against the truth: the RMS error at the image of the
    nominal and of the refined model (over the scanned configurations), and the touch
    reference centres' mean distance from the true ones (mm)."""

    dataset: str
    nominal_rms_mm: float
    refined_rms_mm: float
    reference_error_mm: float


@dataclass(frozen=True)
class DHChange:
    """The DH model's change from nominal, RMS over the joints."""

    theta_deg: float
    d_mm: float
    a_mm: float
    alpha_deg: float

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> DHChange:
        return cls(float(d["theta_deg"]), float(d["d_mm"]), float(d["a_mm"]), float(d["alpha_deg"]))


#: The truth table's columns: (name, what a fold mean reads, fold kind) per figure.
_TRUTH_FOLD_COLUMNS = (
    ("1: image", "image_mm", "single"),
    ("1: acc", "accuracy_true_mm", "single"),
    ("3: image", "image_mm", "three"),
    ("3: acc", "accuracy_true_mm", "three"),
)


@dataclass(frozen=True, eq=False)
class PaperEvaluation:
    """The paper's experiment on the twin: its datasets, Tables I and II, every fold
    and DH model against the truth, and what the touches could not identify."""

    datasets: tuple[str, ...]
    tables: tuple[PaperTable, ...]  # Tables I and II
    folds: tuple[FoldTruth, ...]
    kinematics: tuple[KinematicsTruth, ...]  # per dataset, in order
    unobservable_share: Mapping[str, float]  # per DH parameter: share touches cannot see
    rms_change: DHChange  # mean over the leave-one-out models

    @classmethod
    def from_metrics(cls, m: Mapping[str, Any]) -> PaperEvaluation:
        """From the whole ``metrics.json`` of the paper's experiment (its ``evaluation``
        and ``kinematics`` sections, both always there when ``evaluation`` is)."""
        ev, kin = m["evaluation"], m["kinematics"]
        names = tuple(ev["datasets"])
        folds = tuple(
            FoldTruth(
                f["fold"],
                f["dataset"],
                f["kind"],
                float(f["true"]["image_mm"]),
                float(f["true"]["accuracy_true_mm"]),
                f["verdict"]["status"] if "verdict" in f else None,
            )
            for f in ev["folds"]
        )

        def kinematics(name: str) -> KinematicsTruth:
            k = kin["datasets"][name]
            return KinematicsTruth(
                name,
                float(k["true_error"]["nominal_rms"]),
                float(k["true_error"]["refined_rms"]),
                float(np.mean(list(k["reference_error_mm"].values()))),
            )

        return cls(
            names,
            tuple(tables_i_ii(ev)),  # the kinds' tables (single, three); other keys ignored
            folds,
            tuple(kinematics(n) for n in names),
            {k: float(v) for k, v in kin["unobservable_share"].items()},
            DHChange.from_metrics(kin["rms_change_mean"]),
        )

    def fold_mean(self, dataset: str, kind: str, figure: str) -> float | None:
        """Mean over a dataset's folds of one kind of ``image_mm`` or
        ``accuracy_true_mm``; None without such folds."""
        v = [getattr(f, figure) for f in self.folds if f.dataset == dataset and f.kind == kind]
        return float(np.mean(v)) if v else None

    def _accepted(self, dataset: str, kind: str) -> str:
        """How many of a dataset's folds of one kind the verdict accepted, "k / n"."""
        v = [f.verdict for f in self.folds if f.dataset == dataset and f.kind == kind]
        if not v or any(s is None for s in v):
            return "–"
        return f"{sum(s == 'accepted' for s in v)} / {len(v)}"

    def truth_table(self) -> Table:
        """Per dataset, its kinematic model's and touch reference's errors against the
        truth and its folds' mean true errors (mm; beyond the paper). Without notes:
        the console and the report say what the columns are in their own words."""
        rows = []
        for k in self.kinematics:
            means = [self.fold_mean(k.dataset, kind, fig) for _, fig, kind in _TRUTH_FOLD_COLUMNS]
            rows.append(
                (
                    k.dataset,
                    f"{k.nominal_rms_mm:.2f}",
                    f"{k.refined_rms_mm:.3f}",
                    f"{k.reference_error_mm:.2f}",
                    *(f"{v:.2f}" if v is not None else "–" for v in means),
                    *(self._accepted(k.dataset, kind) for kind in ("single", "three")),
                )
            )
        columns = (
            *left("set"),
            *right("kin. err nominal", "kin. err refined", "ref. err"),
            *right(*(name for name, _, _ in _TRUTH_FOLD_COLUMNS)),
            *right("1: accepted", "3: accepted"),
        )
        return Table(columns, tuple(rows), "against ground truth (beyond the paper)")


# ----------------------------------------------------------------------------- reconstruction


@dataclass(frozen=True)
class DistanceStats:
    """Table III's statistics of point-to-surface distances (mm), with the same
    distances through the true placement when measured (the twin)."""

    mae: float
    sd: float
    rmse: float
    max: float
    without_icp: DistanceStats | None = None

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> DistanceStats:
        """``{mae, sd, rmse, max[, without_icp]}`` (:func:`calib.evaluation.reconstruct.
        distance_stats`); ``without_icp`` only where the true placement is known."""
        without = d.get("without_icp")
        return cls(
            float(d["mae"]),
            float(d["sd"]),
            float(d["rmse"]),
            float(d["max"]),
            None if without is None else DistanceStats.from_metrics(without),
        )


@dataclass(frozen=True)
class PhantomStats:
    """One phantom's Table III figures, per (method, set), the sets pooled as
    ``overall``."""

    kind: str  # cone | prism
    cells: Mapping[tuple[str, str], DistanceStats] = field(default_factory=dict)

    @classmethod
    def from_metrics(cls, kind: str, d: Mapping[str, Any]) -> PhantomStats:
        """``metrics.json``'s ``reconstruction.<kind>`` (or a
        :class:`~bench.results.PhantomReconstruction`'s ``metrics``): per method (single,
        three) per set; its other keys (scan counts, timing) are not Table III's."""
        cells = {
            (method, s): DistanceStats.from_metrics(v)
            for method in ("single", "three")
            for s, v in d.get(method, {}).items()
        }
        return cls(kind, cells)

    def without_icp_mae(self, method: str) -> float:
        """The overall MAE (mm) of a method's points through the true placement, without
        ICP (NaN where not measured)."""
        cell = self.cells.get((method, "overall"))
        return cell.without_icp.mae if cell and cell.without_icp else float("nan")


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """The reconstruction after the remount: Table III (after ICP, and through the true
    placement), the figures per phantom, and the re-calibration against the truth."""

    sets: tuple[str, ...]
    phantoms: tuple[PhantomStats, ...]  # cone, prism: those scanned
    tables: tuple[PaperTable, ...]  # Table III after ICP, then without ICP
    recalibration: Mapping[str, ErrorFigures]  # "<set>/<method>" → true error

    @classmethod
    def from_metrics(cls, m: Mapping[str, Any]) -> Reconstruction:
        """From the whole ``metrics.json`` of the paper's experiment (its
        ``reconstruction`` section, with the datasets of ``evaluation``); the phantoms
        are those scanned, and ``recalibration`` is absent from a run that scanned none."""
        rec = m["reconstruction"]
        names = tuple(m["evaluation"]["datasets"])
        kinds = [k for k in ("cone", "prism") if k in rec]
        truth = rec.get("recalibration", {}).get("true_error", {})
        return cls(
            names,
            tuple(PhantomStats.from_metrics(k, rec[k]) for k in kinds),
            tuple(table_iii({k: rec[k] for k in kinds}, names)),
            {k: ErrorFigures.from_metrics(v) for k, v in truth.items()},
        )

    @property
    def worst_recalibration_image_mm(self) -> float | None:
        """The largest true image error of the re-calibrations (None: none scored)."""
        image = [e.image_mm for e in self.recalibration.values() if e.image_mm is not None]
        return max(image) if image else None
