"""Targets as one concept (calib/targets.py) and one fit over any mix of them
(calib/calibration/targets.py), against a known truth: an image plane at known poses
cutting a single wire, or passing through a cone's tip, the points as the image would
show them. Every error source off first (the answer exact), then pixel noise inside the
bound; a lone wire's pose along and about itself left alone; the single wire's
threshold-free detection on a frame."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.calibration.targets import calibrate_targets
from calib.errors import CalibrationError
from calib.image import us_to_pixel
from calib.localize.nwire import detect_wire
from calib.targets import (
    KINDS,
    NWireTarget,
    PointTarget,
    TargetObservations,
    WireTarget,
    constraint_rows,
)

MM = 1e-3
W, H = 400, 300
SPACING = (0.1 * MM, 0.1 * MM)
WIRE = WireTarget("wire", np.array([45.0, 0.0, 10.0]) * MM, np.array([45.0, 40.0, 10.0]) * MM)
TIP = PointTarget("apex", np.array([30.0, 20.0, 15.0]) * MM)
T_EE_US = se3.make(se3.matrix_from_rotvec([0.02, -0.03, -1.57]), [0.011, 0.0155, 0.0004])
T_BASE_PHANTOM = se3.make(se3.matrix_from_rotvec([0.1, -0.05, 0.4]), [0.40, -0.10, 0.05])
#: The probe above the phantom looking down: image x along the phantom's x, depth its −z.
R_DOWN = np.column_stack([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


def _frames(rng, n: int, target, turn_deg: float = 15.0):
    """(pixels (n, 2), phantom points (n, 3), T_base_ee (n, 4, 4)) of ``n`` frames whose
    image plane meets the target inside the image."""
    pixels, points, poses = [], [], []
    while len(poses) < n:
        turn = se3.matrix_from_rotvec(np.radians(rng.uniform(-turn_deg, turn_deg, 3)))
        R = turn @ R_DOWN
        if isinstance(target, WireTarget):
            origin = np.array([45.0, rng.uniform(8, 32), 10.0]) * MM
            origin = origin - R @ np.array([rng.uniform(-8, 8), rng.uniform(10, 22), 0]) * MM
            T_phantom_us = se3.make(R, origin)
            a, b = (se3.apply(se3.invert(T_phantom_us), p) for p in (target.front, target.back))
            u = a[2] / (a[2] - b[2])
            if not 0 <= u <= 1:
                continue
            p_us = a + u * (b - a)
            point = target.front
        else:
            in_image = np.array([rng.uniform(-8, 8), rng.uniform(10, 22), 0.0]) * MM
            T_phantom_us = se3.make(R, target.position - R @ in_image)
            p_us, point = in_image, target.position
        r, c = us_to_pixel(p_us, W, SPACING)
        if not (0 <= r < H and 0 <= c < W):
            continue
        pixels.append([c, r])
        points.append(point)
        poses.append(T_BASE_PHANTOM @ T_phantom_us @ se3.invert(T_EE_US))
    return np.array(pixels), np.array(points), np.array(poses)


def _observations(rng, parts, noise_px: float = 0.0):
    """Observations of several targets, frames numbered in order."""
    frame, target, pixel, point, poses = [], [], [], [], []
    for j, (t, n) in enumerate(parts):
        px, pts, T = _frames(rng, n, t)
        frame += list(range(len(poses), len(poses) + n))
        target += [j] * n
        pixel.append(px + rng.normal(0, noise_px, px.shape) if noise_px else px)
        point.append(pts)
        poses += list(T)
    obs = TargetObservations.of(frame, target, np.vstack(pixel), np.vstack(point))
    return obs, [t for t, _ in parts], np.array(poses)


def _start(rng, mm: float, deg: float):
    """The truth, off by about ``mm`` and ``deg`` (the coarse mount, the taught pose)."""

    def off(T):
        turn = se3.matrix_from_rotvec(np.radians(deg) * rng.normal(size=3) / np.sqrt(3))
        return se3.make(turn @ T[:3, :3], T[:3, 3] + mm * MM * rng.normal(size=3) / np.sqrt(3))

    return off(T_EE_US), off(T_BASE_PHANTOM)


def test_each_kind_states_its_constraints():
    """A point is constrained along every direction, a wire only across itself."""
    d = WIRE.direction
    B = constraint_rows(WIRE)
    assert B.shape == (KINDS["wire"], 3)
    np.testing.assert_allclose(B @ B.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(B @ d, 0.0, atol=1e-12)
    np.testing.assert_array_equal(constraint_rows(TIP), np.eye(3))
    assert KINDS["cone_tip"] == KINDS["sphere"] == KINDS["nwire"] == 3
    assert NWireTarget("n", None).kind == "nwire"  # type: ignore[arg-type]


def test_a_single_wire_gives_the_mount_with_every_error_source_off(rng):
    """From a start 3 mm / 3° off, the wire's frames alone give T_ee_us exactly; the
    phantom's pose moves in the four directions a line has, and its line is the true
    one."""
    obs, targets, poses = _observations(rng, [(WIRE, 80)])
    cal = calibrate_targets(
        obs, targets, poses, width_px=W, height_px=H, spacing_m=SPACING,
        start=_start(rng, 3.0, 3.0), estimate_scale=False, n_draws=200,
    )  # fmt: skip
    assert cal.converged and cal.phantom_dof == 4
    assert se3.rotation_angle(cal.T_ee_us, T_EE_US) < 1e-6
    assert np.linalg.norm(cal.T_ee_us[:3, 3] - T_EE_US[:3, 3]) < 1e-7
    line = [se3.apply(T_BASE_PHANTOM, p) for p in (WIRE.front, WIRE.back)]
    fitted = [se3.apply(cal.T_base_phantom, p) for p in (WIRE.front, WIRE.back)]
    d_true = (line[1] - line[0]) / np.linalg.norm(line[1] - line[0])
    d_fit = (fitted[1] - fitted[0]) / np.linalg.norm(fitted[1] - fitted[0])
    assert abs(d_true @ d_fit) > 1 - 1e-10
    gap = fitted[0] - line[0]
    assert np.linalg.norm(gap - (gap @ d_true) * d_true) < 1e-8  # the same line


def test_a_wire_and_a_cone_tip_in_one_fit_stay_within_their_bound(rng):
    """Half a pixel of noise on a wire's and a cone tip's points, the pixel scale fitted:
    the answer lies inside its 95 % bound, and a point beside the wire fixes the
    phantom's whole pose."""
    obs, targets, poses = _observations(rng, [(WIRE, 60), (TIP, 60)], noise_px=0.5)
    cal = calibrate_targets(
        obs, targets, poses, width_px=W, height_px=H, spacing_m=SPACING,
        start=_start(rng, 2.0, 2.0), n_draws=1000,
    )  # fmt: skip
    assert cal.phantom_dof == 6 and cal.converged
    rot = np.degrees(se3.rotation_angle(cal.T_ee_us, T_EE_US))
    trans = np.linalg.norm(cal.T_ee_us[:3, 3] - T_EE_US[:3, 3]) / MM
    assert rot <= cal.bound95["rotation_deg"] and trans <= cal.bound95["translation_mm"]
    assert cal.bound95["translation_mm"] < 1.0
    assert 0.02 < cal.sigma_mm < 0.1  # half a pixel of 0.1 mm, per axis


