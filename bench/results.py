"""The typed results of the jobs (the bottom layer of :mod:`bench`): what a run, the
paper's experiment, one of its datasets, the re-calibration and reconstruction, and a
recorded dataset's calibration hand to the outputs. Each carries its ``metrics.json``
part and the objects it came from; none holds frames, except a single run's
acquisition. With them, what ``metrics.json`` keeps of one calibration
(:func:`calibration_entry`), truth aside."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from calib.calibration.alternation import AlternationResult
from calib.calibration.uncertainty import Bound95, UncertaintyInputs
from calib.calibration.verdict import Requirements, SweepGeometry, Verdict, judge
from calib.dh import DHTable
from calib.evaluation.cross_validation import FoldResult, training_precision
from calib.files.dataset import AcquisitionInfo
from calib.kinematics import DHRefinement, TouchReference
from calib.localize import SweepLocalization
from calib.records import Dataset, Sweep

from .files import with_frames

if TYPE_CHECKING:  # types only: the results layer loads neither the twin nor the pipeline
    from calib.pipeline import MarkerCalibrations

    from .acquire_sim import SimulatedAcquisition
    from .snapshot import LocalizationSnapshot

__all__ = [
    "DatasetOutcome",
    "EvaluationResult",
    "PhantomReconstruction",
    "PhantomScan",
    "Recalibration",
    "RecordedCalibration",
    "RemountScan",
    "RunResult",
    "calibration_entry",
    "layout_entry",
    "uncertainty_entry",
]

Array = NDArray[np.float64]
_MM = 1e3  # mm per metre


@dataclass(frozen=True, eq=False)
class RecordedCalibration:
    """``uscal calibrate``'s result: metrics, and what they came from."""

    metrics: dict[str, Any]
    dataset: Dataset
    info: AcquisitionInfo
    calibrations: MarkerCalibrations
    axial_scale: float  # the axial spacing's correction from the recorded temperature
    dh_table: DHTable | None = None  # refined from touches, when the dataset has them


@dataclass(frozen=True, eq=False)
class RunResult:
    """Metrics (the ``metrics.json`` content) and the objects they came from: one
    acquisition with the controller's kinematics, or the paper's evaluation."""

    metrics: dict[str, Any]
    acquisition: SimulatedAcquisition | None = None
    single: AlternationResult | None = None
    three: AlternationResult | None = None
    evaluation: EvaluationResult | None = None
    snapshot: LocalizationSnapshot | None = None  # what the report shows of one sweep
    nwire: Any = None  # an N-wire scenario's run (bench.jobs.targets.TargetRun)
    # What the bounds were made from beside the data: the declared terms and the CAD
    # sphere centres (phantom frame) of a single acquisition's calibrations.
    uncertainty_inputs: UncertaintyInputs | None = None
    cad_centres: dict[str, NDArray[np.float64]] | None = None

    def alternations(self) -> dict[str, AlternationResult]:
        """The calibrations ``metrics["calibration"]`` describes, by method (in an
        evaluation: the first dataset's first single- and three-marker folds)."""
        if self.evaluation is not None:
            out: dict[str, AlternationResult] = {}
            for r in self.evaluation.outcomes[0].folds:
                out.setdefault(r.fold.kind, r.alternation)
            return out
        pairs = (("single", self.single), ("three", self.three))
        return {k: a for k, a in pairs if a is not None}


@dataclass(frozen=True, eq=False)
class DatasetOutcome:
    """What one dataset task returns (no frames)."""

    name: str
    folds: list[FoldResult]
    truth: dict[str, Any]
    localization_errors_mm: Array
    n_sweeps: int
    n_rejected: int
    timing_s: dict[str, float]
    recording_part: Path | None = None
    snapshot: LocalizationSnapshot | None = None  # the report's look (first dataset only)
    uncertainty: dict[str, dict[str, Any]] = field(default_factory=dict)  # per fold name


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """Metrics (``metrics.json`` content), the tables as text, and the parts."""

    metrics: dict[str, Any]
    tables_markdown: str
    tables_csv: str
    refinements: dict[str, DHRefinement]
    references: dict[str, TouchReference]
    outcomes: list[DatasetOutcome] = field(repr=False)
    reconstruction: list[PhantomReconstruction] = field(default_factory=list, repr=False)


@dataclass(frozen=True, eq=False)
class RemountScan:
    """One sphere of the re-calibration scan after the remount: its sweeps and their
    first localization (under the coarse ``T_ee_us``). The frames are in the file
    ``images`` (one array, sweep by sweep), which every calibration task maps instead of
    receiving its own copy; :meth:`sweeps_with_frames` puts them back."""

    target: str
    sweeps: tuple[Sweep, ...]  # their ``images`` are empty: the frames are in the file
    images: Path
    first: tuple[SweepLocalization, ...]
    cad_centre: Array  # the sphere's centre in the phantom's CAD (three-marker)
    T_ee_us_coarse: Array
    T_ee_us_true: Array  # truth: kept apart, for the error against it
    dh_true: DHTable  # truth: the true arm, for the error in each model's gauge
    timing_s: dict[str, float]

    def sweeps_with_frames(self) -> tuple[Sweep, ...]:
        return tuple(with_frames(self.sweeps, self.images))


