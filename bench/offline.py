"""Recorded data: the twin's acquisitions as dataset files, and ``uscal calibrate`` —
localization and single-/three-marker calibration of a dataset on disk (from the
hardware or from the twin), with no ground truth.

The acquisition's facts come from the dataset (frames, reported poses and joint angles,
pixel spacing, medium temperature, the phantom's CAD landmarks, the holder's coarse
``T_ee_us``); the pipeline's settings (localizer, alternation limits) from a scenario,
the built-in default unless the user names one.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.calibrate import AlternationResult, alternate
from calib.dataset_files import AcquisitionInfo, DatasetWriter, read_dataset
from calib.dh import DHTable
from calib.errors import DatasetError
from calib.evaluate import evaluate_fold, folds, training_precision
from calib.kinematics import TouchReference, fit_reference, refine_dh, with_kinematics
from calib.localization import LocalizerConfig
from calib.localize import localize_sphere
from calib.records import Dataset
from calib.uncertainty import Bound95, UncertaintyInputs, alternation_bound, image_grid

from .experiment import SimulatedAcquisition, speed_ratio
from .progress import report
from .scenario import Scenario, layout_sigma_mm
from .truth import transform_difference

__all__ = [
    "THERMOMETER_UNCERTAINTY_C",
    "MarkerCalibrations",
    "acquisition_info",
    "calibrate_markers",
    "calibrate_recorded",
    "declared_uncertainty",
    "record_recorded",
    "save_dataset",
]

Array = NDArray[np.float64]
_MM = 1e3


# ------------------------------------------------------------------ twin → dataset


def acquisition_info(scenario: Scenario, twin, T_ee_us_coarse: Array) -> AcquisitionInfo:
    """What a twin acquisition's dataset records besides its sweeps: what the pipeline
    knows (CAD landmarks, coarse mount, settings), never the truth."""
    return AcquisitionInfo(
        T_ee_us_coarse=np.asarray(T_ee_us_coarse, dtype=float),
        landmarks={k: np.asarray(v, dtype=float) for k, v in twin.phantom_cad.landmarks.items()},
        sphere_radius_mm=scenario.phantom.sphere_radius_mm,
        temperature_c=scenario.medium.temperature_c,
        assumed_speed_m_s=scenario.imaging.assumed_speed_m_s,
        sound_speed_correction=scenario.imaging.sound_speed_correction,
        medium=scenario.medium.kind,
        stylus_tip_cad_mm=tuple(scenario.evaluation.stylus_tip_cad_mm),
        source="twin",
        target_depth_mm=scenario.protocol.target_depth_mm,
        extra={"scenario": scenario.source, "seed": scenario.seed},
    )


def image_meta(scenario: Scenario) -> dict[str, Any]:
    """The probe settings a dataset's manifest keeps (for the reader's information)."""
    im = scenario.imaging
    H, W = im.image_shape
    return {
        "width_px": int(W),
        "height_px": int(H),
        "pixel_spacing_mm": [float(v) for v in im.pixel_spacing_mm],
        "depth_mm": float(im.depth_mm),
        "f_mhz": float(im.f_mhz),
        "gain_db": float(im.gain_db),
    }


def save_dataset(
    directory: str | os.PathLike[str], scenario: Scenario, twin, acq: SimulatedAcquisition
) -> Path:
    """Write a twin acquisition in the dataset format (:mod:`calib.dataset_files`).

    The twin has no acquisition clock; each frame's timestamp is its index in the
    dataset times a nominal frame period, so timestamps increase through the dataset.
    """
    writer = DatasetWriter(
        directory,
        acq.dataset.name,
        acquisition_info(scenario, twin, acq.T_ee_us_coarse),
        image_meta(scenario),
    )
    period = 0.5  # s per frame: settle and grab
    n = 0
    for sweep in acq.dataset.sweeps:
        writer.add_sweep(sweep, period * (n + np.arange(sweep.n_frames)))
        n += sweep.n_frames
    writer.add_touches(acq.dataset.touches)
    writer.finish()
    return Path(directory)


# ----------------------------------------------------------------- calibration


def axial_scale_of(info: AcquisitionInfo) -> float:
    """The axial spacing's correction factor from the recorded water temperature."""
    return speed_ratio(
        info.sound_speed_correction, info.medium, info.temperature_c, info.assumed_speed_m_s
    )


