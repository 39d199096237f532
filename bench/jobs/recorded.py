"""``uscal calibrate``: localization and single-/three-marker calibration of a dataset
on disk (from the hardware or from the twin), with no ground truth; with touches, the
paper's touch-based kinematics and folds on it.

The acquisition's facts come from the dataset (frames, reported poses and joint angles,
pixel spacing, medium temperature, the phantom's CAD landmarks, the holder's coarse
``T_ee_us``); the pipeline's settings (localizer, alternation limits) from a scenario,
the built-in default unless the user names one.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from calib.dataset_files import AcquisitionInfo, read_dataset
from calib.dh import DHTable
from calib.errors import DatasetError
from calib.kinematics import with_kinematics
from calib.records import Dataset
from calib.uncertainty import alternation_bound, image_grid

from ..acquire_sim import make_twin
from ..config.scenario import Scenario
from ..pipeline import (
    MethodInputs,
    axial_scale_of,
    calibrate_markers,
    declared_uncertainty,
    fold_summary,
    residual_rms_mm,
    run_folds,
    touch_kinematics,
)
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


def _touch_kinematics(
    dataset: Dataset,
    info: AcquisitionInfo,
    settings: Scenario,
    dh_from: list[tuple[Dataset, AcquisitionInfo]],
):
    """The paper's touch-based steps on recorded data (:func:`bench.pipeline.
    touch_kinematics`): DH corrections from the touches of ``dh_from`` (the paper's
    leave-one-dataset-out; this dataset's own when empty), then this dataset's reference
    with that model frozen. Also returns the names the model was refined from."""
    vertices = {k: v for k, v in info.landmarks.items() if k.startswith("vertex_")}
    if not vertices:
        raise DatasetError(f"dataset {dataset.name}: touches but no vertex_* landmarks")
    tip = np.asarray(info.stylus_tip_cad_mm, dtype=float) * 1e-3
    sources = dh_from or [(dataset, info)]
    refinement, reference = touch_kinematics(
        settings.robot.nominal_table,
        [d.touches for d, _ in sources],
        dataset.touches,
        vertices,
        tip,
        settings.evaluation,
    )
    return refinement, reference, ", ".join(d.name for d, _ in sources)


def calibrate_recorded(
    directory: str | os.PathLike[str],
    settings: Scenario,
    markers: tuple[int, ...] = (1, 3),
    dh_from: tuple[str | os.PathLike[str], ...] = (),
) -> RecordedCalibration:
    """Read a dataset and calibrate it (no ground truth: precision, the calibrations'
    own uncertainty, and consistency between the spheres).

    With touches in the dataset, the paper's evaluation follows: the DH model refined from
    the touches of the ``dh_from`` datasets (this dataset's own when none), every frame's
    flange pose recomputed from its joint angles with it, this dataset's touch reference,
    and the paper's folds (each sphere trained alone and tested on the others, then
    leave-one-out) scored by precision and accuracy against the touch reference."""
    t0 = time.perf_counter()
    dataset, info = read_dataset(directory)
    # Where this dataset's plan put the spheres, not where the settings' protocol would
    # (a dataset that did not record it is searched over the whole image).
    settings = dataclasses.replace(
        settings,
        localization=dataclasses.replace(
            settings.localization, expected_depth_mm=info.target_depth_mm
        ),
    )
    others = [read_dataset(d) for d in dh_from]
    for d, _ in others:
        if not d.touches:
            raise DatasetError(f"--dh-from: dataset {d.name} has no touches")
    if others and not dataset.touches:
        raise DatasetError(f"--dh-from: dataset {dataset.name} itself has no touches")
    t_read = time.perf_counter() - t0
    scale = axial_scale_of(info)
    cad = {k: v for k, v in info.landmarks.items() if k.startswith("sphere_")}
    evaluation: dict[str, Any] | None = None
    dh_table: DHTable | None = None
    kinematic_rms_mm = 0.0  # the controller's own model: no residual known
    if dataset.touches:
        t1 = time.perf_counter()
        refinement, reference, origin = _touch_kinematics(dataset, info, settings, others)
        dh_table, kinematic_rms_mm = refinement.table, residual_rms_mm(refinement.residuals_mm)
        # Every frame's flange pose from its joint angles through the refined model.
        dataset = Dataset(
            dataset.name,
            tuple(s for t in dataset.targets() for s in with_kinematics(dataset.of(t), dh_table)),
            dataset.meta,
            dataset.touches,
        )
        evaluation = {"dh_from": origin, "touches": len(dataset.touches)}
        evaluation["touch_residual_rms_mm"] = residual_rms_mm(reference.residuals_mm)
        evaluation["tool_precision_mm"] = {
            k: float(v) for k, v in reference.tool_precision_mm.items()
        }
        evaluation["seconds_dh"] = time.perf_counter() - t1
    method = MethodInputs.of(settings, info.sphere_radius_mm, scale, cad, info.T_ee_us_coarse)
    cals = calibrate_markers(dataset, method, markers)
    targets = cals.targets
    final: dict[str, Any] = {}
    calibration: dict[str, Any] = {}
    # The bounds' declared terms: the settings' print specification of the phantom, the
    # recorded medium, the refinement's residual.
    inputs = declared_uncertainty(
        settings.phantom.tolerance_position_mm,
        info.sound_speed_correction,
        info.medium,
        info.temperature_c,
        info.assumed_speed_m_s,
        kinematic_rms_mm,
        settings.phantom.tolerance_radius_mm,
        settings.imaging.axial_fwhm_mm,
    )
    sweep0 = dataset.sweeps[0]
    H, W = sweep0.images.shape[1:]
    grid = image_grid((W - 1) * sweep0.spacing[0], (H - 1) * sweep0.spacing[1] * scale)
    if cals.single is not None:
        final.update(cals.single.localizations)
        bound = alternation_bound(cals.single, grid, None, inputs)
        calibration["single"] = calibration_entry(
            cals.single, targets[:1], targets[1:], (bound, inputs)
        )
    if cals.three is not None:
        final.update(cals.three.localizations)
        bound = alternation_bound(cals.three, grid, {t: cad[t] for t in targets[:3]}, inputs)
        calibration["three"] = calibration_entry(
            cals.three, targets[:3], targets[3:], (bound, inputs)
        )
    n_sweeps = sum(len(v) for v in final.values())
    n_rejected = sum(not loc.accepted for v in final.values() for loc in v)
    if cals.single is not None and cals.three is not None:
        a, b = cals.single.result.T_ee_us, cals.three.result.T_ee_us
        calibration["single_vs_three"] = transform_difference(a, b)
    if evaluation is not None and len(targets) >= 2:
        evaluation.update(_folds(dataset, reference, method))
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
            "axial_scale": scale,
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
        metrics["dh_table_refined"] = dh_table.as_array().tolist()
    return RecordedCalibration(metrics, dataset, info, cals, scale, dh_table)


def _folds(dataset: Dataset, reference, method: MethodInputs) -> dict[str, Any]:
    """The paper's folds of one dataset against its touch reference."""
    targets = dataset.targets()
    run = run_folds(
        dataset.name,
        {t: dataset.of(t) for t in targets},
        reference.reference_points({t: method.cad_centres[t] for t in targets}),
        method,
    )
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
