"""One dataset of the paper's experiment (stage 2 of :mod:`bench.jobs.paper`), as a
process-pool task: simulate its 4 × 45 sweeps (:func:`simulate_dataset`, which needs no
DH model, so it starts while the touches are refined), recompute every frame's flange
pose with the dataset's frozen DH model, run its folds (:func:`calib.pipeline.run_folds`),
bound each fold's error, and score it against the twin's truth (:func:`run_dataset`).
Frames stay inside the task; it returns metrics and small arrays only."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.calibration.uncertainty import alternation_bound
from calib.calibration.verdict import image_scale, sweep_geometry
from calib.dh import DHTable
from calib.kinematics import (
    TouchReference,
    kinematic_gauge,
    kinematic_modes,
    with_kinematics,
)
from calib.pipeline import run_folds
from calib.records import Touch
from twin.imager import acoustic_scene
from twin.world import GroundTruth

from ..acquire_sim import (
    SimulatedAcquisition,
    make_imager,
    make_twin,
    save_dataset,
    simulate_acquisition,
)
from ..config.method import (
    axial_scale,
    image_points,
    method_inputs,
    scenario_uncertainty,
    stated_radius,
)
from ..config.scenario import Scenario
from ..files import drop_frame_pages, with_frames, without_frames
from ..parallel import release_memory
from ..recording.logs import log_acquisition
from ..recording.options import RecordingOptions
from ..recording.recorder import Recorder
from ..results import DatasetOutcome, uncertainty_entry
from ..sessions import dataset_rngs
from ..truth import localization_errors, mount_error, snapshot_of

__all__ = ["DatasetScan", "DatasetTask", "record_dataset", "run_dataset", "simulate_dataset"]
Array = NDArray[np.float64]
_MM = 1e3


@dataclass(frozen=True, eq=False)
class DatasetTask:
    scenario: Scenario
    index: int
    name: str
    table: DHTable
    reference: TouchReference
    touches: tuple[Touch, ...]
    recording: RecordingOptions | None = None
    save_dir: Path | None = None  # write the acquisition (with its touches) here
    kinematic_rms_mm: float = 0.0  # the DH refinement's residual (RMS touch distance)
    scratch: Path | None = None  # the run's scratch directory: the frames go there
    kinematic_covariance: Array | None = None  # the DH refinement's (DHRefinement.covariance)


@dataclass(frozen=True, eq=False)
class DatasetScan:
    """A dataset's simulated acquisition, its truth and what the folds need of its twin.
    From a pool task (``frames_dir`` set) the sweeps carry no frames: those stay in the
    run's scratch files, and :meth:`acquisition_with_frames` maps them back."""

    acquisition: SimulatedAcquisition
    truth: GroundTruth
    cad: dict[str, Array]  # the CAD's sphere centres
    scene_view: tuple[Any, Any] | None  # what a recording shows of the scene
    seconds: float
    frames_dir: Path | None = None

    def acquisition_with_frames(self) -> SimulatedAcquisition:
        acq = self.acquisition
        if self.frames_dir is None:
            return acq
        # One file per sphere, scanned one after the other (simulate_acquisition).
        name = acq.dataset.name
        sweeps = [
            s
            for t in acq.dataset.targets()
            for s in with_frames(acq.dataset.of(t), self.frames_dir / f"{name}_{t}.npy")
        ]
        return replace(acq, dataset=replace(acq.dataset, sweeps=tuple(sweeps)))


