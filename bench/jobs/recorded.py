"""``uscal calibrate``: localization and single-/three-marker calibration of a dataset
on disk (from the hardware or from the twin), with no ground truth; with touches, the
paper's touch-based kinematics and folds on it.

The acquisition's facts come from the dataset (frames, reported poses and joint angles,
pixel spacing, medium temperature, the phantom's CAD landmarks, the holder's coarse
``T_ee_us``); the pipeline's settings (localizer, alternation limits) from a scenario,
the built-in default unless the user names one.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from calib.acquisition.protocol import sweep_axis_off_normal
from calib.calibration.verdict import sweep_geometry
from calib.files.dataset import read_dataset
from calib.pipeline import FoldRun, calibrate_dataset, fold_summary, residual_rms_mm

from ..acquire_sim import make_twin
from ..config.method import method_settings, requirements
from ..config.scenario import Scenario
from ..recording.logs import log_acquisition, merge_parts
from ..recording.options import RecordingOptions
from ..recording.recorder import Recorder
from ..results import RecordedCalibration, RunResult, calibration_entry
from ..snapshot import dataset_snapshot
from ..truth import transform_difference

__all__ = ["calibrate_recorded", "record_recorded", "recorded_run_result"]


def record_recorded(
    options: RecordingOptions, settings: Scenario, result: RecordedCalibration
) -> int:
    """The calibration of a recorded dataset in rerun (:func:`bench.recording.
    log_acquisition` without truth or scene: the phantom's placement is unknown). The arm
    is drawn from the settings' robot model at the reported joint angles."""
    cals = result.calibrations
    alternations = {
        k: v for k, v in (("single", cals.single), ("three", cals.three)) if v is not None
    }
    rec = Recorder(options)
    logged = log_acquisition(
        rec,
        "run",
        [],
        make_twin(settings).scene.model,
        result.dataset,
        alternations,
        result.info.sphere_radius_mm * 1e-3,
        settings.localization,
        result.axial_scale,
    )
    merge_parts(options, [], ["run"], main=rec)
    return logged


def calibrate_recorded(
    directory: str | os.PathLike[str],
    settings: Scenario,
    markers: tuple[int, ...] = (1, 3),
    dh_from: tuple[str | os.PathLike[str], ...] = (),
) -> RecordedCalibration:
    """Read a dataset and calibrate it with the settings of a scenario
    (:func:`calib.pipeline.calibrate_dataset`: no ground truth; with touches, the paper's
    touch-based kinematics and folds) and gather its metrics."""
    t0 = time.perf_counter()
    dataset, info = read_dataset(directory)
    others = [read_dataset(d)[0] for d in dh_from]
    t_read = time.perf_counter() - t0
    found = calibrate_dataset(
        dataset, info, method_settings(settings), markers=markers, dh_from=others
    )
    dataset, cals, targets = found.dataset, found.calibrations, found.calibrations.targets
    calibration: dict[str, Any] = {}
    final: dict[str, Any] = {}
    for kind, n_markers in (("single", 1), ("three", 3)):
        alt = getattr(cals, kind)
        if alt is not None:
            final.update(alt.retained_localizations())
            calibration[kind] = calibration_entry(
                alt,
                targets[:n_markers],
                targets[n_markers:],
                found.bounds[kind],
                requirements(settings),
                geometry=sweep_geometry(alt, dataset.sweeps, info.sphere_radius_mm * 1e-3),
            )
    n_sweeps = sum(len(v) for v in final.values())
    n_rejected = sum(not loc.accepted for v in final.values() for loc in v)
    if cals.single is not None and cals.three is not None:
        a, b = cals.single.result.T_ee_us, cals.three.result.T_ee_us
        calibration["single_vs_three"] = transform_difference(a, b)
    used = cals.three if cals.three is not None else cals.single
    if used is not None:
        calibration["sweep_axis"] = sweep_axis_off_normal(dataset.sweeps, used.result.T_ee_us)
    evaluation: dict[str, Any] | None = None
    if found.reference is not None:
        evaluation = {"dh_from": ", ".join(found.dh_from), "touches": len(dataset.touches)}
        evaluation["touch_residual_rms_mm"] = residual_rms_mm(found.reference.residuals_mm)
        evaluation["tool_precision_mm"] = {
            k: float(v) for k, v in found.reference.tool_precision_mm.items()
        }
        evaluation["seconds_dh"] = found.seconds_dh
        if found.folds is not None:
            evaluation.update(_folds(found.folds))
    sweep0 = dataset.sweeps[0]
    metrics: dict[str, Any] = {
        "dataset": {
            "path": str(Path(directory)),
            "name": dataset.name,
            "source": info.source,
            "n_sweeps": len(dataset.sweeps),
            "n_frames": int(sum(s.n_frames for s in dataset.sweeps)),
            "targets": targets,
            "n_touches": len(dataset.touches),
            "temperature_c": info.temperature_c,
            "axial_scale": found.axial_scale,
        },
        "image": {
            "width_px": int(sweep0.images.shape[2]),
            "height_px": int(sweep0.images.shape[1]),
            "spacing_m": [float(v) for v in sweep0.spacing],
        },
        "localization": {
            "method": settings.localization.method,
            "n_sweeps": n_sweeps,
            "n_rejected": n_rejected,
        },
        "calibration": calibration,
        "timing_s": {"read": t_read, "total": time.perf_counter() - t0},
    }
    if evaluation is not None:
        metrics["evaluation"] = evaluation
        metrics["dh_table_refined"] = found.dh_table.as_array().tolist()
    return RecordedCalibration(metrics, dataset, info, cals, found.axial_scale, found.dh_table)


def _folds(run: FoldRun) -> dict[str, Any]:
    """The paper's folds of one dataset against its touch reference, as metrics."""
    rows = [
        {
            "fold": r.fold.name,
            "kind": r.fold.kind,
            "train": list(r.fold.train),
            "test": list(r.fold.test),
            "precision_mm": r.precision_mm,
            "accuracy_mm": r.accuracy_mm,
            "T_ee_us": np.round(r.T_ee_us, 9).tolist(),
        }
        for r in run.results
    ]
    return {"folds": rows, "summary": fold_summary(run.results)}


def recorded_run_result(recorded: RecordedCalibration, settings: Scenario) -> RunResult:
    """A recorded dataset's calibration (``uscal calibrate``) as the report draws a run."""
    cals = recorded.calibrations
    first = cals.single or cals.three
    snapshot = None
    if first is not None:
        snapshot = dataset_snapshot(
            recorded.dataset,
            first,
            recorded.info.sphere_radius_mm * 1e-3,
            settings.localization,
            recorded.axial_scale,
        )
    return RunResult(recorded.metrics, None, cals.single, cals.three, snapshot=snapshot)
