"""``uscal calibrate`` of an N-wire dataset (``uscal import plus --config``, or a robot
rig's N-wire acquisition): uscal's own wire detection on every frame, ``T_ee_us`` (PLUS's
``ImageToProbe``) with the pixel scale and, without a tracked phantom, the phantom's pose
(:mod:`calib.calibration.nwire`), its bounds and verdict; and ``uscal run`` of an N-wire
scenario, the same on the twin's acquisition scored against its truth. Written by
:mod:`bench.outputs.target_files`."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.calibration.nwire import (
    NWireCalibration,
    NWireObservations,
    calibrate_either_side,
    dataset_frames,
    dataset_spacing_m,
    observe_nwires,
    plus_error_mm,
)
from calib.calibration.targets import (
    TargetModel,
    TargetVerdict,
    calibrate_targets,
    judge_targets,
    nominal_xy,
    wire_starts,
)
from calib.calibration.uncertainty import pose_orientation_groups
from calib.calibration.verdict import Requirements
from calib.errors import UscalError
from calib.files.dataset import AcquisitionInfo
from calib.image import pixel_to_us
from calib.localize.cone_tip import locate_cone_tip
from calib.localize.nwire import detect_wire
from calib.records import Dataset
from calib.targets import PointTarget, TargetObservations, WireTarget
from sim_us.materials import medium_material

from ..acquire_sim import acquisition_info
from ..config.method import requirements, scenario_uncertainty
from ..truth import equivalent_mount, transform_difference

__all__ = [
    "TargetRun",
    "calibrate_cone_dataset",
    "calibrate_nwire_dataset",
    "calibrate_wire_dataset",
    "run_target",
]

_MM = 1e3
Array = NDArray[np.float64]


@dataclass(frozen=True)
class TargetRun:
    """An N-wire dataset's calibration and what it rests on."""

    dataset: Dataset
    info: AcquisitionInfo
    path: Path
    observations: NWireObservations
    calibration: NWireCalibration
    verdict: TargetVerdict
    metrics: dict[str, Any]


def echo_depth_bias_m(scenario) -> float:
    """The echoes' depth uncertainty a target's bounds declare (1 σ, m): the scenario's
    (the localizer's bias along the beam) and, for wires, where between the wire's front
    surface and its axis the echo's centre lies — anywhere from the specular point a
    radius above the axis (the wire's definition) to the axis itself: the rms of such
    a bias, r/√3 (on the twin with every other error source off, the single wire's
    0.06 mm over the image is that bias)."""
    bias = scenario_uncertainty(scenario).axial_bias_m
    if scenario.phantom.kind in ("nwire", "wire"):
        bias = max(bias, scenario.phantom.wire_diameter_mm / 2 * 1e-3 / np.sqrt(3.0))
    return bias


def mount_error(scenario) -> dict[str, float]:
    """The rig's own mount error a target's bounds declare (``mount_sigma_m``,
    ``mount_sigma_rad``): the scenario's, as its sphere calibrations' bounds take it
    (:func:`bench.config.method.scenario_uncertainty`)."""
    inputs = scenario_uncertainty(scenario)
    return {"mount_sigma_m": inputs.mount_sigma_m, "mount_sigma_rad": inputs.mount_sigma_rad}


def _views(info: AcquisitionInfo, poses: Array) -> NDArray[np.int_] | None:
    """The jackknife's groups of a robot's frames: its views (the frames of one flange
    orientation share what that orientation does to the targets' echoes); None for a
    freehand recording (PLUS's), whose groups are blocks of consecutive frames."""
    if info.source == "plus":
        return None
    return pose_orientation_groups(poses)


def _condition(eigenvalues) -> float:
    return float(eigenvalues[0] / eigenvalues[-1]) if eigenvalues[-1] > 0 else float("inf")