def simulate_dataset(
    scenario: Scenario,
    index: int,
    name: str,
    touches: tuple[Touch, ...] = (),
    scratch: Path | None = None,
    save_dir: Path | None = None,
    scene: bool = False,
    detach: bool = False,
) -> DatasetScan:
    """Simulate one dataset's sweeps (the first half of a dataset's work: it needs no DH
    model, so a pool runs it while the touches are refined). ``scratch``: the frames go
    to files there (:func:`~bench.files.frames_to_file`); ``detach``: the returned
    sweeps leave them there (a pool task's result crosses a pipe)."""
    t0 = time.perf_counter()
    rngs = dataset_rngs(scenario, index)
    twin = make_twin(scenario, rngs["joints"])
    imager = make_imager(scenario, twin, rngs["imaging"])
    acq = simulate_acquisition(
        scenario,
        twin,
        imager,
        name,
        rngs["protocol"],
        touches=touches,
        progress=f"{name}: acquire sweeps",
        frames_dir=scratch,
    )
    t_sim = time.perf_counter() - t0
    if save_dir is not None:
        save_dataset(save_dir, scenario, twin, acq)
    truth = twin.truth
    cad = {k: v for k, v in twin.phantom_cad.landmarks.items() if k.startswith("sphere_")}
    # What a recording shows of the scene (small: meshes and the MuJoCo model).
    scene_view = (acoustic_scene(twin.robot.scene.scene).parts, twin.scene.model) if scene else None
    # The scanner and scene are done: free them before the folds (memory per worker).
    del imager, twin
    release_memory()
    frames_dir = None
    if detach and scratch is not None:
        bare = without_frames(acq.dataset.sweeps)
        acq = replace(acq, dataset=replace(acq.dataset, sweeps=bare))
        frames_dir = scratch
    return DatasetScan(acq, truth, cad, scene_view, t_sim, frames_dir)


