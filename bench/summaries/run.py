"""``uscal run``'s ``metrics.json``, typed (:class:`RunSummary`): one acquisition on the
twin, or the paper's experiment with its evaluation and reconstruction
(:mod:`bench.summaries.paper`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..tables import Table, left, right
from .calibration import Calibrations, ErrorFigures, LocalizationSummary
from .paper import PaperEvaluation, Reconstruction

__all__ = ["RunSummary", "RunTiming", "figure"]


def figure(v: float | None, digits: int = 3) -> str:
    """A figure as a table shows it (``digits`` decimals), ``-`` when there is none."""
    return "-" if v is None else f"{v:.{digits}f}"


@dataclass(frozen=True)
class RunTiming:
    """Where a run's time went (s); with ``workers``, the stages are summed over the
    paper's worker processes."""

    simulate: float
    localize: float
    calibrate: float
    total: float
    workers: int | None = None

    @classmethod
    def from_metrics(cls, d: Mapping[str, Any]) -> RunTiming:
        """``metrics.json``'s ``timing_s``; ``workers`` only in the paper's experiment
        (its other keys, per dataset and stage, are not shown)."""
        workers = d.get("workers")
        return cls(
            float(d["simulate"]),
            float(d["localize"]),
            float(d["calibrate"]),
            float(d["total"]),
            None if workers is None else int(workers),
        )


@dataclass(frozen=True, eq=False)
class RunSummary:
    """``uscal run``'s results: the localization and calibrations against the twin's
    truth (in the paper's experiment, the first dataset's first folds) and the timing;
    the paper's experiment adds its evaluation and, when it scanned phantoms, the
    reconstruction."""

    scenario: str
    localization: LocalizationSummary
    calibrations: Calibrations
    timing: RunTiming
    evaluation: PaperEvaluation | None = None
    reconstruction: Reconstruction | None = None
    #: Planned sweeps that did not clear in this session and what took their place.
    replaced: tuple[str, ...] = ()

    @classmethod
    def from_metrics(cls, m: Mapping[str, Any]) -> RunSummary:
        """The whole ``metrics.json`` of ``uscal run``. ``evaluation`` only in the
        paper's experiment (two datasets or more), ``reconstruction`` only when it
        scanned the phantoms."""
        return cls(
            m["scenario"]["name"],
            LocalizationSummary.from_metrics(m["localization"]),
            Calibrations.from_metrics(m["calibration"]),
            RunTiming.from_metrics(m["timing_s"]),
            PaperEvaluation.from_metrics(m) if "evaluation" in m else None,
            Reconstruction.from_metrics(m) if "reconstruction" in m else None,
            tuple(m.get("acquisition", {}).get("replaced", ())),
        )

    def calibration_table(self) -> Table:
        """One row per calibration: its true errors, precision, accuracy, observations
        kept and alternations. Short headers: the table fits an 80-column terminal."""
        rows = []
        for c in self.calibrations:
            e = c.true_error or ErrorFigures(float("nan"), float("nan"))  # none: recorded data
            rows.append(
                (
                    c.method,
                    figure(e.rotation_deg),
                    figure(e.translation_mm),
                    figure(e.image_mm),
                    figure(c.precision_mm),
                    figure(c.accuracy_mm),
                    str(c.n_retained),
                    str(c.iterations),
                )
            )
        columns = (
            *left("method"),
            *right("rot °", "trans mm", "image mm", "prec mm", "acc mm", "kept", "iter"),
        )
        return Table(columns, tuple(rows), "calibration against ground truth")