@dataclass(frozen=True, eq=False)
class MarkerCalibrations:
    """The single-marker calibration (first sphere) and, with three or more spheres and
    ``markers`` 3, the three-marker one (first three)."""

    targets: list[str]
    single: AlternationResult | None
    three: AlternationResult | None


def calibrate_markers(
    dataset: Dataset,
    radius: float,
    localizer: LocalizerConfig,
    axial_scale: float,
    cad_centres: dict[str, Array],
    T_coarse: Array,
    max_alternations: int,
    markers: tuple[int, ...] = (1, 3),
    layout_sigma_mm: float = 0.0,
) -> MarkerCalibrations:
    """Localize ↔ calibrate (the paper's alternation) with one and/or three markers;
    the three-marker fit estimates the printed layout at ``layout_sigma_mm`` (see
    :func:`calib.calibrate.calibrate`)."""
    targets = dataset.targets()
    by_target = {t: dataset.of(t) for t in targets}
    if 3 in markers and len(targets) < 3 and 1 not in markers:
        raise DatasetError(
            f"dataset {dataset.name}: three-marker calibration needs sweeps of three "
            f"spheres; it has {', '.join(targets)}"
        )
    missing = [t for t in targets[:3] if t not in cad_centres]
    if 3 in markers and len(targets) >= 3 and missing:
        raise DatasetError(
            f"dataset {dataset.name}: no CAD centre for {', '.join(missing)} (acquisition."
            "landmarks_mm)"
        )
    run_three = 3 in markers and len(targets) >= 3
    n_cal = int(1 in markers) + int(run_three)
    report("calibrations", 0, n_cal)
    single = three = None
    if 1 in markers:
        single = alternate(
            {targets[0]: by_target[targets[0]]},
            radius,
            localizer,
            axial_scale,
            None,
            T_coarse,
            max_alternations,
        )
        report("calibrations", 1, n_cal)
    if run_three:
        three = alternate(
            {t: by_target[t] for t in targets[:3]},
            radius,
            localizer,
            axial_scale,
            {t: cad_centres[t] for t in targets[:3]},
            T_coarse,
            max_alternations,
            layout_sigma_mm=layout_sigma_mm,
        )
        report("calibrations", n_cal, n_cal)
    return MarkerCalibrations(targets, single, three)


#: Uncertainty (°C) of the water temperature a user reads off a lab thermometer: with the
#: speed-of-sound correction, the axial scale is uncertain by the speed's change over it
#: (≈ 0.1 % at 20 °C, Marczak's formula).
THERMOMETER_UNCERTAINTY_C = 0.5


def declared_uncertainty(
    print_tolerance_mm: float,
    sound_speed_correction: bool,
    medium: str,
    temperature_c: float,
    assumed_speed_m_s: float,
    kinematic_residual_rms_mm: float = 0.0,
    radius_tolerance_mm: float = 0.0,
    axial_fwhm_mm: float = 0.0,
) -> UncertaintyInputs:
    """The systematic terms the pipeline knows of (:class:`calib.uncertainty.
    UncertaintyInputs`): the phantom's print specification (1 σ per axis of a sphere
    centre, 1 σ of a sphere's radius), the axial scale's uncertainty — with the
    speed-of-sound correction, the thermometer's; without, the whole difference
    between the medium's speed at the recorded temperature and the scanner's assumed
    one — the localizer's bias along the beam (uniform within ± half the probe's axial
    resolution, as 1 σ: FWHM / (2√3)) and the kinematic model's
    residual after a DH refinement (RMS distance of the touches from the model; per axis
    it is that over √3)."""
    ratio = speed_ratio(True, medium, temperature_c, assumed_speed_m_s)
    if sound_speed_correction:
        warmer = speed_ratio(
            True, medium, temperature_c + THERMOMETER_UNCERTAINTY_C, assumed_speed_m_s
        )
        scale_sigma = abs(warmer / ratio - 1.0)
    else:
        scale_sigma = abs(ratio - 1.0)
    return UncertaintyInputs(
        print_tolerance_m=print_tolerance_mm * 1e-3,
        radius_tolerance_m=radius_tolerance_mm * 1e-3,
        axial_bias_m=axial_fwhm_mm * 1e-3 / (2.0 * np.sqrt(3.0)),
        kinematic_sigma_m=kinematic_residual_rms_mm * 1e-3 / np.sqrt(3.0),
        axial_scale_sigma=scale_sigma,
    )


