"""Cone and prism reconstruction on the twin (paper, "Volumetric Reconstruction of
Different Phantoms", Table III and its heatmap figure).

As in the paper, the probe has been taken off and put back (a new true ``T_ee_us``), so it
is re-calibrated from a separate scan of the four-sphere phantom: single-marker on sphere
1 and three-marker on spheres 1-3, with each of the three frozen leave-one-out DH models
(sets A-C). Each DH/``T_ee_us`` pair then maps the boundary samples of one cone scan (45
sweeps about the apex) and one prism scan (45 parallel sweeps along the ridge) to the base
frame, where they are registered to the CAD surface with ICP and scored by their
point-to-surface distances.

Beyond the paper, the same distances are computed without ICP, through the true phantom
pose the twin knows (expressed in each DH model's gauge): this separates the calibration
and kinematic error from shape consistency, which is all the post-ICP residual shows.

The stages are process-pool tasks, queued after the evaluation's datasets and cut small
enough to keep every core busy once those are done (a single 50 CPU-second
re-calibration task left one core idle for half a minute at the end):
- one :func:`run_remount_scan` per sphere (the frames go to a scratch file) and one
  :func:`run_scan` per phantom (its frames are dropped per sweep, only boundary samples
  come back);
- :func:`run_recalibration` per method, as soon as the scans of its spheres are done
  (single-marker: sphere 1's), mapping their frames (both in :mod:`bench.jobs.recalibration`);
- then one :func:`reconstruct_phantom` per phantom.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.protocol import (
    acquire,
    check_plan,
    plan_parallel_sweeps,
    plan_sweeps,
)
from calib.dh import DHTable, forward_kinematics
from calib.evaluation.cross_validation import TABLE_III_METHODS
from calib.evaluation.reconstruct import (
    distance_stats,
    extract_boundaries,
    register_icp,
    surface_distances,
)
from calib.image import pixel_to_us
from calib.kinematics import kinematic_gauge
from twin.imager import acoustic_scene
from twin.phantoms import build_phantom

from ..acquire_sim import coarse_estimate, make_imager, make_twin, teach_at
from ..config.method import axial_scale, image_points
from ..config.scenario import Scenario
from ..progress import report
from ..recording.options import RecordingOptions, sweeps_to_log
from ..recording.recorder import Recorder
from ..results import PhantomReconstruction, PhantomScan, Recalibration
from ..sessions import SESSIONS, dataset_rngs, stage_rngs
from .recalibration import remounted

__all__ = [
    "nominal_placement",
    "phantom_scan_scenario",
    "reconstruct_phantom",
    "reconstruction_metrics",
    "run_scan",
]

Array = NDArray[np.float64]
_MM = 1e3


def phantom_scan_scenario(scenario: Scenario, kind: str) -> Scenario:
    """The cone or prism in the tank: it stands up to ± ``placement_error_mm`` off the
    scenario's position (x, y) and turned up to ± ``placement_error_deg`` about the
    vertical; the scenario's placement is the nominal one ICP starts from."""
    sc = remounted(scenario)
    rc = scenario.reconstruction
    rng = dataset_rngs(scenario, SESSIONS[kind])["placement"]
    dx, dy = rng.uniform(-1, 1, 2) * rc.placement_error_mm
    dz = rng.uniform(-1, 1) * rc.placement_error_deg
    ph = sc.phantom
    x, y, z = ph.position_mm
    rx, ry, rz = ph.rotation_deg
    phantom = replace(
        ph, kind=kind, position_mm=(x + dx, y + dy, z), rotation_deg=(rx, ry, rz + dz)
    )
    return replace(sc, phantom=phantom)


def nominal_placement(scenario: Scenario) -> Array:
    """``T_base_phantom`` as the user placed it: the scenario's phantom pose."""
    ph = scenario.phantom
    R = se3.matrix_from_euler(np.radians(ph.rotation_deg))
    return se3.make(R, np.array(ph.position_mm) * 1e-3)


# ------------------------------------------------------------------------- scan tasks


def _plan(sc: Scenario, twin, kind: str, rng: np.random.Generator):
    """Teach at the apex (cone) or the ridge's middle (prism), as an operator would, off
    by the teaching error; plan the 45 sweeps with the coarse ``T_ee_us``."""
    truth = twin.truth
    proto = sc.protocol
    depth = proto.target_depth_mm * 1e-3
    coarse = coarse_estimate(truth.T_ee_us, sc.calibration, stage_rngs(sc)["calibration"])
    error = proto.teaching_error_mm
    if kind == "cone":
        apex = truth.landmarks_base["apex"]
        taught = teach_at(twin, apex, depth, "taught at the apex", rng, error)
        return taught, plan_sweeps("cone", taught.T_base_ee, coarse, proto)
    a, b = truth.landmarks_base["ridge_start"], truth.landmarks_base["ridge_end"]
    ridge = (b - a) / np.linalg.norm(b - a)
    # The image plane across the ridge: its lateral axis horizontal, normal to the ridge.
    lateral = np.cross([0.0, 0.0, 1.0], ridge)
    taught = teach_at(twin, (a + b) / 2, depth, "taught at the ridge", rng, error, lateral)
    # The sweeps travel along the ridge as the operator sees it on the taught image: the
    # normal of the image plane there, which the coarse T_ee_us predicts.
    travel = (taught.T_base_ee @ coarse)[:3, 2]
    return taught, plan_parallel_sweeps("prism", taught.T_base_ee, coarse, proto, travel=travel)