@dataclass(frozen=True, eq=False)
class Recalibration:
    """``T_ee_us[(set, method)]`` re-estimated after the remount with each DH model, and
    (kept apart) its error against the truth in that model's gauge."""

    T_ee_us: dict[tuple[str, str], Array]
    n_retained: dict[tuple[str, str], int]
    truth: dict[tuple[str, str], dict[str, float]]
    timing_s: dict[str, float]

    @staticmethod
    def merge(parts: list[Recalibration], scans: list[RemountScan]) -> Recalibration:
        """The per-method tasks' results as one, timed with the scans: ``simulate`` and
        ``calibrate`` (the first localizations included), seconds summed over the tasks."""
        timing = {
            "simulate": sum(s.timing_s["simulate"] for s in scans),
            "calibrate": sum(s.timing_s["localize"] for s in scans)
            + sum(p.timing_s["calibrate"] for p in parts),
        }
        return Recalibration(
            {k: v for p in parts for k, v in p.T_ee_us.items()},
            {k: v for p in parts for k, v in p.n_retained.items()},
            {k: v for p in parts for k, v in p.truth.items()},
            timing,
        )


@dataclass(frozen=True, eq=False)
class PhantomScan:
    """Boundary samples of one phantom's 45 sweeps (no frames): per used frame its joint
    angles, per sample its frame and its point in the image (``us``, metres)."""

    kind: str
    q_frames: Array  # (m, 6) reported joint angles of the central frames
    frame: NDArray[np.int32]  # (n,) index into q_frames
    p_us: Array  # (n, 3)
    q_taught: Array  # (6,) the taught pose (apex or mid-ridge on the image centre line)
    target_depth: float  # metres below the transducer face at the taught pose
    n_sweeps: int
    frames_without_two_boundaries: int
    # Of those, the frames with no echo at all (nothing of the phantom in the section, the
    # noise below the display): no extraction could find a boundary there.
    frames_without_echo: int
    T_base_phantom_true: Array  # truth: kept apart, for the without-ICP distances
    timing_s: dict[str, float]
    recording_part: Path | None = None


@dataclass(frozen=True, eq=False)
class PhantomReconstruction:
    """One phantom's Table III statistics (``metrics[method][set]``, plus scan figures)
    and its registered points (CAD frame, metres, float32) with their distances (mm), by
    (method, set)."""

    kind: str
    metrics: dict[str, Any]
    points: dict[tuple[str, str], tuple[NDArray[np.float32], NDArray[np.float32]]]


def uncertainty_entry(bound: Bound95, inputs: UncertaintyInputs) -> dict[str, Any]:
    """``metrics.json``'s ``bound95`` and ``uncertainty`` of one calibration."""
    details = bound.details()
    details["declared"] = {
        "print_tolerance_mm": inputs.print_tolerance_m * _MM,
        "radius_tolerance_mm": inputs.radius_tolerance_m * _MM,
        "axial_bias_mm": inputs.axial_bias_m * _MM,
        "kinematic_sigma_mm": inputs.kinematic_sigma_m * _MM,
        "axial_scale_sigma": inputs.axial_scale_sigma,
        "mount_sigma_mm": inputs.mount_sigma_m * _MM,
        "mount_sigma_deg": float(np.degrees(inputs.mount_sigma_rad)),
    }
    return {"bound95": bound.as_dict(), "uncertainty": details}


def calibration_entry(
    alt: AlternationResult,
    train: Sequence[str],
    test: Sequence[str],
    bound: tuple[Bound95, UncertaintyInputs] | None = None,
    requirements: Requirements | None = None,
    *,
    verdict: Verdict | None = None,
    geometry: SweepGeometry | None = None,
) -> dict[str, Any]:
    """What ``metrics.json`` keeps of one calibration, truth aside (``bound``: its 95 %
    error bounds and the declared terms they include), with its verdict
    (:func:`calib.calibration.verdict.judge` against ``requirements``, or ``verdict`` when it was
    made already, e.g. from a bound the paper's dataset tasks computed; ``geometry``: how
    its sweeps met the spheres, :func:`calib.calibration.verdict.sweep_geometry`). Its
    precision is the mean over the training spheres of the spread of their reconstructed
    centres."""
    # A training sphere none of whose sweeps was localized has no spread (the fit ran on
    # the others: gel, caps 5 mm under the face, one sphere of three found in no sweep).
    precision = training_precision(alt)
    seen = [precision[t] for t in train if t in precision]
    if verdict is None:
        verdict = judge(
            alt,
            bound[0] if bound is not None else None,
            requirements,
            geometry=geometry,
            kinematic_modes=bound[1].kinematic_modes if bound is not None else None,
        )
    return {
        "verdict": verdict.as_dict(),
        "precision_mm": float(np.mean(seen)) if seen else float("nan"),
        "n_retained": int(alt.result.retained.sum()),
        "iterations": len(alt.history),
        "rejected": dict(alt.result.rejection_reasons),
        "T_ee_us": np.round(alt.result.T_ee_us, 9).tolist(),
        "covariance_rotvec_rad_translation_m": alt.result.covariance.tolist(),
        "history": alt.history,
        "trained_on": list(train),
        "tested_on": list(test),
        **(uncertainty_entry(*bound) if bound is not None else {}),
        **({"sweep_geometry": geometry.as_dict()} if geometry is not None else {}),
        **layout_entry(alt),
    }


def layout_entry(alt: AlternationResult) -> dict[str, Any]:
    """The printed sphere layout a multi-marker fit estimated (phantom frame, mm; with
    the phantom pose it came with), or nothing."""
    layout = alt.result.layout
    if layout is None:
        return {}
    return {
        "layout_estimated_mm": {
            t: [round(float(v) * _MM, 4) for v in c] for t, c in layout.items()
        },
        "layout_prior_weight": alt.result.layout_weight,
    }