def test_a_declared_mount_error_goes_into_a_targets_bound_whole(rng):
    """The rig's own mount error (1 σ per axis, declared) widens a target calibration's
    bounds as a sphere calibration's: the translation bound at least its own 95 %
    quantile (2.80 σ), the rotation bound likewise with its orientation term."""
    obs, targets, poses = _observations(rng, [(WIRE, 60), (TIP, 60)], noise_px=0.5)
    kw = dict(width_px=W, height_px=H, spacing_m=SPACING, start=_start(rng, 2.0, 2.0))
    plain = calibrate_targets(obs, targets, poses, n_draws=1000, **kw)
    sigma_mm, sigma_deg = 0.4, 1.5
    declared = calibrate_targets(
        obs, targets, poses, n_draws=1000, mount_sigma_m=sigma_mm * MM,
        mount_sigma_rad=np.radians(sigma_deg), **kw,
    )  # fmt: skip
    assert declared.bound95["translation_mm"] >= 2.8 * sigma_mm > plain.bound95["translation_mm"]
    assert declared.bound95["rotation_deg"] >= 2.8 * sigma_deg > plain.bound95["rotation_deg"]
    np.testing.assert_allclose(declared.T_ee_us, plain.T_ee_us)  # the estimate is the same


def test_wires_without_a_start_and_too_few_frames_are_refused(rng):
    obs, targets, poses = _observations(rng, [(WIRE, 20)])
    with pytest.raises(CalibrationError, match="needs a start"):
        calibrate_targets(obs, targets, poses, width_px=W, height_px=H, spacing_m=SPACING)
    few = obs.subset(obs.frame < 5)
    with pytest.raises(CalibrationError, match="5 frames show the targets"):
        calibrate_targets(
            few, targets, poses, width_px=W, height_px=H, spacing_m=SPACING,
            start=(T_EE_US, T_BASE_PHANTOM),
        )  # fmt: skip


