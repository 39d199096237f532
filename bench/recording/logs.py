"""What each job logs to rerun (an acquisition: the scene, the arm, every sweep's frames
with the sections found and, in the twin, the true ones; a calibration's convergence) and
the merge of the workers' parts into the run's one ``.rrd``."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import mujoco
import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.calibration.alternation import AlternationResult
from calib.localize import LocalizerConfig, SweepLocalization, frame_offsets, sphere_profile
from calib.records import Sweep

from .options import RecordingOptions, frames_per_target, sweeps_to_log
from .recorder import GREEN, RED, Recorder, rr

Array = NDArray[np.float64]
log = logging.getLogger(__name__)


def log_sweeps(
    rec: Recorder,
    session: str,
    sweeps: Sequence[Sweep],
    model: mujoco.MjModel,
    data: mujoco.MjData,
    robot_ids: list[int],
    T_ee_us_estimated: Array | None,
    localizations: Mapping[tuple[str, int], SweepLocalization] | None = None,
    radius: float = 0.0,
    axial_scale: float = 1.0,
    true_centres: Mapping[tuple[str, int], Array] | None = None,
    T_base_us_true: Mapping[tuple[str, int], Array] | None = None,
    max_frames: int | None = None,
) -> int:
    """Log a spread of whole sweeps frame by frame: robot, frame (2D, 3D quad at the true
    pose, estimated outline) and, when given, the detected (red) and true (green) sphere
    sections. ``localizations`` and ``true_centres`` are keyed by (target, pose id), the
    centres in the sweep's reference frame (localization) or per frame (truth, (n, 3)).
    At most ``max_frames`` frames (default: the recording's). Returns the number of frames
    logged."""
    if not sweeps:
        return 0
    limit = rec.options.max_frames if max_frames is None else max_frames
    chosen = sweeps_to_log(len(sweeps), sweeps[0].n_frames, limit)
    logged = 0
    for i in chosen:
        sweep = sweeps[i]
        key = (sweep.target, sweep.pose_id)
        W = sweep.images.shape[2]
        sx, sy = sweep.spacing
        true_spacing = (sx, sy * axial_scale)
        loc = localizations.get(key) if localizations else None
        offsets = frame_offsets(sweep, T_ee_us_estimated) if loc is not None else None
        for j in range(sweep.n_frames):
            rec.next_frame()
            rec.robot_pose(session, model, data, sweep.q[j], robot_ids)
            T_true = T_base_us_true[key][j] if T_base_us_true else None
            T_est = (
                sweep.T_base_ee[j] @ T_ee_us_estimated if T_ee_us_estimated is not None else None
            )
            rec.frame(
                session,
                sweep.images[j],
                sweep.spacing,
                T_true,
                T_est,
                textured=j == sweep.reference_index or j == 0,
            )
            detected = None
            if loc is not None and loc.accepted and offsets is not None:
                detected = (loc.centre - offsets[j], radius)
            true = None
            if true_centres is not None and key in true_centres:
                true = (true_centres[key][j], radius)
            if radius > 0:
                rec.sections(
                    session, W, true_spacing, detected, true, with_truth=true_centres is not None
                )
            logged += 1
    return logged


def log_acquisition(
    rec: Recorder,
    session: str,
    scene_parts: Sequence,
    model: mujoco.MjModel,
    dataset,
    alternations: Mapping[str, AlternationResult],
    radius: float,
    cfg: LocalizerConfig,
    axial_scale: float,
    truth: tuple[Mapping[tuple[str, int], Array], Array, Mapping[str, Array]] | None = None,
) -> int:
    """One acquisition session: the scene (``scene_parts``: parts with ``name``,
    ``material``, ``mesh`` in the base frame), the robot (``model``'s arm and tool), a
    spread of sweeps (at most ``max_frames`` frames over all spheres) with each sphere's
    section as found by the alternation that localized it last (``alternations`` by
    method, in order) and, in simulation, the true one; each alternation's convergence,
    residuals and radial profiles; the localized centres in the base frame. ``truth`` =
    (true flange poses per (target, pose id), true ``T_ee_us``, true landmarks): the
    twin's, kept apart; None for recorded data. Returns the frames logged."""
    rec.scene(session, scene_parts)
    data = mujoco.MjData(model)
    ids = rec.robot_shapes(session, model)
    owner: dict[str, str] = {}
    for method, alt in alternations.items():
        for target in alt.localizations:
            owner.setdefault(target, method)
    targets = [t for t in dataset.targets() if t in owner]
    per_sweep = max((s.n_frames for s in dataset.sweeps), default=0)
    budgets = frames_per_target(targets, per_sweep, rec.options.max_frames)
    logged = 0
    for target in targets:
        budget = budgets[target]
        alt = alternations[owner[target]]
        sweeps = dataset.of(target)
        T_true = centres = None
        if truth is not None:
            T_flange_true, T_ee_us_true, landmarks = truth
            T_true = {
                (target, s.pose_id): T_flange_true[(target, s.pose_id)] @ T_ee_us_true
                for s in sweeps
            }
            centres = {k: se3.apply(se3.invert(T), landmarks[target]) for k, T in T_true.items()}
        locs = alt.retained_localizations()[target]
        logged += log_sweeps(
            rec,
            session,
            sweeps,
            model,
            data,
            ids,
            alt.result.T_ee_us,
            {(target, s.pose_id): loc for s, loc in zip(sweeps, locs, strict=True)},
            radius,
            axial_scale,
            centres,
            T_true,
            budget,
        )
    for method, alt in alternations.items():
        T_est = alt.result.T_ee_us
        for target, locs in alt.localizations.items():
            prof = sphere_profile(
                dataset.of(target), locs, T_est, radius, cfg, axial_scale=axial_scale
            )
            rec.profile(session, f"{method}/{target}", prof)
        rec.alternation(session, method, alt)
        centres_base = [
            se3.apply(s.T_base_ee[s.reference_index] @ T_est, loc.centre)
            for t, locs in alt.retained_localizations().items()
            for s, loc in zip(dataset.of(t), locs, strict=True)
            if loc.accepted
        ]
        if centres_base:
            rec.points(f"/{session}/world/centres/{method}", np.array(centres_base))
    return logged


def blueprint(
    sessions: Sequence[str], scans: Sequence[str] = (), reconstruction: bool = False
) -> rr.blueprint.Blueprint:
    """One tab per sphere session (3D scene | current frame over convergence, radial
    profile and residuals), one per phantom scan (3D scene | frame with its boundary
    samples), and one for the reconstruction."""
    rrb = rr.blueprint
    tabs = []
    for s in sessions:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"/{s}/world", name=f"{s}: scene"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin=f"/{s}/bmode", name=f"{s}: B-mode"),
                    rrb.Tabs(
                        rrb.TimeSeriesView(origin=f"/{s}/calibration", name="convergence"),
                        rrb.Spatial2DView(origin=f"/{s}/localization", name="radial profile"),
                        rrb.BarChartView(origin=f"/{s}/calibration", name="residuals"),
                    ),
                ),
                column_shares=[3, 2],
                name=s,
            )
        )
    for s in scans:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"/{s}/world", name=f"{s}: scene"),
                rrb.Spatial2DView(origin=f"/{s}/bmode", name=f"{s}: B-mode"),
                column_shares=[3, 2],
                name=s,
            )
        )
    if reconstruction:
        tabs.append(rrb.Spatial3DView(origin="/reconstruction", name="reconstruction"))
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)