def run_scan(
    scenario: Scenario, kind: str, recording: RecordingOptions | None = None
) -> PhantomScan:
    """Scan the cone or prism with the remounted probe and extract the boundary samples
    of each sweep's central frames (a process-pool task; frames are dropped per sweep).
    ``recording``: log a spread of the frames with their boundary samples to a part file
    of the run's recording (session ``kind``)."""
    t0 = time.perf_counter()
    sc = phantom_scan_scenario(scenario, kind)
    rngs = dataset_rngs(scenario, SESSIONS[kind])
    twin = make_twin(sc, rngs["joints"])
    imager = make_imager(sc, twin, rngs["imaging"])
    taught, plan = _plan(sc, twin, kind, rngs["protocol"])
    check_plan(twin.robot, plan)
    n_central = min(sc.reconstruction.central_frames, sc.protocol.frames_per_sweep)
    scale = axial_scale(sc)
    q_frames, frame, points, missing, empty = [], [], [], 0, 0
    t_extract = 0.0
    first = (sc.protocol.frames_per_sweep - n_central) // 2
    rec = logged = None
    if recording is not None:
        rec = Recorder(recording.part(kind))
        rec.scene(kind, acoustic_scene(twin.robot.scene.scene).parts)
        robot_ids = rec.robot_shapes(kind, twin.scene.model)
        robot_data = mujoco.MjData(twin.scene.model)
        logged = set(sweeps_to_log(len(plan), n_central, recording.max_frames))
    t_record = 0.0
    for i, planned in enumerate(plan):
        report(f"{kind}: scan sweeps", i, len(plan))
        # The sweep's other frames are never read: the twin does not render them.
        central = replace(planned, T_base_ee=planned.T_base_ee[first : first + n_central])
        true_flange = []
        (sweep,) = acquire(
            twin.robot,
            imager,
            [central],
            on_frame=lambda _p, _j, log=true_flange: log.append(twin.robot.truth.T_base_ee),
        )
        t2 = time.perf_counter()
        sx, sy = sweep.spacing
        width = sweep.images.shape[2]
        pixel_mm = float(np.sqrt(sx * sy)) * _MM
        for j in range(n_central):
            bounds = extract_boundaries(sweep.images[j], pixel_mm=pixel_mm, seed=len(q_frames))
            missing += len(bounds) < 2
            empty += int(sweep.images[j].max() == sweep.images[j].min())
            if rec is not None and i in logged:
                t3 = time.perf_counter()
                rec.next_frame()
                rec.robot_pose(kind, twin.scene.model, robot_data, sweep.q[j], robot_ids)
                T_true = true_flange[j] @ twin.truth.T_ee_us
                rec.frame(kind, sweep.images[j], sweep.spacing, T_true, None, textured=j == 0)
                samples = [b.samples for b in bounds] or [np.zeros((0, 2))]
                rec.boundary(kind, np.concatenate(samples))
                t_record += time.perf_counter() - t3
            for b in bounds:
                points.append(
                    pixel_to_us(b.samples[:, 1], b.samples[:, 0], width, (sx, sy * scale))
                )
                frame.append(np.full(len(b.samples), len(q_frames), dtype=np.int32))
            q_frames.append(sweep.q[j])
        t_extract += time.perf_counter() - t2
    report(f"{kind}: scan sweeps", len(plan), len(plan))
    part = None
    if rec is not None:
        rec.close()
        part = rec.options.path
    t_extract -= t_record
    return PhantomScan(
        kind,
        np.array(q_frames),
        np.concatenate(frame) if frame else np.zeros(0, dtype=np.int32),
        np.concatenate(points) if points else np.zeros((0, 3)),
        taught.q,
        sc.protocol.target_depth_mm * 1e-3,  # image frame: metres, depth corrected
        len(plan),
        missing,
        empty,
        twin.truth.T_base_phantom,
        {
            "simulate": time.perf_counter() - t0 - t_extract - t_record,
            "extract": t_extract,
            "recording": t_record,
        },
        part,
    )


# --------------------------------------------------------------------- reconstruction


