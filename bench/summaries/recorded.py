"""``uscal calibrate``'s ``metrics.json``, typed (:class:`RecordedSummary`): a recorded
dataset's calibrations, with no ground truth; with touches, the paper's folds against its
touch reference (:class:`TouchEvaluation`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..tables import Column, Table, left, right
from .calibration import Array, Calibrations, ErrorFigures, LocalizationSummary
from .run import figure

__all__ = [
    "DatasetInfo",
    "FoldSpread",
    "ImageInfo",
    "RecordedSummary",
    "TouchEvaluation",
    "TouchFold",
]


@dataclass(frozen=True)
class DatasetInfo:
    """The dataset calibrated: where, what, and its medium."""

    path: str
    name: str
    source: str  # twin | robot | plus ...
    n_sweeps: int
    n_frames: int
    targets: tuple[str, ...]
    n_touches: int
    temperature_c: float
    axial_scale: float  # the axial spacing's correction from the temperature

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> DatasetInfo:
        """``metrics.json``'s ``dataset`` (every key always there)."""
        return cls(
            str(d["path"]),
            str(d["name"]),
            str(d["source"]),
            int(d["n_sweeps"]),
            int(d["n_frames"]),
            tuple(d["targets"]),
            int(d["n_touches"]),
            float(d["temperature_c"]),
            float(d["axial_scale"]),
        )


@dataclass(frozen=True)
class ImageInfo:
    """The dataset's frames: size (px) and pixel spacing (m, lateral and axial, as the
    scanner displays it)."""

    width_px: int
    height_px: int
    spacing_m: tuple[float, float]

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> ImageInfo:
        """``metrics.json``'s ``image``."""
        sx, sy = (float(v) for v in d["spacing_m"])
        return cls(int(d["width_px"]), int(d["height_px"]), (sx, sy))


@dataclass(frozen=True)
class TouchFold:
    """One of the paper's folds on a recorded dataset: per test sphere, its precision
    and its accuracy against the touch reference (mm)."""

    fold: str
    kind: str  # single | three
    precision_mm: Mapping[str, float]
    accuracy_mm: Mapping[str, float]


@dataclass(frozen=True)
class FoldSpread:
    """Mean and SD over one kind of fold's test spheres (mm)."""

    kind: str  # single | three
    accuracy_mean: float
    accuracy_sd: float
    precision_mean: float
    precision_sd: float


@dataclass(frozen=True)
class TouchEvaluation:
    """A recorded dataset's touches: the DH model they refined, the phantom pose they
    fixed and, when the folds ran, the paper's folds against the touch reference."""

    dh_from: str
    touches: int
    touch_residual_rms_mm: float
    folds: tuple[TouchFold, ...] = ()
    summary: tuple[FoldSpread, ...] = ()  # per kind of fold that ran

    @classmethod
    def from_metrics(cls, ev: Mapping[str, Any]) -> TouchEvaluation:
        """``metrics.json``'s ``evaluation`` of ``uscal calibrate``; ``folds`` and
        ``summary`` only when the folds ran (:func:`calib.pipeline.calibrate_dataset`)."""
        folds = tuple(
            TouchFold(
                f["fold"],
                f["kind"],
                {s: float(v) for s, v in f["precision_mm"].items()},
                {s: float(v) for s, v in f["accuracy_mm"].items()},
            )
            for f in ev.get("folds", [])
        )
        summary = tuple(
            FoldSpread(
                kind,
                float(v["accuracy_mm"]["mean"]),
                float(v["accuracy_mm"]["sd"]),
                float(v["precision_mm"]["mean"]),
                float(v["precision_mm"]["sd"]),
            )
            for kind, v in ev.get("summary", {}).items()
        )
        return cls(
            str(ev["dh_from"]),
            int(ev["touches"]),
            float(ev["touch_residual_rms_mm"]),
            folds,
            summary,
        )

    def folds_table(self) -> Table:
        """One row per fold and test sphere: its precision and accuracy (mm)."""
        rows = tuple(
            (f.fold, s, f"{f.precision_mm[s]:.3f}", f"{acc:.3f}")
            for f in self.folds
            for s, acc in f.accuracy_mm.items()
        )
        columns = (
            Column("fold", code=True),
            *left("test sphere"),
            *right("precision (mm)", "accuracy (mm)"),
        )
        return Table(columns, rows, "the paper's folds against the touch reference")


@dataclass(frozen=True, eq=False)
class RecordedSummary:
    """``uscal calibrate``'s results: the dataset, its localization and calibrations (no
    truth), how far apart the two methods are, and what its touches gave."""

    dataset: DatasetInfo
    image: ImageInfo
    localization: LocalizationSummary
    calibrations: Calibrations
    single_vs_three: ErrorFigures | None = None
    touches: TouchEvaluation | None = None
    dh_table_refined: Array | None = None  # (6, 4): θ, d, a, α of each joint

    @classmethod
    def from_metrics(cls, m: Mapping[str, Any]) -> RecordedSummary:
        """The whole ``metrics.json`` of ``uscal calibrate``. ``single_vs_three`` only
        when both methods ran; ``evaluation`` and ``dh_table_refined`` only when the
        dataset had touches (or ``--dh-from`` gave some)."""
        cal = m["calibration"]
        both = cal.get("single_vs_three")
        dh = m.get("dh_table_refined")
        return cls(
            DatasetInfo.from_metrics(m["dataset"]),
            ImageInfo.from_metrics(m["image"]),
            LocalizationSummary.from_metrics(m["localization"]),
            Calibrations.from_metrics(cal),
            ErrorFigures.from_metrics(both) if both else None,
            TouchEvaluation.from_metrics(m["evaluation"]) if "evaluation" in m else None,
            None if dh is None else np.array(dh, dtype=float),
        )

    def calibration_table(self) -> Table:
        """One row per calibration: ``T_ee_us``'s translation, its 95 % error bounds
        (what the estimate can be off by; ``-`` without them), precision and observations
        kept."""
        rows = []
        for c in self.calibrations:
            b = c.bound95
            rows.append(
                (
                    c.method,
                    *(f"{v:.2f}" for v in c.T_ee_us[:3, 3] * 1e3),
                    figure(None if b is None else b.rotation_deg),
                    figure(None if b is None else b.translation_mm),
                    figure(c.precision_mm),
                    str(c.n_retained),
                )
            )
        columns = (
            *left("method"),
            *right("x mm", "y mm", "z mm", "≤95% rot °", "≤95% mm", "prec mm", "kept"),
        )
        return Table(columns, tuple(rows), "calibration (no ground truth)")