def _speckle(rng, shape=(250, 250)) -> np.ndarray:
    """A water-and-speckle background as a scanner's log-compressed display draws it."""
    env = rng.rayleigh(1.0, shape)
    return np.clip(20 * np.log10(env + 1e-3) + 40, 0, 255)


def test_the_wire_s_dot_is_found_and_an_empty_frame_refused(rng):
    """A dot a wire's size on speckle is found at its centre (the whole echo's centroid);
    speckle alone has no dot standing out of its own maxima: refused with the reason."""
    spacing_mm = (0.1, 0.1)
    frame = _speckle(rng)
    rr, cc = np.mgrid[: frame.shape[0], : frame.shape[1]]
    col, row = 120.3, 140.6
    frame += 180 * np.exp(-(((cc - col) / 4.0) ** 2 + ((rr - row) / 3.0) ** 2) / 2)
    det = detect_wire(np.clip(frame, 0, 255).astype(np.uint8), spacing_mm)
    assert det.ok
    x, y = det.points["wire"]
    assert abs(x - col) < 0.3 and abs(y - row) < 0.3
    empty = detect_wire(_speckle(rng).astype(np.uint8), spacing_mm)
    assert not empty.ok and "stand out" in empty.reason


def test_the_information_of_each_kind_is_the_observability_module_s(rng):
    """A point's constraint rows give the point information, a wire's the line
    information along its direction in the base frame (paper §III-B)."""
    from calib.acquisition.observability import information, information_of_target, jacobians

    T = np.array([se3.make(se3.matrix_from_rotvec(rng.normal(0, 0.2, 3)), rng.normal(0, 0.05, 3))
                  for _ in range(12)])  # fmt: skip
    G = jacobians(T, T_EE_US, rng.normal(0, 0.01, (12, 3)))
    R = T_BASE_PHANTOM[:3, :3]
    np.testing.assert_allclose(information_of_target(G, TIP, R), information(G), rtol=1e-12)
    np.testing.assert_allclose(
        information_of_target(G, WIRE, R),
        information(G, line_direction=R @ WIRE.direction),
        rtol=1e-10,
        atol=1e-9,
    )


def test_a_calibration_held_fits_the_wire_s_pose_and_shows_its_error(rng):
    """With the true mount held, the wire's pose is found and the dots lie on it; a mount
    1 mm off leaves them a tenth of a millimetre off (what `uscal validate` reports of a
    calibration on a single-wire dataset: the wire's own fitted pose absorbs the rest)."""
    from calib.calibration.targets import fit_phantom_pose, wire_starts

    obs, targets, poses = _observations(rng, [(WIRE, 60)])
    off = se3.make(T_EE_US[:3, :3], T_EE_US[:3, 3] + 1e-3)
    errors = {}
    for name, X in (("true", T_EE_US), ("off", off)):
        fits = [
            fit_phantom_pose(obs, targets, poses, T_ee_us=X, spacing_m=SPACING, width_px=W,
                             start=start)
            for start in wire_starts(obs, WIRE, poses, X, W, SPACING)
        ]  # fmt: skip
        errors[name] = min(float(np.median(e)) for _, e in fits)
    assert errors["true"] < 1e-6 and errors["off"] > 0.05