def _initial_alignment(
    scan: PhantomScan, landmarks: dict[str, Array], table: DHTable, X: Array, T_nominal: Array
) -> Array:
    """ICP's start (applied to base-frame points): the nominal placement's orientation,
    moved so the scanned landmark (apex, or the ridge's middle) sits where the taught
    image's centre line put it. The nominal position alone can be a centimetre off in the
    DH model's base frame (its base rotation is not identified by touches)."""
    if scan.kind == "cone":
        landmark = landmarks["apex"]
    else:
        landmark = (landmarks["ridge_start"] + landmarks["ridge_end"]) / 2
    T_taught = forward_kinematics(table, scan.q_taught) @ X
    seen = se3.apply(T_taught, np.array([0.0, scan.target_depth, 0.0]))
    R = T_nominal[:3, :3]
    return se3.invert(se3.make(R, seen - R @ landmark))


def reconstruct_phantom(
    scenario: Scenario, scan: PhantomScan, recal: Recalibration, tables: dict[str, DHTable]
) -> PhantomReconstruction:
    """Map one phantom's samples to the base frame with every (set, method) pair of DH
    model and ``T_ee_us``, register each to the CAD surface (ICP) and score it; also score
    it through the true phantom pose (no ICP). A process-pool task."""
    t0 = time.perf_counter()
    rc = scenario.reconstruction
    kind = scan.kind
    true_table = make_twin(scenario).truth.dh_table
    cad = build_phantom(phantom_scan_scenario(scenario, kind).phantom)  # the CAD: no tolerance
    mesh = cad.mesh()
    T_nominal = nominal_placement(scenario)
    q_gauge = scan.q_frames[:: max(1, len(scan.q_frames) // 100)]
    # Per DH model: the flange poses of the frames, and its gauge against the true arm
    # (the base and flange motions touches cannot see) for the distances without ICP.
    flange = {name: forward_kinematics(table, scan.q_frames) for name, table in tables.items()}
    T_phantom_base = {
        name: se3.invert(
            kinematic_gauge(
                table,
                true_table,
                q_gauge,
                se3.apply(recal.T_ee_us[(name, "single")], image_points(scenario, 3)),
            ).B
            @ scan.T_base_phantom_true
        )
        for name, table in tables.items()
    }
    metrics: dict[str, Any] = {}
    points: dict[tuple[str, str], tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
    for method in TABLE_III_METHODS:
        pooled, pooled_true = [], []
        metrics[method] = {}
        for name, table in tables.items():
            X = recal.T_ee_us[(name, method)]
            T = flange[name] @ X
            R, t = T[scan.frame, :3, :3], T[scan.frame, :3, 3]
            P = np.einsum("nij,nj->ni", R, scan.p_us) + t
            report(f"{kind}: ICP", len(points), len(TABLE_III_METHODS) * len(tables))
            reg = register_icp(
                P,
                mesh,
                initial=_initial_alignment(scan, cad.landmarks, table, X, T_nominal),
                max_iterations=rc.icp_max_iterations,
                max_points=rc.icp_points,
            )
            # Without ICP: through the true placement, in this DH model's gauge.
            d_true = surface_distances(mesh, se3.apply(T_phantom_base[name], P)) * _MM
            metrics[method][name] = {
                **distance_stats(reg.distances_mm),
                "n": len(P),
                "icp_iterations": reg.iterations,
                "without_icp": distance_stats(d_true),
            }
            pooled.append(reg.distances_mm)
            pooled_true.append(d_true)
            points[(method, name)] = (
                se3.apply(reg.T, P).astype(np.float32),
                reg.distances_mm.astype(np.float32),
            )
        report(f"{kind}: ICP", len(points), len(TABLE_III_METHODS) * len(tables))
        metrics[method]["overall"] = {
            **distance_stats(np.concatenate(pooled)),
            "n": int(sum(len(d) for d in pooled)),
            "without_icp": distance_stats(np.concatenate(pooled_true)),
        }
    metrics.update(
        {
            "n_sweeps": scan.n_sweeps,
            "n_frames": len(scan.q_frames),
            "frames_without_two_boundaries": scan.frames_without_two_boundaries,
            "frames_without_echo": scan.frames_without_echo,
            "timing_s": {**scan.timing_s, "register": time.perf_counter() - t0},
        }
    )
    return PhantomReconstruction(kind, metrics, points)


def reconstruction_metrics(
    parts: list[PhantomReconstruction], recal: Recalibration
) -> dict[str, Any]:
    """``metrics.json``'s ``reconstruction`` section: per phantom Table III's statistics
    (``{cone,prism}.{single,three}.{A,B,C,overall}.{mae,sd,rmse,max}``, with ``n`` and
    the ``without_icp`` figures), and the re-calibration against the truth."""
    out: dict[str, Any] = {p.kind: p.metrics for p in parts}
    out["recalibration"] = {
        "true_error": {
            f"{name}/{method}": {"n_retained": recal.n_retained[(name, method)], **err}
            for (name, method), err in recal.truth.items()
        },
        "timing_s": recal.timing_s,
    }
    return out
