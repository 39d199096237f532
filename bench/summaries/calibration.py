"""What every run's ``metrics.json`` holds, typed: its localization
(:class:`LocalizationSummary`) and its calibrations (:class:`Calibrations` of
:class:`CalibrationSummary`, as :func:`bench.results.calibration_entry` and the jobs
write them), with their errors and bounds (:class:`ErrorFigures`, :class:`Uncertainty`)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CalibrationSummary",
    "Calibrations",
    "DeclaredTerms",
    "ErrorFigures",
    "LocalizationSummary",
    "Spread",
    "Uncertainty",
    "VerdictSummary",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ErrorFigures:
    """How far one ``T_ee_us`` is from another: rotation angle (°), distance of the
    origins (mm) and, when known, the mean distance over the image (mm). An error against
    the truth, a 95 % error bound, or the difference of two estimates (no image figure)."""

    rotation_deg: float
    translation_mm: float
    image_mm: float | None = None

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> ErrorFigures:
        """``{rotation_deg, translation_mm[, image_mm]}``; ``image_mm`` is absent from a
        plain difference of two transforms (:func:`bench.truth.transform_difference`:
        single vs three-marker) and from a 1 σ term of a bound."""
        image = d.get("image_mm")
        return cls(
            float(d["rotation_deg"]),
            float(d["translation_mm"]),
            None if image is None else float(image),
        )

    def within(self, bound: ErrorFigures) -> bool:
        """Every figure at or under the bound's (an image figure on both sides)."""
        if self.image_mm is None or bound.image_mm is None:
            return False
        return (
            self.rotation_deg <= bound.rotation_deg
            and self.translation_mm <= bound.translation_mm
            and self.image_mm <= bound.image_mm
        )


@dataclass(frozen=True)
class DeclaredTerms:
    """The systematic terms a 95 % bound includes as declared (1 σ; mm unless named)."""

    print_tolerance_mm: float = 0.0
    radius_tolerance_mm: float = 0.0
    axial_bias_mm: float = 0.0
    kinematic_sigma_mm: float = 0.0
    axial_scale_sigma: float = 0.0
    mount_sigma_mm: float = 0.0
    mount_sigma_deg: float = 0.0

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> DeclaredTerms:
        """``uncertainty.declared`` (:func:`bench.results.uncertainty_entry`); a term
        missing counts as zero."""
        return cls(**{f.name: float(d[f.name]) for f in fields(cls) if f.name in d})


@dataclass(frozen=True)
class Uncertainty:
    """How a 95 % bound was made: the views its jackknife ran over, the 1 σ of each term
    (rss over the axes; rotation and translation only) and the declared terms. Empty
    for a calibration without bounds."""

    views: int | None = None
    one_sigma_rss: Mapping[str, ErrorFigures] = field(default_factory=dict)
    declared: DeclaredTerms = DeclaredTerms()

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> Uncertainty:
        """A calibration's ``uncertainty`` (:meth:`calib.calibration.uncertainty.Bound95.details`
        and the declared terms), or ``{}``: each part may be missing."""
        views = d.get("views")
        return cls(
            None if views is None else int(views),
            {k: ErrorFigures.from_metrics(v) for k, v in d.get("one_sigma_rss", {}).items()},
            DeclaredTerms.from_metrics(d.get("declared", {})),
        )


@dataclass(frozen=True)
class VerdictSummary:
    """A calibration's verdict (:mod:`calib.calibration.verdict`): ``accepted``, ``suspect`` or
    ``rejected``, and why."""

    status: str
    reasons: tuple[str, ...] = ()

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> VerdictSummary:
        """A calibration's ``verdict`` (:meth:`calib.calibration.verdict.Verdict.as_dict`)."""
        return cls(str(d["status"]), tuple(str(r) for r in d.get("reasons", ())))

    def line(self) -> str:
        """One line: the status and its reasons."""
        return self.status + (": " + "; ".join(self.reasons) if self.reasons else "")


