"""The paper's experiment on the twin: three datasets, touch-based DH refinement, the
leave-one-dataset-out kinematics, single- and three-marker folds, Tables I and II — and,
beyond the paper, every result scored against the twin's ground truth.

Stages (the split the timing figures use):

1. **touches** — each dataset's 24 stylus touches (own twin session, new phantom
   placement), the three leave-one-out DH fits (Step 1) and each dataset's reference
   (Step 2). Cheap; in the main process.
2. **datasets** — one task per dataset, in a process pool: simulate the 4 × 45 sweeps,
   recompute every frame's flange pose with the dataset's frozen DH model, localize every
   sweep once (shared by all folds), run the eight folds, score against the truth.
   Frames stay inside the task; it returns metrics and small arrays only.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.dh import DHTable
from calib.evaluate import (
    TABLE_III_METHODS,
    FoldResult,
    Summary,
    evaluate_fold,
    folds,
    format_table_iii_csv,
    format_table_iii_markdown,
    format_tables_csv,
    format_tables_markdown,
    summarize,
    training_precision,
)
from calib.kinematics import (
    DHRefinement,
    TouchReference,
    fit_reference,
    identifiability,
    kinematic_gauge,
    refine_dh,
    with_kinematics,
)
from calib.localize import localize_sphere
from calib.records import Touch
from calib.uncertainty import alternation_bound
from twin.imager import acoustic_scene
from twin.printing import forget_parts, use_disk_cache
from twin.world import GroundTruth

from . import progress as progress_report
from .experiment import (
    SimulatedAcquisition,
    axial_scale,
    coarse_estimate,
    drop_frame_pages,
    image_points,
    make_imager,
    make_twin,
    one_blas_thread,
    release_memory,
    simulate_acquisition,
    simulate_touches,
    true_centre_in_sweep,
    with_frames,
    without_frames,
)
from .figures import LocalizationSnapshot
from .offline import layout_entry, scenario_uncertainty, uncertainty_entry
from .reconstruction import (
    PhantomReconstruction,
    PhantomScan,
    Recalibration,
    RemountScan,
    recalibration_scenario,
    reconstruct_phantom,
    reconstruction_metrics,
    run_recalibration,
    run_remount_scan,
    run_scan,
)
from .recording_options import RecordingOptions
from .scenario import Scenario, layout_sigma_mm
from .sessions import dataset_rngs, dataset_scenario, scan_scenario, stage_rngs
from .truth import mount_error, snapshot_of, transform_difference

__all__ = ["DatasetOutcome", "EvaluationResult", "run_evaluation"]

Array = NDArray[np.float64]
_MM = 1e3
log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- stage 2


@dataclass(frozen=True, eq=False)
class _DatasetTask:
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
class _DatasetScan:
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


def _simulate_dataset(
    scenario: Scenario,
    index: int,
    name: str,
    touches: tuple[Touch, ...] = (),
    scratch: Path | None = None,
    save_dir: Path | None = None,
    scene: bool = False,
    detach: bool = False,
) -> _DatasetScan:
    """Simulate one dataset's sweeps (the first half of a dataset's work: it needs no DH
    model, so a pool runs it while the touches are refined). ``scratch``: the frames go
    to files there (:func:`~bench.experiment.frames_to_file`); ``detach``: the returned
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
        from .offline import save_dataset

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
    return _DatasetScan(acq, truth, cad, scene_view, t_sim, frames_dir)