def calibrate_nwire_dataset(
    dataset: Dataset,
    info: AcquisitionInfo,
    path: str | Path,
    requirements: Requirements,
    *,
    estimate_scale: bool = True,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
    mount_sigma_m: float = 0.0,
    mount_sigma_rad: float = 0.0,
) -> TargetRun:
    """Detect, calibrate and judge (see the module doc). ``wire_tolerance_m``,
    ``axial_bias_m``, ``mount_sigma_m`` and ``mount_sigma_rad``: the declared errors of
    the bounds (the phantom's build tolerance, the echoes' depth bias, the rig's own
    mount error; :func:`calib.calibration.nwire.calibrate_nwire`)."""
    assert info.nwire is not None
    t0 = time.perf_counter()
    images, poses = dataset_frames(dataset)
    spacing = dataset_spacing_m(dataset, info)
    spacing_mm = (spacing[0] * _MM, spacing[1] * _MM)
    obs = observe_nwires(images, info.nwire.patterns, spacing_mm)
    t_detect = time.perf_counter() - t0
    H, W = images.shape[1:]
    cal, obs, mirrored = calibrate_either_side(
        obs,
        info.nwire.patterns,
        spacing_mm,
        poses,
        width_px=W,
        height_px=H,
        spacing_m=spacing,
        T_base_phantom=info.nwire.T_base_phantom,
        estimate_scale=estimate_scale,
        wire_tolerance_m=wire_tolerance_m,
        axial_bias_m=axial_bias_m,
        mount_sigma_m=mount_sigma_m,
        mount_sigma_rad=mount_sigma_rad,
        groups_of_frames=_views(info, poses),
    )
    verdict = judge_targets(cal, requirements)
    return _target_run(
        "nwire", dataset, info, path, obs, cal, verdict,
        shape=(H, W), spacing=spacing, n_frames=len(images),
        patterns=len(info.nwire.patterns),
        phantom_pose="estimated" if cal.phantom_estimated else "tracked",
        detection={
            "frames_found": obs.frames_used,
            "points": len(obs.frame),
            "refused": dict(obs.refusals().most_common()),
            "marked_side": "last wire first" if mirrored else "first wire first",
        },
        times=(t_detect, t0),
    )  # fmt: skip


def _target_run(
    kind: str,
    dataset: Dataset,
    info: AcquisitionInfo,
    path: str | Path,
    obs: NWireObservations,
    cal: NWireCalibration,
    verdict: TargetVerdict,
    *,
    shape: tuple[int, int],
    spacing: tuple[float, float],
    n_frames: int,
    patterns: int,
    phantom_pose: str,
    detection: dict[str, Any],
    times: tuple[float, float],
    error_note: str | None = None,
) -> TargetRun:
    """The run's metrics, one layout for every kind of target (``kind``: its key)."""
    t_detect, t0 = times
    metrics: dict[str, Any] = {
        "dataset": {
            "path": str(path),
            "name": dataset.name,
            "source": info.source,
            "target": kind,
            "n_sequences": len(dataset.sweeps),
            "n_frames": n_frames,
            "patterns": patterns,
            "phantom_pose": phantom_pose,
        },
        "image": {
            "width_px": int(shape[1]),
            "height_px": int(shape[0]),
            "spacing_m": [float(v) for v in spacing],
        },
        "detection": detection | {"ms_per_frame": t_detect / max(n_frames, 1) * 1e3},
        "calibration": {kind: _calibration_metrics(cal, verdict)},
        "timing_s": {"detection": t_detect, "total": time.perf_counter() - t0},
    }
    if error_note is not None:
        metrics["calibration"][kind]["reprojection_3d_mm"]["note"] = error_note
    return TargetRun(dataset, info, Path(path), obs, cal, verdict, metrics)


def _calibration_metrics(cal: NWireCalibration, verdict: TargetVerdict) -> dict[str, Any]:
    mean, sd = plus_error_mm(cal.errors_mm)
    return {
        "T_ee_us": cal.T_ee_us.tolist(),
        "plus_ImageToProbe_mm": cal.image_to_probe_mm().tolist(),
        "spacing_fitted_mm": [v * _MM for v in cal.spacing_m],
        "scale_estimated": cal.scale_estimated,
        "scale": list(cal.scale),
        "T_base_phantom": cal.T_base_phantom.tolist(),
        "reprojection_3d_mm": {
            "plus_mean": mean,
            "plus_sd": sd,
            "mean": float(cal.errors_mm.mean()),
            "median": float(np.median(cal.errors_mm)),
            "p95": float(np.percentile(cal.errors_mm, 95)),
            "note": "PLUS's statistic: mean and SD below the 95th percentile",
        },
        "bound95": cal.bound95,
        "covariance_rotvec_rad_translation_m_scale": cal.covariance.tolist(),
        "jackknife_blocks": cal.blocks,
        "information": {
            "eigenvalues": cal.information_eigenvalues.tolist(),
            "condition_number": _condition(cal.information_eigenvalues),
            "note": "about the mount (rotation rad, translation mm), the phantom "
            "pose and scale profiled out",
        },
        "outliers": cal.outliers,
        "converged": cal.converged,
        "solver": cal.message,
        "verdict": verdict.as_dict(),
        "seconds": cal.seconds,
    }