def scenario_uncertainty(
    scenario: Scenario, kinematic_residual_rms_mm: float = 0.0
) -> UncertaintyInputs:
    """:func:`declared_uncertainty` of a twin's scenario: its phantom's print tolerance
    as the print specification, its medium and speed-of-sound setting."""
    return declared_uncertainty(
        scenario.phantom.tolerance_position_mm,
        scenario.imaging.sound_speed_correction,
        scenario.medium.kind,
        scenario.medium.temperature_c,
        scenario.imaging.assumed_speed_m_s,
        kinematic_residual_rms_mm,
        scenario.phantom.tolerance_radius_mm,
        scenario.imaging.axial_fwhm_mm,
    )


def uncertainty_entry(bound: Bound95, inputs: UncertaintyInputs) -> dict[str, Any]:
    """``metrics.json``'s ``bound95`` and ``uncertainty`` of one calibration."""
    details = bound.details()
    details["declared"] = {
        "print_tolerance_mm": inputs.print_tolerance_m * _MM,
        "radius_tolerance_mm": inputs.radius_tolerance_m * _MM,
        "axial_bias_mm": inputs.axial_bias_m * _MM,
        "kinematic_sigma_mm": inputs.kinematic_sigma_m * _MM,
        "axial_scale_sigma": inputs.axial_scale_sigma,
    }
    return {"bound95": bound.as_dict(), "uncertainty": details}