def _run_dataset(task: _DatasetTask, scan: _DatasetScan | None = None) -> DatasetOutcome:
    """Run one dataset's folds, after simulating its sweeps unless ``scan`` holds them
    (a process-pool task)."""
    if scan is None:
        scan = _simulate_dataset(
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
    radius = scenario.phantom.sphere_radius_mm * 1e-3
    scale = axial_scale(scenario)
    loc_cfg = scenario.localization
    targets = acq.dataset.targets()
    # Every frame's flange pose from its joint angles through the frozen DH model.
    sweeps = {t: with_kinematics(acq.dataset.of(t), task.table) for t in targets}
    t0 = time.perf_counter()
    initial = {t: localize_sphere(sweeps[t], None, radius, loc_cfg, scale) for t in targets}
    t_loc0 = time.perf_counter() - t0
    references = task.reference.reference_points({t: cad[t] for t in targets})
    t0 = time.perf_counter()
    fold_list = folds(task.name, targets)
    results = []
    everything = [s for ss in sweeps.values() for s in ss]
    for k, fold in enumerate(fold_list):
        progress_report.report(f"{task.name}: folds", k, len(fold_list))
        # A fold maps only its own spheres' frames back in (≈ 145 MB a sphere).
        drop_frame_pages(everything)
        results.append(
            evaluate_fold(
                fold,
                sweeps,
                initial,
                references,
                radius,
                loc_cfg,
                scale,
                cad,
                acq.T_ee_us_coarse,
                scenario.calibration.max_alternations,
                layout_sigma_mm(scenario),
            )
        )
    progress_report.report(f"{task.name}: folds", len(fold_list), len(fold_list))
    t_folds = time.perf_counter() - t0
    # Each fold's 95 % error bounds (no truth): its own data, the print specification,
    # the medium and the frozen DH model's residual.
    t0 = time.perf_counter()
    inputs = scenario_uncertainty(scenario, task.kinematic_rms_mm)
    grid = image_points(scenario)
    uncertainty = {}
    for r in results:
        multi = {t: cad[t] for t in r.fold.train} if len(r.fold.train) >= 2 else None
        uncertainty[r.fold.name] = uncertainty_entry(
            alternation_bound(r.alternation, grid, multi, inputs), inputs
        )
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
    errors, n_sweeps, n_rejected = [], 0, 0
    for t, locs in first.alternation.localizations.items():
        for sweep, loc in zip(acq.dataset.of(t), locs, strict=True):
            n_sweeps += 1
            if not loc.accepted:
                n_rejected += 1
                continue
            p_true = true_centre_in_sweep(acq, truth, t, sweep)
            errors.append(np.linalg.norm(loc.centre - p_true) * _MM)
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
        part = _record_dataset(task, scenario, acq, truth, scene_view, results)
        t_rec = time.perf_counter() - t1
    return DatasetOutcome(
        task.name,
        results,
        truth_doc,
        np.array(errors),
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


def _record_dataset(task, scenario, acq, truth, scene_view, results) -> Path:
    """A dataset's part of the run's recording: its acquisition with the first single-
    and three-marker folds' localizations, and every fold's convergence."""
    from .recording import Recorder, log_acquisition

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
            scenario.phantom.sphere_radius_mm * 1e-3,
            scenario.localization,
            axial_scale(scenario),
            truth=(acq.T_base_ee_true, truth.T_ee_us, truth.landmarks_base),
        )
        for r in results:
            rec.alternation(
                task.name, f"folds/{r.fold.kind}/{'+'.join(r.fold.train)}", r.alternation
            )
    return options.path


# ----------------------------------------------------------------------------- the run


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


def _pool_task(fn: Callable[..., Any], *args: Any) -> Any:
    """Run a pool task, then release the memory it freed (its printed parts included:
    a worker's next task reads them back from the run's disk cache)."""
    try:
        return fn(*args)
    finally:
        forget_parts()
        release_memory()


def _started() -> None:
    """A no-op task: submitting it starts a worker process."""


def _worker_initializer(counts: Any, parts: Path) -> None:
    """A pool worker: report progress to the run, share the run's printed parts, one
    BLAS thread (:func:`~bench.experiment.one_blas_thread`)."""
    progress_report.worker_initializer(counts)
    use_disk_cache(parts)
    one_blas_thread()


def _workers(scenario: Scenario, n_tasks: int) -> int:
    """Worker processes: the scenario's number, or one per core (at most one per task).
    Since the reconstruction's tasks queue behind the datasets, a third worker on two
    cores no longer fills an idle core: it only adds a dataset's frames to the memory
    (paper.yaml, 2 cores: 89.6 s and 2.7 GB with two workers, 94.2 s and 3.9 GB with
    three)."""
    w = scenario.evaluation.workers or (os.cpu_count() or 1)
    return max(1, min(w, n_tasks))


def run_evaluation(
    scenario: Scenario,
    progress: Callable[[str], None] | None = None,
    recording: RecordingOptions | None = None,
    save_dataset: Path | None = None,
) -> EvaluationResult:
    """The paper's experiment: touches, leave-one-out DH, folds, Tables I and II; the
    reconstruction (Table III). ``recording``: a rerun recording of it
    (:mod:`bench.recording`). ``save_dataset``: a directory that receives each dataset's
    acquisition, touches included, as ``<dir>/<name>`` (:mod:`calib.dataset_files`)."""
    say = progress or (lambda _msg: None)
    # The run's scratch directory: the printed parts its processes share (built once,
    # read by every worker), and the re-calibration scan's frames. Removed at the end.
    # (The pool, entered into ``stack``, shuts down before the directory goes.)
    with tempfile.TemporaryDirectory(prefix="uscal-run-") as tmp, contextlib.ExitStack() as stack:
        use_disk_cache(Path(tmp) / "printed-parts")
        try:
            return _run_evaluation(scenario, say, recording, save_dataset, Path(tmp), stack)
        finally:
            use_disk_cache(None)


def _run_evaluation(
    scenario: Scenario,
    say: Callable[[str], None],
    recording: RecordingOptions | None,
    save_dataset: Path | None,
    scratch: Path,
    stack: contextlib.ExitStack,
) -> EvaluationResult:
    """:func:`run_evaluation` inside its scratch directory; its process pool (if any)
    lives in ``stack``."""
    t_start = time.perf_counter()
    ev = scenario.evaluation
    names = list(ev.datasets)
    scenarios = [dataset_scenario(scenario, i) for i in range(len(names))]
    # Where each dataset's sweeps find the phantom (moved since its touches, if at all).
    scans = [scan_scenario(scenario, i) for i in range(len(names))]
    workers = _workers(scenario, len(names))
    pool: cf.ProcessPoolExecutor | None = None
    counts: Any = None
    if workers > 1:
        ctx = multiprocessing.get_context("spawn")
        counts = ctx.Queue()  # the workers' progress reports
        pool = stack.enter_context(
            cf.ProcessPoolExecutor(
                max_workers=workers,
                mp_context=ctx,
                initializer=_worker_initializer,
                initargs=(counts, scratch / "printed-parts"),
            )
        )

    def result(future: cf.Future):
        while not future.done():
            cf.wait([future], timeout=0.2)
            progress_report.drain(counts)
        return future.result()

    def submit(fn: Callable[..., Any], *args: Any) -> cf.Future:
        assert pool is not None
        return pool.submit(_pool_task, fn, *args)

    # The sweeps need no DH model: with a pool the datasets' simulations start now and
    # run while the touches are simulated and refined below (their frames stay in the
    # scratch directory). A recording or saved datasets need the twin after the
    # simulation: then each dataset is one task, as without a pool.
    split = pool is not None and recording is None and save_dataset is None
    if pool is not None:
        stack.enter_context(one_blas_thread())
        # Start the workers (their imports take seconds) while this process prints the
        # phantom into the run's disk cache: the datasets' twins then read it instead
        # of each building the same parts at once (≈ 1.5 s of CPU per twin).
        for _ in range(workers):
            submit(_started)
        make_twin(scenario)
    sim_futures = (
        [
            submit(_simulate_dataset, sc, i, name, (), scratch, None, False, True)
            for i, (name, sc) in enumerate(zip(names, scans, strict=True))
        ]
        if split
        else []
    )

    # ---- stage 1: touches, DH refinement, references
    touches: dict[str, list[Touch]] = {}
    for i, (name, sc) in enumerate(zip(names, scenarios, strict=True)):
        progress_report.report("touches (datasets)", i, len(names))
        rngs = dataset_rngs(scenario, i)
        twin = make_twin(sc, rngs["touch_joints"])
        touches[name] = simulate_touches(sc, twin, rngs["touch_contact"])
        del twin
    progress_report.report("touches (datasets)", len(names), len(names))
    twin = make_twin(scenario)
    cad_vertices = {k: v for k, v in twin.phantom_cad.landmarks.items() if k.startswith("vertex_")}
    truth = twin.truth
    # The scene (printed meshes, ≈ 100 MB) is done with: this process only waits on the
    # pool from here.
    del twin
    forget_parts()
    release_memory()
    tip_cad = np.array(ev.stylus_tip_cad_mm) * 1e-3
    nominal = scenario.robot.nominal_table
    refinements: dict[str, DHRefinement] = {}
    references: dict[str, TouchReference] = {}
    for k, name in enumerate(names):
        progress_report.report("DH refinement", k, len(names))
        train = [touches[n] for n in names if n != name]
        say(f"DH refinement for {name} from {', '.join(n for n in names if n != name)}")
        refinements[name] = refine_dh(
            nominal,
            train,
            cad_vertices,
            tip_cad,
            ev.dh_regularizer,
            ev.initialisations,
            ev.dh_bound,
        )
        references[name] = fit_reference(
            refinements[name].table, touches[name], cad_vertices, tip_cad
        )
    progress_report.report("DH refinement", len(names), len(names))
    t_touch = time.perf_counter() - t_start

    # ---- stage 2: datasets (and the reconstruction's tasks) in a process pool
    tasks = [
        _DatasetTask(
            sc,
            i,
            name,
            refinements[name].table,
            references[name],
            tuple(touches[name]),
            recording,
            Path(save_dataset) / name if save_dataset is not None else None,
            float(np.sqrt(np.mean(refinements[name].residuals_mm ** 2))),
            scratch,
        )
        for i, (name, sc) in enumerate(zip(names, scans, strict=True))
    ]
    tables = {name: refinements[name].table for name in names}
    phantoms = scenario.reconstruction.phantoms
    say(f"{len(tasks)} datasets on {workers} worker process(es)")
    if phantoms:
        say(f"reconstruction of the {' and '.join(phantoms)} after them")
    t0 = time.perf_counter()
    recon_parts: list[PhantomReconstruction] = []
    scans: list[PhantomScan] = []
    recal: Recalibration | None = None
    spheres = recalibration_scenario(scenario).protocol.spheres if phantoms else ()
    # The re-calibration scan's frames go to the scratch directory, mapped by each
    # calibration task.
    if workers == 1:
        outcomes = [_run_dataset(t) for t in tasks]
        if phantoms:
            remount = [run_remount_scan(scenario, k, scratch) for k in spheres]
            recal = Recalibration.merge(
                [run_recalibration(scenario, m, tables, remount) for m in TABLE_III_METHODS],
                remount,
            )
            for kind in phantoms:
                scan = run_scan(scenario, kind, recording)
                scans.append(scan)
                recon_parts.append(reconstruct_phantom(scenario, scan, recal, tables))
    else:
        # The datasets first: each is a long serial task, and one started late
        # would run alone at the end. The reconstruction's small tasks follow,
        # each queued as soon as what it needs is done: the sphere scans, a
        # method's calibrations once its spheres are scanned (single-marker
        # ahead of the phantom scans), the registrations.
        if split:
            # Each dataset's folds as soon as its sweeps are simulated.
            dataset_futures = [
                submit(_run_dataset, t, result(f)) for t, f in zip(tasks, sim_futures, strict=True)
            ]
        else:
            dataset_futures = [submit(_run_dataset, t) for t in tasks]
        if phantoms:
            remount_futures = [submit(run_remount_scan, scenario, k, scratch) for k in spheres]
            remount: list[RemountScan] = []
            recal_futures: dict[str, cf.Future] = {}
            scan_futures: list[cf.Future] = []
            for f in remount_futures:
                remount.append(result(f))
                scanned = {s.target for s in remount}
                for method, used in TABLE_III_METHODS.items():
                    if method not in recal_futures and set(used) <= scanned:
                        # The last calibrations run mostly alone: two threads.
                        threads = 2 if len(recal_futures) == len(TABLE_III_METHODS) - 1 else 1
                        recal_futures[method] = submit(
                            run_recalibration, scenario, method, tables,
                            list(remount), threads,
                        )  # fmt: skip
                if not scan_futures:
                    scan_futures = [
                        submit(run_scan, scenario, kind, recording) for kind in phantoms
                    ]
            recal = Recalibration.merge([result(f) for f in recal_futures.values()], remount)
            recon_futures = [
                submit(reconstruct_phantom, scenario, result(f), recal, tables)
                for f in scan_futures
            ]
            recon_parts = [result(f) for f in recon_futures]
            scans = [f.result() for f in scan_futures]
        outcomes = [result(f) for f in dataset_futures]
        progress_report.drain(counts)
    t_datasets = time.perf_counter() - t0
    log.debug("touches and DH refinement: %.1f s; pool: %.1f s", t_touch, t_datasets)
    for o in outcomes:
        log.debug("dataset %s: %s", o.name, {k: round(v, 2) for k, v in o.timing_s.items()})
    if recal is not None:
        log.debug("re-calibration: %s", {k: round(v, 2) for k, v in recal.timing_s.items()})
    t_record = 0.0
    if recording is not None:
        t1 = time.perf_counter()
        _record_evaluation(scenario, recording, touches, tip_cad, outcomes, scans, recon_parts)
        t_record = time.perf_counter() - t1

    metrics = _metrics(
        scenario, names, touches, refinements, references, outcomes, truth, cad_vertices
    )
    metrics["timing_s"] = {
        "touches_and_dh": t_touch,
        "pool_wall": t_datasets,
        "workers": workers,
        "per_dataset": {o.name: o.timing_s for o in outcomes},
        "simulate": float(sum(o.timing_s["simulate"] for o in outcomes)),
        "localize": float(
            sum(o.timing_s["localize_initial"] + o.timing_s["localize_folds"] for o in outcomes)
        ),
        "calibrate": float(
            sum(h["calibrate_s"] for o in outcomes for r in o.folds for h in r.alternation.history)
        ),
        "reconstruction": {
            "recalibration": recal.timing_s if recal is not None else {},
            **{p.kind: p.metrics["timing_s"] for p in recon_parts},
        },
        "recording": t_record
        + sum(o.timing_s["recording"] for o in outcomes)
        + sum(sc.timing_s["recording"] for sc in scans),
        "total": time.perf_counter() - t_start,
    }
    tables_i_ii = _tables(names, references, outcomes)
    metrics["evaluation"]["single"] = _tables_json(tables_i_ii["single"])
    metrics["evaluation"]["three"] = _tables_json(tables_i_ii["three"])
    markdown, csv_text = format_tables_markdown(tables_i_ii), format_tables_csv(tables_i_ii)
    if recal is not None:
        metrics["reconstruction"] = reconstruction_metrics(recon_parts, recal)
        table_iii = {p.kind: p.metrics for p in recon_parts}
        markdown += "\n" + format_table_iii_markdown(table_iii, names)
        csv_text += format_table_iii_csv(table_iii, names)
    return EvaluationResult(
        metrics, markdown, csv_text, refinements, references, outcomes, recon_parts
    )


def _record_evaluation(
    scenario: Scenario,
    options: RecordingOptions,
    touches: dict[str, list[Touch]],
    tip_cad: Array,
    outcomes: list[DatasetOutcome],
    scans: list[PhantomScan],
    recon_parts: list[PhantomReconstruction],
) -> None:
    """The main process's part of the recording (touches, the registered reconstructions)
    and the merge of the workers' parts into the run's file."""
    from twin.phantoms import build_phantom

    from .reconstruction import scan_scenario
    from .recording import Recorder, merge_parts

    rec = Recorder(options)
    for name, ts in touches.items():
        tips = np.array([se3.apply(t.T_base_ee, tip_cad) for t in ts])
        rec.points(f"/{name}/world/touches", tips, colour=(255, 200, 0), radius=0.001)
    for part in recon_parts:
        mesh = build_phantom(scan_scenario(scenario, part.kind).phantom).mesh()
        rec.reconstruction(part.kind, mesh, part.points)
    parts = [o.recording_part for o in outcomes] + [s.recording_part for s in scans]
    merge_parts(
        options,
        [p for p in parts if p is not None],
        [o.name for o in outcomes],
        [s.kind for s in scans],
        bool(recon_parts),
        main=rec,
    )


def _tables(
    names: list[str], references: dict[str, TouchReference], outcomes: list[DatasetOutcome]
) -> dict[str, dict[str, dict[str, Summary]]]:
    by_name = {o.name: o for o in outcomes}
    tool = {n: list(references[n].tool_precision_mm.values()) for n in names}
    out: dict[str, dict[str, dict[str, Summary]]] = {}
    for kind in ("single", "three"):
        prec = {n: [r.precision for r in by_name[n].folds if r.fold.kind == kind] for n in names}
        acc = {n: [r.accuracy for r in by_name[n].folds if r.fold.kind == kind] for n in names}
        table = {"sphere_precision_mm": summarize(prec), "sphere_accuracy_mm": summarize(acc)}
        if kind == "single":
            table = {"tool_precision_mm": summarize(tool), **table}
        out[kind] = table
    return out


def _tables_json(table: dict[str, dict[str, Summary]]) -> dict[str, Any]:
    return {metric: {s: v.as_dict() for s, v in by_set.items()} for metric, by_set in table.items()}


def _metrics(
    scenario, names, touches, refinements, references, outcomes, truth, cad_vertices
) -> dict[str, Any]:
    first = outcomes[0]
    single = next(r for r in first.folds if r.fold.kind == "single")
    three = next((r for r in first.folds if r.fold.kind == "three"), None)
    errors = first.localization_errors_mm
    if len(errors) == 0:
        errors = np.array([np.nan])
    fold_truth = {f["fold"]: f for o in outcomes for f in o.truth["folds"]}
    fold_bounds = {k: v for o in outcomes for k, v in o.uncertainty.items()}

    def calibration_entry(r: FoldResult) -> dict[str, Any]:
        t = fold_truth[r.fold.name]
        alt = r.alternation
        return {
            "fold": r.fold.name,
            "true_error": {
                "rotation_deg": t["rotation_deg"],
                "translation_mm": t["translation_mm"],
                "image_mm": t["image_mm"],
            },
            **(
                {"bound95": fold_bounds[r.fold.name]["bound95"]}
                if r.fold.name in fold_bounds
                else {}
            ),
            "precision_mm": float(np.mean(list(training_precision(alt).values()))),
            "accuracy_mm": r.accuracy,
            "accuracy_true_mm": t["accuracy_true_mm"],
            "n_retained": int(alt.result.retained.sum()),
            "iterations": len(alt.history),
            "rejected": dict(alt.result.rejection_reasons),
            "T_ee_us": np.round(r.T_ee_us, 9).tolist(),
            "covariance_rotvec_rad_translation_m": alt.result.covariance.tolist(),
            "history": alt.history,
            "trained_on": list(r.fold.train),
            "tested_on": list(r.fold.test),
            **layout_entry(alt),
            **(
                {"uncertainty": fold_bounds[r.fold.name]["uncertainty"]}
                if r.fold.name in fold_bounds
                else {}
            ),
        }

    folds_doc = []
    for o in outcomes:
        for r in o.folds:
            t = fold_truth[r.fold.name]
            folds_doc.append(
                {
                    "fold": r.fold.name,
                    "dataset": r.fold.dataset,
                    "kind": r.fold.kind,
                    "train": list(r.fold.train),
                    "test": list(r.fold.test),
                    "sphere_precision_mm": r.precision,
                    "sphere_accuracy_mm": r.accuracy,
                    "per_sphere": {
                        s: {"precision_mm": r.precision_mm[s], "accuracy_mm": r.accuracy_mm[s]}
                        for s in r.fold.test
                    },
                    "n_retained": int(r.alternation.result.retained.sum()),
                    "iterations": len(r.alternation.history),
                    "true": {k: v for k, v in t.items() if k != "fold"},
                    **(
                        {"bound95": fold_bounds[r.fold.name]["bound95"]}
                        if r.fold.name in fold_bounds
                        else {}
                    ),
                }
            )
    kin = {}
    for n in names:
        ref = refinements[n]
        kin[n] = {
            "trained_on": [m for m in names if m != n],
            "rms_change": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), ref.rms_change, strict=True)
            ),
            "z": ref.z.round(6).tolist(),
            "training_loss_mm2": ref.loss,
            "start_losses_mm2": ref.start_losses.round(6).tolist(),
            "touch_residual_rms_mm": float(np.sqrt(np.mean(ref.residuals_mm**2))),
            "reference_residual_rms_mm": float(np.sqrt(np.mean(references[n].residuals_mm ** 2))),
            "tip_mm": (references[n].tip * _MM).round(4).tolist(),
        }
        o = next(o for o in outcomes if o.name == n)
        kin[n]["true_error"] = o.truth["kinematic_error_mm"]
        kin[n]["reference_error_mm"] = o.truth["reference_error_mm"]
    # The paper's figure: RMS over the three leave-one-out models and the six joints.
    rms = np.sqrt(np.mean(np.array([r.rms_change for r in refinements.values()]) ** 2, axis=0))
    true_rms = np.array(truth.dh_deltas.rms()) * [180 / np.pi, _MM, _MM, 180 / np.pi]
    ident = identifiability(
        refinements[names[0]], [touches[n] for n in names if n != names[0]], cad_vertices
    )
    return {
        "scenario": {"name": scenario.source, "seed": scenario.seed},
        "localization": {
            "method": scenario.localization.method,
            "n_sweeps": first.n_sweeps,
            "n_rejected": first.n_rejected,
            "error_mm": {
                "median": float(np.median(errors)),
                "p95": float(np.percentile(errors, 95)),
                "max": float(np.max(errors)),
            },
        },
        "calibration": {
            "coarse_error": _coarse_error(scenario, truth),
            "single": calibration_entry(single),
            **({"three": calibration_entry(three)} if three is not None else {}),
        },
        "kinematics": {
            "datasets": kin,
            "rms_change_mean": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), rms.tolist(), strict=True)
            ),
            "true_dh_error_rms": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), true_rms.tolist(), strict=True)
            ),
            "unobservable_share": {k: round(v, 4) for k, v in ident.unobservable.items()},
            "weak_directions": [
                {"singular_value": w.singular_value, "dh": w.dh} for w in ident.weak
            ],
        },
        "evaluation": {"datasets": names, "folds": folds_doc},
    }


def _coarse_error(scenario: Scenario, truth) -> dict[str, float]:
    coarse = coarse_estimate(
        truth.T_ee_us, scenario.calibration, stage_rngs(scenario)["calibration"]
    )
    return transform_difference(coarse, truth.T_ee_us)