def _wire_tolerance(obs: TargetObservations, target: WireTarget, tolerance: float):
    """The build tolerance as declared errors: each coordinate of each wire end at 1 σ,
    moving the line where each observation meets it (by its place along the wire)."""

    def columns(model: TargetModel, x):
        if tolerance <= 0:
            return None
        _, T_P, _ = model.unpack(x)
        image, _ = model.points(x)
        local = se3.apply(se3.invert(T_P), image)
        front, back = np.asarray(target.front), np.asarray(target.back)
        s = ((local - front) @ target.direction) / np.linalg.norm(back - front)
        cols = []
        for weight in (1.0 - s, s):  # the front end, the back end
            for axis in range(3):
                delta = np.zeros((len(s), 3))
                delta[:, axis] = weight * tolerance
                cols.append(model.shift_columns(x, delta))
        return np.column_stack(cols)

    return columns


def calibrate_wire_dataset(
    dataset: Dataset,
    info: AcquisitionInfo,
    path: str | Path,
    requirements: Requirements,
    *,
    estimate_scale: bool = True,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
    mount_sigma_m: float = 0.0,
    mount_sigma_rad: float = 0.0,
) -> TargetRun:
    """A single wire's dataset: the wire's dot in every frame
    (:func:`calib.localize.nwire.detect_wire`), then ``T_ee_us``, the pixel scale and the
    wire's pose (:func:`calib.calibration.targets.calibrate_targets`, the wire's two
    constraints per frame), from the coarse mount as start; its bounds and verdict."""
    if info.wire is None:
        raise UscalError("not a single-wire dataset: its manifest has no acquisition.phantom.wire")
    front, back = info.wire.wire.front, info.wire.wire.back
    target = WireTarget(info.wire.wire.name, front, back)
    t0 = time.perf_counter()
    images, poses = dataset_frames(dataset)
    spacing = dataset_spacing_m(dataset, info)
    spacing_mm = (spacing[0] * _MM, spacing[1] * _MM)
    detections = tuple(detect_wire(f, spacing_mm) for f in images)
    found = [k for k, d in enumerate(detections) if d.ok]
    t_detect = time.perf_counter() - t0
    obs = NWireObservations(
        np.array(found, dtype=int),
        np.zeros(len(found), dtype=int),
        np.array([detections[k].points["wire"] for k in found], dtype=float).reshape(-1, 2),
        np.tile(np.asarray(front, dtype=float), (len(found), 1)),
        detections,
        None,
        np.array([detections[k].skew["wire"] for k in found], dtype=float),
    )
    tobs = TargetObservations(
        obs.frame, obs.pattern, obs.pixel, obs.phantom_point, obs.skew, obs.refusals()
    )
    H, W = images.shape[1:]
    starts = [None]
    if len(found):
        X0 = info.T_ee_us_coarse
        starts = [(X0, P0) for P0 in wire_starts(tobs, target, poses, X0, W, spacing)]
    views = _views(info, poses)
    fits = [
        calibrate_targets(
            tobs,
            [target],
            poses,
            width_px=W,
            height_px=H,
            spacing_m=spacing,
            start=start,
            estimate_scale=estimate_scale,
            declared=_wire_tolerance(tobs, target, wire_tolerance_m),
            axial_bias_m=axial_bias_m,
            mount_sigma_m=mount_sigma_m,
            mount_sigma_rad=mount_sigma_rad,
            groups=None if views is None else views[tobs.frame],
        )
        for start in starts
    ]
    # The start whose answer the dots agree with best (the others' fits end in a
    # minimum where they scatter by millimetres).
    cal = min(fits, key=lambda c: c.sigma_mm)
    verdict = judge_targets(cal, requirements)
    return _target_run(
        "wire", dataset, info, path, obs, cal, verdict,
        shape=(H, W), spacing=spacing, n_frames=len(images), patterns=1,
        phantom_pose=f"estimated ({cal.phantom_dof} of its 6 directions: a lone wire's "
        "pose along and about itself is not seen)",
        detection={
            "frames_found": obs.frames_used,
            "points": len(obs.frame),
            "refused": dict(obs.refusals().most_common()),
        },
        times=(t_detect, t0),
        error_note="for a wire: each dot's distance from the wire across it (mean and SD "
        "below the 95th percentile, as PLUS states its 3-D error)",
    )  # fmt: skip


def _pose_at(T: Array, e: Array, e0: float) -> Array:
    """The flange pose of a sweep at elevation ``e0`` between its frames' (``e`` each):
    the two nearest frames' translations interpolated (a sweep slides the probe; its
    turn is the nearest frame's)."""
    order = np.argsort(e)
    i = int(np.clip(np.searchsorted(e[order], e0), 1, len(e) - 1))
    a, b = order[i - 1], order[i]
    u = (e0 - e[a]) / (e[b] - e[a]) if e[b] != e[a] else 0.0
    out = T[a if u < 0.5 else b].copy()
    out[:3, 3] = T[a, :3, 3] + u * (T[b, :3, 3] - T[a, :3, 3])
    return out


