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
  (single-marker: sphere 1's), mapping their frames;
- then one :func:`reconstruct_phantom` per phantom.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.calibrate import alternate
from calib.dh import DHTable, forward_kinematics
from calib.evaluate import TABLE_III_METHODS
from calib.image import pixel_to_us
from calib.kinematics import kinematic_gauge, with_kinematics
from calib.localization import SweepLocalization
from calib.localize import localize_sphere
from calib.protocol import (
    acquire,
    check_plan,
    facing_pose,
    plan_parallel_sweeps,
    plan_sweeps,
)
from calib.reconstruct import distance_stats, extract_boundaries, register_icp, surface_distances
from calib.records import Sweep
from twin.imager import acoustic_scene
from twin.phantoms import build_phantom

from .experiment import (
    axial_scale,
    coarse_estimate,
    frames_to_file,
    image_points,
    make_imager,
    make_twin,
    release_memory,
    simulate_acquisition,
    with_frames,
    without_frames,
)
from .progress import report
from .recording_options import RecordingOptions
from .scenario import Scenario, layout_sigma_mm
from .sessions import REMOUNT_KEY, SESSIONS, dataset_rngs, stage_rngs, stream
from .truth import mount_error

__all__ = [
    "PhantomReconstruction",
    "PhantomScan",
    "Recalibration",
    "RemountScan",
    "nominal_placement",
    "recalibration_scenario",
    "reconstruct_phantom",
    "reconstruction_metrics",
    "run_recalibration",
    "run_remount_scan",
    "run_scan",
    "scan_scenario",
]

Array = NDArray[np.float64]
_MM = 1e3


def _remounted(scenario: Scenario) -> Scenario:
    """The probe taken off and put back: its true mount moves by the configured amounts."""
    rc = scenario.reconstruction
    rng = stream(scenario.seed, REMOUNT_KEY)
    t = scenario.tools
    pos = np.add(t.probe_mount_position_mm, rng.normal(0.0, rc.remount_position_mm, 3))
    rot = np.add(t.probe_mount_rotation_deg, rng.normal(0.0, rc.remount_rotation_deg, 3))
    tools = replace(
        t,
        probe_mount_position_mm=tuple(float(v) for v in pos),
        probe_mount_rotation_deg=tuple(float(v) for v in rot),
    )
    return replace(scenario, tools=tools)


def recalibration_scenario(scenario: Scenario) -> Scenario:
    """The separate four-sphere scan after the remount, of the spheres Table III's
    methods use (sphere 4 is used by neither, so it is not scanned)."""
    sc = _remounted(scenario)
    used = sorted({t for spheres in TABLE_III_METHODS.values() for t in spheres})
    spheres = tuple(int(t.split("_")[1]) for t in used)
    return replace(sc, protocol=replace(sc.protocol, spheres=spheres))


def scan_scenario(scenario: Scenario, kind: str) -> Scenario:
    """The cone or prism in the tank: it stands up to ± ``placement_error_mm`` off the
    scenario's position (x, y) and turned up to ± ``placement_error_deg`` about the
    vertical; the scenario's placement is the nominal one ICP starts from."""
    sc = _remounted(scenario)
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


# ----------------------------------------------------------------- re-calibration tasks


@dataclass(frozen=True, eq=False)
class RemountScan:
    """One sphere of the re-calibration scan after the remount: its sweeps and their
    first localization (under the coarse ``T_ee_us``). The frames are in the file
    ``images`` (one array, sweep by sweep), which every calibration task maps instead of
    receiving its own copy; :meth:`sweeps_with_frames` puts them back."""

    target: str
    sweeps: tuple[Sweep, ...]  # their ``images`` are empty: the frames are in the file
    images: Path
    first: tuple[SweepLocalization, ...]
    cad_centre: Array  # the sphere's centre in the phantom's CAD (three-marker)
    T_ee_us_coarse: Array
    T_ee_us_true: Array  # truth: kept apart, for the error against it
    dh_true: DHTable  # truth: the true arm, for the error in each model's gauge
    timing_s: dict[str, float]

    def sweeps_with_frames(self) -> tuple[Sweep, ...]:
        return tuple(with_frames(self.sweeps, self.images))


def run_remount_scan(scenario: Scenario, index: int, scratch: Path) -> RemountScan:
    """Scan sphere ``index`` with the remounted probe (the re-calibration's protocol), save
    its frames to ``scratch`` and localize it once under the coarse ``T_ee_us`` (a
    process-pool task: one per sphere, so the scan spreads over the workers)."""
    t0 = time.perf_counter()
    sc = recalibration_scenario(scenario)
    sc = replace(sc, protocol=replace(sc.protocol, spheres=(index,)))
    rngs = dataset_rngs(scenario, SESSIONS["recalibration"] + index)
    twin = make_twin(sc, rngs["joints"])
    imager = make_imager(sc, twin, rngs["imaging"])
    target = f"sphere_{index}"
    acq = simulate_acquisition(
        sc, twin, imager, "remount", rngs["protocol"], progress=f"remount: scan {target}"
    )
    truth, coarse = twin.truth, acq.T_ee_us_coarse
    cad_centre = twin.phantom_cad.landmarks[target]
    del imager, twin
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    sweeps = acq.dataset.of(target)
    # The first localization (under the coarse T_ee_us) is done once, on the poses the
    # controller recorded: it depends only on the flange's motion within each 20 mm
    # sweep, on which the DH models differ by a turn of the flange frame of a degree or
    # two (≈ 0.3 mm over 10 mm) — well inside the coarse T_ee_us's own error (up to
    # 10°), and absorbed by the calibration. Every model's alternation starts from it and
    # re-localizes with its own poses.
    first = localize_sphere(
        sweeps, None, sc.phantom.sphere_radius_mm * 1e-3, sc.localization, axial_scale(sc)
    )
    path = scratch / f"remount_{target}.npy"
    frames_to_file(sweeps, path)
    scan = RemountScan(
        target,
        without_frames(sweeps),
        path,
        tuple(first),
        cad_centre,
        coarse,
        truth.T_ee_us,
        truth.dh_table,
        {"simulate": t_sim, "localize": time.perf_counter() - t0},
    )
    del acq, sweeps
    release_memory()
    return scan


@dataclass(frozen=True, eq=False)
class Recalibration:
    """``T_ee_us[(set, method)]`` re-estimated after the remount with each DH model, and
    (kept apart) its error against the truth in that model's gauge."""

    T_ee_us: dict[tuple[str, str], Array]
    n_retained: dict[tuple[str, str], int]
    truth: dict[tuple[str, str], dict[str, float]]
    timing_s: dict[str, float]

    @staticmethod
    def merge(parts: list[Recalibration], scans: list[RemountScan]) -> Recalibration:
        """The per-method tasks' results as one, timed with the scans: ``simulate`` and
        ``calibrate`` (the first localizations included), seconds summed over the tasks."""
        timing = {
            "simulate": sum(s.timing_s["simulate"] for s in scans),
            "calibrate": sum(s.timing_s["localize"] for s in scans)
            + sum(p.timing_s["calibrate"] for p in parts),
        }
        return Recalibration(
            {k: v for p in parts for k, v in p.T_ee_us.items()},
            {k: v for p in parts for k, v in p.n_retained.items()},
            {k: v for p in parts for k, v in p.truth.items()},
            timing,
        )


def run_recalibration(
    scenario: Scenario,
    method: str,
    tables: dict[str, DHTable],
    scans: list[RemountScan],
    threads: int = 1,
) -> Recalibration:
    """Calibrate with ``method`` (of :data:`TABLE_III_METHODS`) from the re-calibration scan of its
    spheres, with each DH model of ``tables`` (a process-pool task, mapping the scans'
    frames). ``threads`` > 1 localizes the spheres side by side (the localizer's kernels
    release the GIL): the three-marker task is the last of the run, mostly alone."""
    t0 = time.perf_counter()
    sc = recalibration_scenario(scenario)
    by_target = {s.target: s for s in scans}
    spheres = TABLE_III_METHODS[method]
    missing = [t for t in spheres if t not in by_target]
    assert not missing, f"re-calibration scan lacks {missing}"
    frames = {t: by_target[t].sweeps_with_frames() for t in spheres}
    truth = by_target[spheres[0]]
    cad = {t: by_target[t].cad_centre for t in spheres} if len(spheres) > 1 else None
    # The truth in each model's gauge: over the frames this calibration used.
    q_frames = np.concatenate([s.q[::10] for t in spheres for s in frames[t]])
    tool_points = se3.apply(truth.T_ee_us_true, image_points(sc, 3))
    T_ee_us, n_retained, errors = {}, {}, {}
    # Every model's alternation would reach its estimate from the first localizations;
    # each later model's starts from the previous model's final ones instead and gets
    # there (within 0.02 mm over the image, measured) in fewer re-localizations, which
    # is why one task calibrates with every model.
    start = {t: by_target[t].first for t in spheres}
    label = f"remount: {method}-marker calibrations"
    report(label, 0, len(tables))
    for name, table in tables.items():
        X_equiv = (
            kinematic_gauge(table, truth.dh_true, q_frames, tool_points).G @ truth.T_ee_us_true
        )
        alt = alternate(
            {t: with_kinematics(frames[t], table) for t in spheres},
            sc.phantom.sphere_radius_mm * 1e-3,
            sc.localization,
            axial_scale(sc),
            cad,
            truth.T_ee_us_coarse,
            sc.calibration.max_alternations,
            initial=start,
            threads=threads,
            layout_sigma_mm=layout_sigma_mm(sc),
        )
        start = alt.localizations
        X = alt.result.T_ee_us
        T_ee_us[(name, method)] = X
        n_retained[(name, method)] = int(alt.result.retained.sum())
        errors[(name, method)] = mount_error(sc, X, X_equiv)
        report(label, len(errors), len(tables))
    return Recalibration(T_ee_us, n_retained, errors, {"calibrate": time.perf_counter() - t0})


# ------------------------------------------------------------------------- scan tasks


@dataclass(frozen=True, eq=False)
class PhantomScan:
    """Boundary samples of one phantom's 45 sweeps (no frames): per used frame its joint
    angles, per sample its frame and its point in the image (``us``, metres)."""

    kind: str
    q_frames: Array  # (m, 6) reported joint angles of the central frames
    frame: NDArray[np.int32]  # (n,) index into q_frames
    p_us: Array  # (n, 3)
    q_taught: Array  # (6,) the taught pose (apex or mid-ridge on the image centre line)
    target_depth: float  # metres below the transducer face at the taught pose
    n_sweeps: int
    frames_without_two_boundaries: int
    T_base_phantom_true: Array  # truth: kept apart, for the without-ICP distances
    timing_s: dict[str, float]
    recording_part: Path | None = None


def _plan(sc: Scenario, twin, kind: str, rng: np.random.Generator):
    """Teach at the apex (cone) or the ridge's middle (prism), as an operator would, off
    by the teaching error; plan the 45 sweeps with the coarse ``T_ee_us``."""
    truth = twin.truth
    proto = sc.protocol
    depth = proto.target_depth_mm * 1e-3
    coarse = coarse_estimate(truth.T_ee_us, sc.calibration, stage_rngs(sc)["calibration"])
    miss = rng.normal(0.0, proto.teaching_error_mm * 1e-3, 3)
    if kind == "cone":
        T_face = facing_pose(truth.landmarks_base["apex"] + miss, depth)
        taught = twin.robot.teach(T_face @ se3.invert(truth.T_ee_us), "taught at the apex")
        return taught, plan_sweeps("cone", taught.T_base_ee, coarse, proto)
    a, b = truth.landmarks_base["ridge_start"], truth.landmarks_base["ridge_end"]
    ridge = (b - a) / np.linalg.norm(b - a)
    # The image plane across the ridge: its lateral axis horizontal, normal to the ridge.
    lateral = np.cross([0.0, 0.0, 1.0], ridge)
    T_face = facing_pose((a + b) / 2 + miss, depth, lateral)
    taught = twin.robot.teach(T_face @ se3.invert(truth.T_ee_us), "taught at the ridge")
    # The sweeps travel along the ridge as the operator sees it on the taught image: the
    # normal of the image plane there, which the coarse T_ee_us predicts.
    travel = (taught.T_base_ee @ coarse)[:3, 2]
    return taught, plan_parallel_sweeps("prism", taught.T_base_ee, coarse, proto, travel)


def run_scan(
    scenario: Scenario, kind: str, recording: RecordingOptions | None = None
) -> PhantomScan:
    """Scan the cone or prism with the remounted probe and extract the boundary samples
    of each sweep's central frames (a process-pool task; frames are dropped per sweep).
    ``recording``: log a spread of the frames with their boundary samples to a part file
    of the run's recording (session ``kind``)."""
    t0 = time.perf_counter()
    sc = scan_scenario(scenario, kind)
    rngs = dataset_rngs(scenario, SESSIONS[kind])
    twin = make_twin(sc, rngs["joints"])
    imager = make_imager(sc, twin, rngs["imaging"])
    taught, plan = _plan(sc, twin, kind, rngs["protocol"])
    check_plan(twin.robot, plan)
    n_central = min(sc.reconstruction.central_frames, sc.protocol.frames_per_sweep)
    scale = axial_scale(sc)
    q_frames, frame, points, missing = [], [], [], 0
    t_extract = 0.0
    first = (sc.protocol.frames_per_sweep - n_central) // 2
    rec = logged = None
    if recording is not None:
        from .recording import Recorder
        from .recording_options import sweeps_to_log

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
            bounds = extract_boundaries(sweep.images[j], pixel_mm, seed=len(q_frames))
            missing += len(bounds) < 2
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
        twin.truth.T_base_phantom,
        {
            "simulate": time.perf_counter() - t0 - t_extract - t_record,
            "extract": t_extract,
            "recording": t_record,
        },
        part,
    )


# --------------------------------------------------------------------- reconstruction


@dataclass(frozen=True, eq=False)
class PhantomReconstruction:
    """One phantom's Table III statistics (``metrics[method][set]``, plus scan figures)
    and its registered points (CAD frame, metres, float32) with their distances (mm), by
    (method, set)."""

    kind: str
    metrics: dict[str, Any]
    points: dict[tuple[str, str], tuple[NDArray[np.float32], NDArray[np.float32]]]


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
    cad = build_phantom(scan_scenario(scenario, kind).phantom)  # the CAD: no tolerance
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
