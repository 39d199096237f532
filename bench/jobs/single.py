"""``uscal run``: simulate the scenario's acquisition with the twin, localize, calibrate
(single- and three-marker), and measure everything against the twin's ground truth."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.protocol import sweep_axis_off_normal
from calib.calibration.alternation import AlternationResult
from calib.calibration.uncertainty import UncertaintyInputs, alternation_bound
from calib.calibration.verdict import sweep_geometry
from calib.errors import UscalError
from calib.kinematics import DHRefinement, with_kinematics
from calib.localize import localize_sphere
from calib.pipeline import (
    calibrate_markers,
    refinement_modes,
    residual_rms_mm,
    touch_kinematics,
)
from twin.imager import acoustic_scene

from ..acquire_sim import (
    SimulatedAcquisition,
    make_imager,
    make_twin,
    simulate_acquisition,
    simulate_touches,
)
from ..acquire_sim import save_dataset as save_dataset_files
from ..config.geometry import TARGET_PHANTOMS
from ..config.method import (
    axial_scale,
    image_points,
    method_inputs,
    requirements,
    scenario_uncertainty,
    stated_radius,
)
from ..config.scenario import Scenario
from ..recording.logs import log_acquisition, log_target, merge_parts
from ..recording.options import RecordingOptions
from ..recording.recorder import Recorder
from ..results import RunResult, calibration_entry
from ..sequential import StopRule, acquire_until
from ..sessions import dataset_rngs
from ..truth import (
    equivalent_mount,
    localization_errors,
    mount_error,
    snapshot_of,
    transform_difference,
)
from .paper import run_evaluation
from .targets import run_target

__all__ = ["run"]

Array = NDArray[np.float64]


def _true_errors(scenario, T_est, T_true) -> dict[str, float]:
    return mount_error(scenario, T_est, T_true)


def refine_from_touches(
    scenario: Scenario, acq: SimulatedAcquisition, twin
) -> tuple[SimulatedAcquisition, DHRefinement]:
    """One acquisition's own touches (``evaluation.touches_one_dataset``): the stylus on
    every cone vertex (on the twin of the same arm, its own joint and contact noise, as
    the paper's datasets are touched), the DH model refined from them, and every frame's
    flange pose recomputed from its joint angles with the refined model."""
    rngs = dataset_rngs(scenario, 0)
    touched = make_twin(scenario, rngs["touch_joints"])
    touches = simulate_touches(scenario, touched, rngs["touch_contact"])
    vertices = {k: v for k, v in twin.phantom_cad.landmarks.items() if k.startswith("vertex_")}
    refinement, _ = touch_kinematics(
        scenario.robot.nominal_table,
        [touches],
        touches,
        vertices=vertices,
        tip_cad=np.asarray(scenario.evaluation.stylus_tip_cad_mm, dtype=float) * 1e-3,
        evaluation=scenario.evaluation,
    )
    return _with_refined_kinematics(acq, refinement, touches), refinement


def _with_refined_kinematics(
    acq: SimulatedAcquisition, refinement: DHRefinement, touches
) -> SimulatedAcquisition:
    """``acq`` with every frame's flange pose recomputed from its joint angles with the
    refined DH model, and the touches it was refined from."""
    ds = acq.dataset
    sweeps = tuple(s for t in ds.targets() for s in with_kinematics(ds.of(t), refinement.table))
    return replace(acq, dataset=replace(ds, sweeps=sweeps, touches=tuple(touches)))


def _calibration_metrics(
    scenario,
    acq,
    truth,
    alt: AlternationResult,
    train,
    test,
    radius,
    scale,
    localizer,
    cad=None,
    inputs: UncertaintyInputs | None = None,
    X_equiv: Array | None = None,
) -> dict[str, Any]:
    T_est = alt.result.T_ee_us
    # Accuracy on spheres not used for calibration (re-localized with this estimate);
    # on the training spheres when there are none.
    accuracy = []
    sweeps = acq.dataset
    for target in test or train:
        locs = localize_sphere(sweeps.of(target), T_est, radius, localizer, axial_scale=scale)
        pts = [
            se3.apply(s.T_base_ee[s.reference_index] @ T_est, loc.centre)
            for s, loc in zip(sweeps.of(target), locs, strict=True)
            if loc.accepted
        ]
        if pts:
            accuracy.append(np.linalg.norm(np.mean(pts, axis=0) - truth.landmarks_base[target]))
    bound = None
    if inputs is not None:
        multi = {t: cad[t] for t in train} if cad is not None and len(train) >= 2 else None
        bound = (
            alternation_bound(alt, image_points(scenario), cad_centres=multi, inputs=inputs),
            inputs,
        )
    entry = calibration_entry(
        alt,
        list(train),
        list(test),
        bound,
        requirements(scenario),
        geometry=sweep_geometry(alt, acq.dataset.sweeps, radius),
    )
    out: dict[str, Any] = {"true_error": _true_errors(scenario, T_est, truth.T_ee_us)}
    if X_equiv is not None:
        # Against the mount that is right through the controller's (off) model.
        out["true_error_equivalent"] = _true_errors(scenario, T_est, X_equiv)
    if bound is not None:
        out["bound95"] = entry.pop("bound95")
    out["accuracy_mm"] = 1e3 * float(np.mean(accuracy)) if accuracy else float("nan")
    return out | entry


def _record_target(options: RecordingOptions, twin, acq: SimulatedAcquisition, result) -> int:
    """A run calibrated from wires or a cone's tip in rerun (see :mod:`bench.recording`):
    its frames, the observations through the answer, and the targets where the fit and
    the truth put them; returns the number of B-mode frames logged."""
    cal, truth = result.calibration, twin.truth
    if twin.phantom_cad.wires:
        names = [w.name for w in twin.phantom_cad.wires]
        fitted = [
            se3.apply(cal.T_base_phantom, np.array([w.front, w.back]))
            for w in twin.phantom_cad.wires
        ]
        true = [
            np.array([truth.landmarks_base[f"{n}_front"], truth.landmarks_base[f"{n}_back"]])
            for n in names
        ]
    else:  # the cone's tip
        fitted = [se3.apply(cal.T_base_phantom, twin.phantom_cad.landmarks["apex"])[None]]
        true = [truth.landmarks_base["apex"][None]]
    rec = Recorder(options)
    logged = log_target(
        rec,
        "run",
        acoustic_scene(twin.robot.scene.scene).parts,
        twin.scene.model,
        acq.dataset,
        cal,
        fitted,
        truth=(acq.T_base_ee_true, truth.T_ee_us, true),
    )
    merge_parts(options, [], ["run"], main=rec)
    return logged


def _record_run(
    options: RecordingOptions,
    scenario: Scenario,
    twin,
    acq: SimulatedAcquisition,
    single: AlternationResult,
    three: AlternationResult | None,
) -> int:
    """The single-acquisition run in rerun (see :mod:`bench.recording`); returns the
    number of B-mode frames logged."""
    rec = Recorder(options)
    alternations = {"single": single} | ({"three": three} if three is not None else {})
    logged = log_acquisition(
        rec,
        "run",
        acoustic_scene(twin.robot.scene.scene).parts,
        twin.scene.model,
        acq.dataset,
        alternations,
        stated_radius(scenario),
        scenario.localization,
        axial_scale(scenario),
        truth=(acq.T_base_ee_true, twin.truth.T_ee_us, twin.truth.landmarks_base),
    )
    merge_parts(options, [], ["run"], main=rec)
    return logged


def _second_pass(
    scenario: Scenario,
    twin,
    imager,
    acq: SimulatedAcquisition,
    cals,
    refinement: DHRefinement | None,
    cad: dict[str, Array],
):
    """``protocol.second_pass``: every sphere scanned again with the sweeps planned
    through the first pass's calibration (three-marker when it ran), so that they run
    along the image normal, and calibrated on those. Returns the second acquisition, its
    calibrations, and the first pass's figures against the truth."""
    used = cals.three if cals.three is not None else cals.single
    T_first = used.result.T_ee_us
    truth = twin.truth
    first = {
        "robot_time_s": acq.robot_time_s,
        "coarse_error": transform_difference(acq.T_ee_us_coarse, truth.T_ee_us),
        "sweep_axis": sweep_axis_off_normal(acq.dataset.sweeps, T_first),
        "true_error": {
            name: _true_errors(scenario, alt.result.T_ee_us, truth.T_ee_us)
            for name, alt in (("single", cals.single), ("three", cals.three))
            if alt is not None
        },
    }
    # Whether the verdict would have called the first pass suspect for its sweeps' tilt.
    tilted = {}
    for name, alt in (("single", cals.single), ("three", cals.three)):
        if alt is not None:
            geometry = sweep_geometry(alt, acq.dataset.sweeps, stated_radius(scenario))
            tilted[name] = geometry is not None and geometry.tilted_over_shallow_caps
    first["tilted_over_shallow_caps"] = tilted
    t0 = time.perf_counter()
    again = simulate_acquisition(
        scenario, twin, imager, progress="second pass: acquire sweeps", T_ee_us_coarse=T_first
    )
    first["simulate_s"] = time.perf_counter() - t0  # the second scan's, counted in "simulate"
    if refinement is not None:  # the first pass's touches and DH model hold for it too
        again = _with_refined_kinematics(again, refinement, acq.dataset.touches)
    method = method_inputs(scenario, cad_centres=cad, T_coarse=T_first)
    return again, calibrate_markers(again.dataset, method), first


def run(
    scenario: Scenario,
    progress: Callable[[str], None] | None = None,
    recording: RecordingOptions | None = None,
    save_dataset: str | os.PathLike[str] | None = None,
    until: StopRule | None = None,
) -> RunResult:
    """The whole experiment of a scenario; returns metrics against ground truth.

    With two or more ``evaluation.datasets`` this is the paper's experiment (touches,
    leave-one-dataset-out DH refinement, folds, Tables I and II); otherwise one
    acquisition calibrated with the controller's kinematics. ``recording`` writes a
    rerun recording of it (:mod:`bench.recording`). ``save_dataset``: a directory to write
    the acquisition to in the dataset format (:mod:`calib.files.dataset`), which
    ``uscal calibrate`` reads back (the paper's experiment: one per dataset,
    ``<dir>/<name>``, with its touches). ``until``: acquire sequentially, each next sweep
    the most informative, until the predicted bounds are reached (:mod:`bench.sequential`;
    one acquisition only).
    """
    if until is not None and len(scenario.evaluation.datasets) >= 2:
        raise UscalError(
            "--until-rotation-deg / --until-translation-mm: the sequential acquisition is "
            f"one acquisition; this scenario runs the paper's experiment on "
            f"{len(scenario.evaluation.datasets)} datasets (set evaluation.datasets=[A])"
        )
    if scenario.protocol.second_pass and (
        until is not None
        or len(scenario.evaluation.datasets) >= 2
        or scenario.phantom.kind in TARGET_PHANTOMS
    ):
        raise UscalError(
            "protocol.second_pass: a second scan along the calibrated normal follows one "
            "sphere acquisition calibrated as it stands; not the sequential acquisition "
            "(--until-*), the paper's experiment on several datasets (evaluation.datasets) "
            "or a wire or N-wire phantom"
        )
    if len(scenario.evaluation.datasets) >= 2:
        save = Path(save_dataset) if save_dataset is not None else None
        ev = run_evaluation(scenario, progress, recording, save)
        return RunResult(ev.metrics, evaluation=ev, snapshot=ev.outcomes[0].snapshot)
    t_start = time.perf_counter()
    twin = make_twin(scenario)
    imager = make_imager(scenario, twin)
    scans = []
    if until is None:
        acq = simulate_acquisition(scenario, twin, imager, progress="acquire sweeps")
    else:
        acq, scans = acquire_until(scenario, twin, imager, until, progress="acquire sweeps")
    if scenario.phantom.kind in TARGET_PHANTOMS:
        nwire = run_target(scenario, twin, acq, t_start)
        if recording is not None:
            t0 = time.perf_counter()
            frames = _record_target(recording, twin, acq, nwire)
            nwire.metrics["recording"] = {"frames": frames, "seconds": time.perf_counter() - t0}
        if save_dataset is not None:
            save_dataset_files(save_dataset, scenario, twin, acq)
        return RunResult(nwire.metrics, acq, nwire=nwire)
    refinement = None
    if scenario.evaluation.touches_one_dataset:
        acq, refinement = refine_from_touches(scenario, acq, twin)
    t_sim = time.perf_counter() - t_start
    truth = twin.truth
    radius = stated_radius(scenario)  # the CAD radius: the only prior
    scale = axial_scale(scenario)
    loc_cfg = scenario.localization
    targets = acq.dataset.targets()
    cad = {k: v for k, v in twin.phantom_cad.landmarks.items() if k.startswith("sphere_")}

    method = method_inputs(scenario, cad_centres=cad, T_coarse=acq.T_ee_us_coarse)
    cals = calibrate_markers(acq.dataset, method)
    first_pass = None
    if scenario.protocol.second_pass:
        acq, cals, first_pass = _second_pass(scenario, twin, imager, acq, cals, refinement, cad)
    single, three = cals.single, cals.three
    assert single is not None  # markers 1 and 3: the single-marker calibration always runs
    # Localization error of the final single-marker localizations vs the true centres.
    # As the calibrations used them: a centre a calibration dropped is not localized.
    final = {targets[0]: single.retained_localizations()[targets[0]]}
    if three is not None:
        final.update(three.retained_localizations())
    errors, n_sweeps, n_rejected = localization_errors(acq, truth, final)
    errors = errors if len(errors) else np.array([np.nan])
    # The bounds' declared terms: the phantom's print specification and the medium; the
    # refinement's touch residual where the arm's model was refined (none is known for
    # the controller's own model).
    kinematic_rms = 0.0 if refinement is None else residual_rms_mm(refinement.residuals_mm)
    inputs = scenario_uncertainty(
        scenario, kinematic_rms, refinement_modes(refinement, acq.dataset.sweeps)
    )
    X_equiv = equivalent_mount(scenario, acq, truth, refinement and refinement.table)
    extra = (cad, inputs, X_equiv)
    hist = single.history + (three.history if three else [])
    t_loc = float(sum(h["localize_s"] for h in hist))
    t_cal = float(sum(h["calibrate_s"] for h in hist))
    metrics: dict[str, Any] = {
        "scenario": {"name": scenario.source, "seed": scenario.seed},
        "acquisition": {
            "sweeps": len(acq.dataset.sweeps),
            "frames": int(sum(s.n_frames for s in acq.dataset.sweeps)),
            "robot_time_s": acq.robot_time_s,
            "plan": "sequential" if until else scenario.protocol.plan or "paper",
            "replaced": [r.line() for r in acq.replaced],
            "touches": len(acq.dataset.touches),
            **({"sequential": {s.target: s.as_dict() for s in scans}} if until else {}),
        },
        "localization": {
            "method": loc_cfg.method,
            "n_sweeps": n_sweeps,
            "n_rejected": n_rejected,
            "error_mm": {
                "median": float(np.median(errors)),
                "p95": float(np.percentile(errors, 95)),
                "max": float(np.max(errors)),
            },
        },
        "calibration": {
            "coarse_error": transform_difference(acq.T_ee_us_coarse, truth.T_ee_us),
            "sweep_axis": sweep_axis_off_normal(
                acq.dataset.sweeps, (three if three is not None else single).result.T_ee_us
            ),
            "single": _calibration_metrics(
                scenario,
                acq,
                truth,
                single,
                targets[:1],
                targets[1:],
                radius,
                scale,
                loc_cfg,
                *extra,
            ),
        },
        "timing_s": {
            "simulate": t_sim,
            "localize": t_loc,
            "calibrate": t_cal,
            "total": time.perf_counter() - t_start,
        },
    }
    if first_pass is not None:
        metrics["first_pass"] = first_pass
        metrics["acquisition"]["robot_time_s"] += first_pass["robot_time_s"]
        metrics["timing_s"]["simulate"] += first_pass.pop("simulate_s")
    if three is not None:
        metrics["calibration"]["three"] = _calibration_metrics(
            scenario,
            acq,
            truth,
            three,
            targets[:3],
            targets[3:],
            radius,
            scale,
            loc_cfg,
            *extra,
        )
    if recording is not None:
        t0 = time.perf_counter()
        frames = _record_run(recording, scenario, twin, acq, single, three)
        metrics["recording"] = {"frames": frames, "seconds": time.perf_counter() - t0}
    snapshot = snapshot_of(scenario, acq, single, truth)
    if save_dataset is not None:
        t0 = time.perf_counter()
        save_dataset_files(save_dataset, scenario, twin, acq)
        metrics["timing_s"]["save_dataset"] = time.perf_counter() - t0
    metrics["timing_s"]["total"] = time.perf_counter() - t_start
    return RunResult(
        metrics,
        acq,
        single,
        three,
        snapshot=snapshot,
        uncertainty_inputs=inputs,
        cad_centres=cad,
    )