def calibrate_cone_dataset(
    dataset: Dataset,
    info: AcquisitionInfo,
    path: str | Path,
    requirements: Requirements,
    *,
    estimate_scale: bool = False,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
    mount_sigma_m: float = 0.0,
    mount_sigma_rad: float = 0.0,
) -> TargetRun:
    """A cone's sweeps: the apex of each (:func:`calib.localize.cone_tip.locate_cone_tip`,
    the sweep's elevations from the robot's poses along the coarse mount's image normal;
    the apex put in the image at the pose the sweep passes over it), then ``T_ee_us``
    and the cone's position (:func:`calib.calibration.targets.calibrate_targets`, a
    point target: three constraints per sweep; the pixel scale held unless asked),
    from the coarse mount as start. ``wire_tolerance_m``: the apex's print tolerance."""
    if info.cone_tip is None:
        raise UscalError("not a cone-tip dataset: its manifest has no acquisition.phantom apex")
    apex = info.cone_tip.apex
    target = PointTarget("apex", np.asarray(apex, dtype=float), "cone_tip")
    t0 = time.perf_counter()
    spacing = dataset_spacing_m(dataset, info)
    X0 = info.T_ee_us_coarse
    poses, pixels, found, refused = [], [], [], Counter()
    W = H = 0
    for s in dataset.sweeps:
        H, W = s.images.shape[1:]
        normal = (s.T_base_ee[s.reference_index] @ X0)[:3, 2]
        e = (s.T_base_ee[:, :3, 3] - s.T_base_ee[s.reference_index, :3, 3]) @ normal
        tip = locate_cone_tip(s.images, e, spacing, W)
        if not tip.ok:
            refused[tip.reason] += 1
            continue
        found.append(tip)
        poses.append(_pose_at(s.T_base_ee, e, tip.elevation_m))
        pixels.append([tip.x_m / spacing[0] + (W - 1) / 2, tip.depth_m / spacing[1]])
    t_detect = time.perf_counter() - t0
    n = len(found)
    tobs = TargetObservations.of(
        np.arange(n), np.zeros(n), pixels, np.tile(target.position, (n, 1)), refused=refused
    )
    start = None
    if n:
        T = np.array(poses) @ X0
        xy = nominal_xy(tobs.pixel, W, spacing)
        pts = np.einsum("nij,nj->ni", T[:, :3, :3], np.column_stack([xy, np.zeros(n)]))
        centre = (pts + T[:, :3, 3]).mean(axis=0)
        start = (X0, se3.make(np.eye(3), centre - target.position))

    views = _views(info, np.array(poses).reshape(-1, 4, 4)) if n else None
    # A view's tips share a bias no residual of the calibration shows: where the surface
    # lies within its echo depends on the incidence, and within the slice's flat top
    # (its half thickness) the apex's elevation is not resolved. Each view's tips are
    # off by as much as the surface echoes scatter about the fitted cone (their robust
    # scatter, per axis, 1 σ) or that half thickness (uniform: its √3rd), the same way
    # for the sweeps of one view (measured on the twin's cone: the views' mean errors
    # 0.1–0.3 mm per axis, the echoes' scatter ≈ 0.2 mm).
    sigma_e = (
        float(
            np.median(
                [max(f.scatter_px * spacing[1], f.slice_half_m / np.sqrt(3.0)) for f in found]
            )
        )
        if n
        else 0.0
    )

    def tolerance(model: TargetModel, x: Array) -> Array | None:
        cols = []
        for axis in range(3 if wire_tolerance_m > 0 else 0):
            delta = np.zeros((n, 3))
            delta[:, axis] = wire_tolerance_m
            cols.append(model.shift_columns(x, delta))
        if sigma_e > 0 and views is not None:
            T_X, T_P, _ = model.unpack(x)
            for axis in range(3):  # the image's axes, in the phantom frame
                along = (model.T_k @ T_X)[:, :3, axis] @ T_P[:3, :3]
                for g in np.unique(views):
                    delta = np.where((views == g)[:, None], sigma_e * along, 0.0)
                    cols.append(model.shift_columns(x, delta))
        return np.column_stack(cols) if cols else None

    cal = calibrate_targets(
        tobs,
        [target],
        np.array(poses).reshape(-1, 4, 4),
        width_px=W,
        height_px=H,
        spacing_m=spacing,
        start=start,
        estimate_scale=estimate_scale,
        declared=tolerance,
        axial_bias_m=axial_bias_m,
        mount_sigma_m=mount_sigma_m,
        mount_sigma_rad=mount_sigma_rad,
        groups=views,
    )
    verdict = judge_targets(cal, requirements)
    obs = NWireObservations(
        tobs.frame, tobs.target, tobs.pixel, tobs.phantom_point, (), None, tobs.skew
    )
    return _target_run(
        "cone_tip", dataset, info, path, obs, cal, verdict,
        shape=(H, W), spacing=spacing,
        n_frames=int(sum(s.n_frames for s in dataset.sweeps)), patterns=1,
        phantom_pose=f"estimated ({cal.phantom_dof} of its 6 directions: a lone point's "
        "turn about itself is not seen)",
        detection={
            "sweeps_found": n,
            "frames_found": n,
            "points": n,
            "refused": dict(refused.most_common()),
            "half_angle_deg": float(np.median([f.half_angle_deg for f in found]))
            if found else None,
        },
        times=(t_detect, t0),
        error_note="each sweep's apex: its distance from the cone's fitted tip (mean and SD "
        "below the 95th percentile, as PLUS states its 3-D error)",
    )  # fmt: skip


