"""The typed read of ``metrics.json`` (the ground layer of :mod:`bench`, beside
:mod:`bench.results`, whose jobs write it): what the console and the reports show, each
part built from the metrics in one place, its ``from_metrics``, which says which keys are
optional and why; the tables they show as :class:`bench.tables.Table`.

- :mod:`~bench.summaries.calibration`: what every run holds (localization,
  calibrations, their errors and 95 % bounds);
- :mod:`~bench.summaries.run`: ``uscal run`` (:class:`RunSummary`);
- :mod:`~bench.summaries.paper`: the paper's experiment (:class:`PaperEvaluation`,
  :class:`Reconstruction`);
- :mod:`~bench.summaries.recorded`: ``uscal calibrate`` (:class:`RecordedSummary`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .calibration import (
    Calibrations,
    CalibrationSummary,
    DeclaredTerms,
    ErrorFigures,
    LocalizationSummary,
    Spread,
    Uncertainty,
)
from .paper import (
    DHChange,
    DistanceStats,
    FoldTruth,
    KinematicsTruth,
    PaperEvaluation,
    PhantomStats,
    Reconstruction,
)
from .recorded import (
    DatasetInfo,
    FoldSpread,
    ImageInfo,
    RecordedSummary,
    TouchEvaluation,
    TouchFold,
)
from .run import RunSummary, RunTiming

__all__ = [
    "CalibrationSummary",
    "Calibrations",
    "DHChange",
    "DatasetInfo",
    "DeclaredTerms",
    "DistanceStats",
    "ErrorFigures",
    "FoldSpread",
    "FoldTruth",
    "ImageInfo",
    "KinematicsTruth",
    "LocalizationSummary",
    "PaperEvaluation",
    "PhantomStats",
    "Reconstruction",
    "RecordedSummary",
    "RunSummary",
    "RunTiming",
    "Spread",
    "TouchEvaluation",
    "TouchFold",
    "Uncertainty",
    "read_metrics",
]


def read_metrics(m: Mapping[str, Any]) -> RunSummary | RecordedSummary:
    """A run's ``metrics.json`` as its summary: ``uscal calibrate``'s (a recorded
    dataset: it has a ``dataset`` section) or ``uscal run``'s."""
    return RecordedSummary.from_metrics(m) if "dataset" in m else RunSummary.from_metrics(m)