def run_dataset(task: DatasetTask, scan: DatasetScan | None = None) -> DatasetOutcome:
    """Run one dataset's folds, after simulating its sweeps unless ``scan`` holds them
    (a process-pool task)."""
    if scan is None:
        scan = simulate_dataset(
            task.scenario,
            task.index,
            task.name,
            task.touches,
            task.scratch,
            task.save_dir,
            scene=task.recording is not None,
        )
        acq = scan.acquisition
    else:
        acq = scan.acquisition_with_frames()
        acq = replace(acq, dataset=replace(acq.dataset, touches=tuple(task.touches)))
    scenario = task.scenario
    truth, cad, scene_view, t_sim = scan.truth, scan.cad, scan.scene_view, scan.seconds
    targets = acq.dataset.targets()
    # Every frame's flange pose from its joint angles through the frozen DH model.
    sweeps = {t: with_kinematics(acq.dataset.of(t), task.table) for t in targets}
    references = task.reference.reference_points({t: cad[t] for t in targets})
    everything = [s for ss in sweeps.values() for s in ss]
    method = method_inputs(scenario, cad_centres=cad, T_coarse=acq.T_ee_us_coarse)
    run = run_folds(
        task.name,
        sweeps,
        references,
        method,
        progress=f"{task.name}: folds",
        # A fold maps only its own spheres' frames back in (≈ 145 MB a sphere).
        before_fold=lambda: drop_frame_pages(everything),
    )
    results, t_loc0, t_folds = run.results, run.seconds_initial, run.seconds_folds
    # Each fold's 95 % error bounds (no truth): its own data, the print specification,
    # the medium and the frozen DH model's residual.
    t0 = time.perf_counter()
    modes = (
        None
        if task.kinematic_covariance is None
        else kinematic_modes(task.table, task.kinematic_covariance, everything)
    )
    inputs = scenario_uncertainty(scenario, task.kinematic_rms_mm, modes)
    grid = image_points(scenario)
    uncertainty = {}
    for r in results:
        multi = {t: cad[t] for t in r.fold.train} if len(r.fold.train) >= 2 else None
        uncertainty[r.fold.name] = uncertainty_entry(
            alternation_bound(r.alternation, grid, cad_centres=multi, inputs=inputs), inputs
        )
        # How its sweeps met the spheres, for its verdict (judged with its bound).
        geometry = sweep_geometry(r.alternation, everything, stated_radius(scenario))
        if geometry is not None:
            uncertainty[r.fold.name]["sweep_geometry"] = geometry.as_dict()
        # Its image scale, with the frozen model's modes carried (judged with its bound).
        scale = image_scale(r.alternation, modes)
        if scale is not None:
            uncertainty[r.fold.name]["image_scale"] = scale.as_dict()
    t_bounds = time.perf_counter() - t0

    # ---- against the truth (beyond the paper)
    t0 = time.perf_counter()
    q_frames = np.concatenate([s.q[::10] for ss in sweeps.values() for s in ss])
    tool_points = se3.apply(truth.T_ee_us, image_points(scenario, 3))
    gauge = kinematic_gauge(task.table, truth.dh_table, q_frames, tool_points)
    gauge_nominal = kinematic_gauge(
        scenario.robot.nominal_table, truth.dh_table, q_frames, tool_points
    )
    X_equiv = gauge.G @ truth.T_ee_us
    true_centres = {t: se3.apply(gauge.B, truth.landmarks_base[t]) for t in targets}
    fold_truth = []
    for r in results:
        X = r.T_ee_us
        fold_truth.append(
            {
                "fold": r.fold.name,
                **mount_error(scenario, X, X_equiv),
                "accuracy_true_mm": float(
                    np.mean(
                        [
                            np.linalg.norm(c.mean(axis=0) - true_centres[t]) * _MM
                            for t, c in r.centres.items()
                            if len(c)
                        ]
                    )
                ),
            }
        )
    # Localization error of the first single-marker fold's final localizations, against
    # the true centre in each sweep's (true) reference frame.
    first = results[0]
    errors, n_sweeps, n_rejected = localization_errors(
        acq, truth, first.alternation.retained_localizations()
    )
    truth_doc = {
        "kinematic_error_mm": {
            "refined_rms": gauge.rms_mm,
            "refined_max": gauge.max_mm,
            "nominal_rms": gauge_nominal.rms_mm,
            "nominal_max": gauge_nominal.max_mm,
        },
        "reference_error_mm": {
            t: float(np.linalg.norm(references[t] - true_centres[t])) * _MM for t in targets
        },
        "folds": fold_truth,
        "T_ee_us_equivalent": X_equiv.tolist(),
    }
    snapshot = None
    if task.index == 0:
        first_single = next(r for r in results if r.fold.kind == "single")
        snapshot = snapshot_of(scenario, acq, first_single.alternation, truth)
    part, t_rec = None, 0.0
    if task.recording is not None:
        t1 = time.perf_counter()
        part = record_dataset(task, scenario, acq, truth, scene_view, results)
        t_rec = time.perf_counter() - t1
    return DatasetOutcome(
        task.name,
        results,
        truth_doc,
        errors,
        n_sweeps,
        n_rejected,
        {
            "recording": t_rec,
            "simulate": t_sim,
            "localize_initial": t_loc0,
            "folds": t_folds,
            "bounds": t_bounds,
            "truth": time.perf_counter() - t0,
            "localize_folds": float(
                sum(h["localize_s"] for r in results for h in r.alternation.history)
            ),
        },
        part,
        snapshot,
        uncertainty,
    )


def record_dataset(task, scenario, acq, truth, scene_view, results) -> Path:
    """A dataset's part of the run's recording: its acquisition with the first single-
    and three-marker folds' localizations, and every fold's convergence."""
    options = task.recording.part(task.name)
    with Recorder(options) as rec:
        first = {}
        for r in results:
            first.setdefault(r.fold.kind, r.alternation)
        log_acquisition(
            rec,
            task.name,
            scene_view[0],
            scene_view[1],
            acq.dataset,
            first,
            stated_radius(scenario),
            scenario.localization,
            axial_scale(scenario),
            truth=(acq.T_base_ee_true, truth.T_ee_us, truth.landmarks_base),
        )
        for r in results:
            rec.alternation(
                task.name, f"folds/{r.fold.kind}/{'+'.join(r.fold.train)}", r.alternation
            )
    return options.path