# ---------------------------------------------------------------- the twin's runs


def run_target(scenario, twin, acq, t_start: float) -> TargetRun:
    """``uscal run`` of an N-wire scenario: the acquisition's frames calibrated as
    ``uscal calibrate`` would (phantom pose estimated), then scored against the twin's
    truth — rotation, translation and mean image error of ``T_ee_us`` with the fitted
    pixel scale, and whether the 95 % bounds cover them."""

    info = acquisition_info(scenario, twin, acq.T_ee_us_coarse)
    t_sim = time.perf_counter() - t_start
    calibrate = {
        "wire": calibrate_wire_dataset,
        "nwire": calibrate_nwire_dataset,
        "cone": calibrate_cone_dataset,
    }[scenario.phantom.kind]
    result = calibrate(
        acq.dataset,
        info,
        "(twin acquisition)",
        requirements(scenario),
        wire_tolerance_m=scenario.phantom.tolerance_position_mm / _MM,
        axial_bias_m=echo_depth_bias_m(scenario),
        **mount_error(scenario),
    )
    truth = twin.truth
    X_equiv = equivalent_mount(scenario, acq, truth)
    T_true = truth.T_ee_us if X_equiv is None else X_equiv
    cal = result.calibration
    # The image's pixels as each maps them: the fit with its spacing, the truth with the
    # scanner's true one (its scale error; depth drawn at the assumed speed of sound).
    im = scenario.imaging
    H, W = im.image_shape
    rows, cols = np.meshgrid(np.linspace(0, H - 1, 21), np.linspace(0, W - 1, 21))
    ex, ey = im.pixel_scale_error_pct
    c = medium_material(scenario.medium.kind, scenario.medium.temperature_c).speed_m_s
    sx, sy = im.spacing_m
    true_spacing = (sx / (1 + ex / 100), sy / (1 + ey / 100) * c / im.assumed_speed_m_s)
    est = se3.apply(cal.T_ee_us, pixel_to_us(rows, cols, W, cal.spacing_m).reshape(-1, 3))
    true = se3.apply(T_true, pixel_to_us(rows, cols, W, true_spacing).reshape(-1, 3))
    error = transform_difference(cal.T_ee_us, T_true) | {
        "image_mm": float(np.linalg.norm(est - true, axis=1).mean() * _MM)
    }
    b = cal.bound95
    covered = {k: bool(error[k] <= b[k]) for k in ("rotation_deg", "translation_mm", "image_mm")}
    m = result.metrics
    m["scenario"] = {"name": scenario.source, "seed": scenario.seed}
    m["acquisition"] = {
        "sweeps": len(acq.dataset.sweeps),
        "frames": int(sum(s.n_frames for s in acq.dataset.sweeps)),
        "robot_time_s": acq.robot_time_s,
        "plan": scenario.protocol.plan or "paper",
        "replaced": [r.line() for r in acq.replaced],
    }
    kind = m["dataset"]["target"]
    m["calibration"][kind]["true_error"] = error
    m["calibration"][kind]["bound_covers"] = covered
    m["calibration"][kind]["coarse_error"] = transform_difference(acq.T_ee_us_coarse, truth.T_ee_us)
    m["timing_s"]["simulate"] = t_sim
    m["timing_s"]["total"] = time.perf_counter() - t_start
    return replace(result, path=Path(scenario.output.dir), metrics=m)