def merge_parts(
    options: RecordingOptions,
    parts: Sequence[Path],
    sessions: Sequence[str],
    scans: Sequence[str] = (),
    reconstruction: bool = False,
    main: Recorder | None = None,
) -> Path:
    """Write the run's recording: the main process's own logs (``main``, closed here),
    then every worker's part file, and the blueprint. The part files are removed."""
    rec = main or Recorder(options)
    t0 = time.perf_counter()
    for part in parts:
        log.debug("merging %s (%.1f MB)", part.name, part.stat().st_size / 2**20)
        rr.send_chunks(rr.chunk.RrdReader(part).stream(), recording=rec.stream)
    rec.stream.send_blueprint(blueprint(sessions, scans, reconstruction))
    rec.close()
    log.debug(
        "recording %s: %.1f MB, merged in %.1f s",
        options.path,
        options.path.stat().st_size / 2**20,
        time.perf_counter() - t0,
    )
    for part in parts:
        part.unlink(missing_ok=True)
    if parts:
        with contextlib.suppress(OSError):  # other runs' parts may share it
            parts[0].parent.rmdir()
    return options.path


def log_target(
    rec: Recorder,
    session: str,
    scene_parts: Sequence,
    model: mujoco.MjModel,
    dataset,
    calibration,
    targets_fitted: Sequence[Array],
    truth: tuple[Mapping[tuple[str, int], Array], Array, Sequence[Array]] | None = None,
) -> int:
    """A run calibrated from wires or a cone's tip: the scene, the robot, a spread of
    sweeps (frames at their true poses, the estimated outline), the observations' image
    points through the answer (red), and the targets (each a line strip (k, 3) in the
    base frame: a wire, or a point's single vertex) where the fit puts them (red) and,
    in simulation, where the truth does (green). ``truth`` = (true flange poses per
    (target, pose id), true ``T_ee_us``, true targets). Returns the frames logged."""
    rec.scene(session, scene_parts)
    data = mujoco.MjData(model)
    ids = rec.robot_shapes(session, model)
    T_true, targets_true = None, ()
    if truth is not None:
        T_flange_true, T_ee_us_true, targets_true = truth
        T_true = {
            (s.target, s.pose_id): T_flange_true[(s.target, s.pose_id)] @ T_ee_us_true
            for s in dataset.sweeps
        }
    logged = log_sweeps(
        rec, session, list(dataset.sweeps), model, data, ids, calibration.T_ee_us,
        T_base_us_true=T_true,
    )  # fmt: skip
    if calibration.points_base is not None and len(calibration.points_base):
        rec.points(f"/{session}/world/targets/observed", calibration.points_base, radius=0.0002)
    shown = [("fitted", targets_fitted, RED)]
    if truth is not None:
        shown.append(("true", targets_true, GREEN))
    for name, strips, colour in shown:
        lines = [s for s in strips if len(s) > 1]
        points = [s[0] for s in strips if len(s) == 1]
        if lines:
            rec.lines(f"/{session}/world/targets/{name}", lines, colour)
        if points:
            rec.points(f"/{session}/world/targets/{name}_points", np.array(points), colour)
    return logged