@dataclass(frozen=True, eq=False)
class CalibrationSummary:
    """One calibration as ``metrics.json`` keeps it: ``T_ee_us`` and its covariance,
    its precision, observations kept and alternations; on the twin its errors against
    the truth and accuracy; its 95 % bounds when computed."""

    method: str  # single | three
    T_ee_us: Array  # (4, 4), metres
    covariance: Array  # (6, 6): rotation vector (rad), translation (m)
    precision_mm: float
    n_retained: int
    iterations: int
    fold: str | None = None  # the paper's experiment: the fold it is
    accuracy_mm: float | None = None  # the twin: against the true centres
    true_error: ErrorFigures | None = None  # the twin
    # A single run: against the mount that is right through the controller's model.
    true_error_equivalent: ErrorFigures | None = None
    bound95: ErrorFigures | None = None
    uncertainty: Uncertainty = Uncertainty()
    verdict: VerdictSummary | None = None

    @classmethod
    def from_metrics(cls, method: str, c: Mapping[str, Any]) -> CalibrationSummary:
        """``metrics.json``'s ``calibration.<method>``. Optional: ``fold`` (the paper's
        experiment), ``accuracy_mm`` and ``true_error`` (the twin: recorded data has no
        truth), ``true_error_equivalent`` (a single run on the twin), ``bound95`` and
        ``uncertainty`` (when the bounds were computed), ``verdict`` (metrics written
        before verdicts have none)."""

        def errors(key: str) -> ErrorFigures | None:
            return ErrorFigures.from_metrics(c[key]) if key in c else None

        accuracy = c.get("accuracy_mm")
        return cls(
            method,
            np.array(c["T_ee_us"], dtype=float),
            np.array(c["covariance_rotvec_rad_translation_m"], dtype=float),
            float(c["precision_mm"]),
            int(c["n_retained"]),
            int(c["iterations"]),
            c.get("fold"),
            None if accuracy is None else float(accuracy),
            errors("true_error"),
            errors("true_error_equivalent"),
            errors("bound95"),
            Uncertainty.from_metrics(c.get("uncertainty", {})),
            VerdictSummary.from_metrics(c["verdict"]) if "verdict" in c else None,
        )

    @property
    def truth_for_bound(self) -> ErrorFigures | None:
        """The true error a bound is checked against: the equivalent mount's when known
        (what the data can reach through the controller's model), else the truth's."""
        return self.true_error_equivalent or self.true_error

    @property
    def std(self) -> Array:
        """(6,) 1 σ from the covariance: rotation vector (rad), translation (m)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))


@dataclass(frozen=True)
class Calibrations:
    """A run's single- and three-marker calibrations, those that ran."""

    single: CalibrationSummary | None = None
    three: CalibrationSummary | None = None

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> Calibrations:
        """``metrics.json``'s ``calibration`` section: either method may be missing
        (``--markers``); its other keys (the coarse error, single vs three) are read by
        the summaries that show them."""
        return cls(
            *(
                CalibrationSummary.from_metrics(k, d[k]) if k in d else None
                for k in ("single", "three")
            )
        )

    def __iter__(self) -> Iterator[CalibrationSummary]:
        """The calibrations that ran, single-marker first."""
        return iter([c for c in (self.single, self.three) if c is not None])

    @property
    def chosen(self) -> CalibrationSummary:
        """The calibration to use: three-marker when it ran (it also anchors the
        phantom; the paper's recommended use), else single-marker."""
        chosen = self.three or self.single
        if chosen is None:
            raise ValueError("the metrics hold no calibration")
        return chosen


@dataclass(frozen=True)
class Spread:
    """Median, 95th percentile and maximum of some errors (mm)."""

    median: float
    p95: float
    max: float


@dataclass(frozen=True)
class LocalizationSummary:
    """The localization: method, sweeps and rejections; on the twin, the centres' error
    against the truth."""

    method: str
    n_sweeps: int
    n_rejected: int
    error_mm: Spread | None = None

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> LocalizationSummary:
        """``metrics.json``'s ``localization``; ``error_mm`` only on the twin."""
        e = d.get("error_mm")
        spread = None if e is None else Spread(float(e["median"]), float(e["p95"]), float(e["max"]))
        return cls(d["method"], int(d["n_sweeps"]), int(d["n_rejected"]), spread)
