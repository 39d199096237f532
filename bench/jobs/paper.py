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
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.evaluation.cross_validation import (
    TABLE_III_METHODS,
    format_table_iii_csv,
    format_table_iii_markdown,
    format_tables_csv,
    format_tables_markdown,
)
from calib.kinematics import DHRefinement, TouchReference
from calib.pipeline import residual_rms_mm, touch_kinematics
from calib.records import Touch
from twin.phantoms import build_phantom
from twin.printing import forget_parts, use_disk_cache

from .. import progress as progress_report
from ..acquire_sim import make_twin, simulate_touches
from ..config.scenario import Scenario
from ..parallel import (
    one_blas_thread,
    pool_task,
    release_memory,
    start_worker,
    worker_initializer,
    workers_for,
)
from ..recording.logs import merge_parts
from ..recording.options import RecordingOptions
from ..recording.recorder import Recorder
from ..results import (
    DatasetOutcome,
    EvaluationResult,
    PhantomReconstruction,
    PhantomScan,
    Recalibration,
    RemountScan,
)
from ..sessions import dataset_rngs, dataset_scenario, scan_scenario
from .paper_dataset import DatasetTask, run_dataset, simulate_dataset
from .paper_metrics import evaluation_metrics, summary_tables, tables_json
from .recalibration import recalibration_scenario, run_recalibration, run_remount_scan
from .table3 import phantom_scan_scenario, reconstruct_phantom, reconstruction_metrics, run_scan

__all__ = ["run_evaluation"]

Array = NDArray[np.float64]
_MM = 1e3
log = logging.getLogger(__name__)


def run_evaluation(
    scenario: Scenario,
    progress: Callable[[str], None] | None = None,
    recording: RecordingOptions | None = None,
    save_dataset: Path | None = None,
) -> EvaluationResult:
    """The paper's experiment: touches, leave-one-out DH, folds, Tables I and II; the
    reconstruction (Table III). ``recording``: a rerun recording of it
    (:mod:`bench.recording`). ``save_dataset``: a directory that receives each dataset's
    acquisition, touches included, as ``<dir>/<name>`` (:mod:`calib.files.dataset`)."""
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
    workers = workers_for(scenario, len(names))
    pool: cf.ProcessPoolExecutor | None = None
    counts: Any = None
    if workers > 1:
        ctx = multiprocessing.get_context("spawn")
        counts = ctx.Queue()  # the workers' progress reports
        pool = stack.enter_context(
            cf.ProcessPoolExecutor(
                max_workers=workers,
                mp_context=ctx,
                initializer=worker_initializer,
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
        return pool.submit(pool_task, fn, *args)

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
            submit(start_worker)
        make_twin(scenario)
    sim_futures = (
        [
            submit(simulate_dataset, sc, i, name, (), scratch, None, False, True)
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
        refinements[name], references[name] = touch_kinematics(
            nominal,
            train,
            touches[name],
            vertices=cad_vertices,
            tip_cad=tip_cad,
            evaluation=ev,
        )
    progress_report.report("DH refinement", len(names), len(names))
    t_touch = time.perf_counter() - t_start

    # ---- stage 2: datasets (and the reconstruction's tasks) in a process pool
    tasks = [
        DatasetTask(
            sc,
            i,
            name,
            refinements[name].table,
            references[name],
            tuple(touches[name]),
            recording,
            Path(save_dataset) / name if save_dataset is not None else None,
            residual_rms_mm(refinements[name].residuals_mm),
            scratch,
            refinements[name].covariance,
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
        outcomes = [run_dataset(t) for t in tasks]
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
                submit(run_dataset, t, result(f)) for t, f in zip(tasks, sim_futures, strict=True)
            ]
        else:
            dataset_futures = [submit(run_dataset, t) for t in tasks]
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

    metrics = evaluation_metrics(
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
    tables_i_ii = summary_tables(names, references, outcomes)
    metrics["evaluation"]["single"] = tables_json(tables_i_ii["single"])
    metrics["evaluation"]["three"] = tables_json(tables_i_ii["three"])
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
    rec = Recorder(options)
    for name, ts in touches.items():
        tips = np.array([se3.apply(t.T_base_ee, tip_cad) for t in ts])
        rec.points(f"/{name}/world/touches", tips, colour=(255, 200, 0), radius=0.001)
    for part in recon_parts:
        mesh = build_phantom(phantom_scan_scenario(scenario, part.kind).phantom).mesh()
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