def calibration_entry(
    alt: AlternationResult,
    train: list[str],
    test: list[str],
    bound: tuple[Bound95, UncertaintyInputs] | None = None,
) -> dict[str, Any]:
    """What ``metrics.json`` keeps of one calibration, truth aside (``bound``: its 95 %
    error bounds and the declared terms they include)."""
    precision = training_precision(alt)
    return {
        "precision_mm": float(np.mean([precision[t] for t in train])),
        "n_retained": int(alt.result.retained.sum()),
        "iterations": len(alt.history),
        "rejected": dict(alt.result.rejection_reasons),
        "T_ee_us": np.round(alt.result.T_ee_us, 9).tolist(),
        "covariance_rotvec_rad_translation_m": alt.result.covariance.tolist(),
        "history": alt.history,
        "trained_on": list(train),
        "tested_on": list(test),
        **(uncertainty_entry(*bound) if bound is not None else {}),
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


@dataclass(frozen=True, eq=False)
class RecordedCalibration:
    """``uscal calibrate``'s result: metrics, and what they came from."""

    metrics: dict[str, Any]
    dataset: Dataset
    info: AcquisitionInfo
    calibrations: MarkerCalibrations
    dh_table: DHTable | None = None  # refined from touches, when the dataset has them

    @property
    def axial_scale(self) -> float:
        return axial_scale_of(self.info)


def record_recorded(options, settings: Scenario, result: RecordedCalibration) -> int:
    """The calibration of a recorded dataset in rerun (:func:`bench.recording.
    log_acquisition` without truth or scene: the phantom's placement is unknown). The arm
    is drawn from the settings' robot model at the reported joint angles."""
    from .experiment import make_twin
    from .recording import Recorder, log_acquisition, merge_parts

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
) -> tuple[DHTable, TouchReference, str, float]:
    """The paper's touch-based steps on recorded data: DH corrections from the touches of
    ``dh_from`` (the paper's leave-one-dataset-out; this dataset's own when empty), then
    this dataset's tip offset and phantom pose with that model frozen. Also returns the
    refinement's residual (RMS touch distance, mm)."""
    vertices = {k: v for k, v in info.landmarks.items() if k.startswith("vertex_")}
    if not vertices:
        raise DatasetError(f"dataset {dataset.name}: touches but no vertex_* landmarks")
    tip = np.asarray(info.stylus_tip_cad_mm, dtype=float) * 1e-3
    ev = settings.evaluation
    sources = dh_from or [(dataset, info)]
    refinement = refine_dh(
        settings.robot.nominal_table,
        [d.touches for d, _ in sources],
        vertices,
        tip,
        ev.dh_regularizer,
        ev.initialisations,
        ev.dh_bound,
    )
    table = refinement.table
    origin = ", ".join(d.name for d, _ in sources)
    rms = float(np.sqrt(np.mean(refinement.residuals_mm**2)))
    return table, fit_reference(table, dataset.touches, vertices, tip), origin, rms


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
    radius = info.sphere_radius_mm * 1e-3
    scale = axial_scale_of(info)
    cad = {k: v for k, v in info.landmarks.items() if k.startswith("sphere_")}
    evaluation: dict[str, Any] | None = None
    dh_table: DHTable | None = None
    kinematic_rms_mm = 0.0  # the controller's own model: no residual known
    if dataset.touches:
        t1 = time.perf_counter()
        dh_table, reference, origin, kinematic_rms_mm = _touch_kinematics(
            dataset, info, settings, others
        )
        # Every frame's flange pose from its joint angles through the refined model.
        dataset = Dataset(
            dataset.name,
            tuple(s for t in dataset.targets() for s in with_kinematics(dataset.of(t), dh_table)),
            dataset.meta,
            dataset.touches,
        )
        evaluation = {"dh_from": origin, "touches": len(dataset.touches)}
        evaluation["touch_residual_rms_mm"] = float(np.sqrt(np.mean(reference.residuals_mm**2)))
        evaluation["tool_precision_mm"] = {
            k: float(v) for k, v in reference.tool_precision_mm.items()
        }
        evaluation["seconds_dh"] = time.perf_counter() - t1
    cals = calibrate_markers(
        dataset,
        radius,
        settings.localization,
        scale,
        cad,
        info.T_ee_us_coarse,
        settings.calibration.max_alternations,
        markers,
        layout_sigma_mm(settings),
    )
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
        evaluation.update(
            _folds(dataset, reference, radius, settings, scale, cad, info.T_ee_us_coarse)
        )
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
    return RecordedCalibration(metrics, dataset, info, cals, dh_table)


def _folds(dataset, reference, radius, settings, scale, cad, T_coarse) -> dict[str, Any]:
    """The paper's folds of one dataset against its touch reference."""
    targets = dataset.targets()
    sweeps = {t: dataset.of(t) for t in targets}
    cfg = settings.localization
    initial = {t: localize_sphere(sweeps[t], None, radius, cfg, scale) for t in targets}
    references = reference.reference_points({t: cad[t] for t in targets})
    fold_list = folds(dataset.name, targets)
    rows = []
    for k, fold in enumerate(fold_list):
        report("folds", k, len(fold_list))
        r = evaluate_fold(
            fold,
            sweeps,
            initial,
            references,
            radius,
            cfg,
            scale,
            cad,
            T_coarse,
            settings.calibration.max_alternations,
            layout_sigma_mm(settings),
        )
        rows.append(
            {
                "fold": fold.name,
                "kind": fold.kind,
                "train": list(fold.train),
                "test": list(fold.test),
                "precision_mm": r.precision_mm,
                "accuracy_mm": r.accuracy_mm,
                "T_ee_us": np.round(r.T_ee_us, 9).tolist(),
            }
        )
    report("folds", len(fold_list), len(fold_list))
    summary = {}
    for kind in ("single", "three"):
        acc = [v for row in rows if row["kind"] == kind for v in row["accuracy_mm"].values()]
        prec = [v for row in rows if row["kind"] == kind for v in row["precision_mm"].values()]
        if acc:
            summary[kind] = {
                "accuracy_mm": {"mean": float(np.mean(acc)), "sd": float(np.std(acc))},
                "precision_mm": {"mean": float(np.mean(prec)), "sd": float(np.std(prec))},
            }
    return {"folds": rows, "summary": summary}
