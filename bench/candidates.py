"""The sweeps a plan can be made of, about the targets the twin's arm faces (spheres, a
wire, an N-wire phantom's wires, a cone's tip): a dense set of sweep poses about each
taught pose (``planning`` settings), kept where the target stays inside the image by the
margin (as the coarse mount predicts it; a wire's or an N pattern's dots in every frame)
and where the arm reaches the sweep's first, middle and last frames with the clearance
from the tank and the phantom; and their information about ``T_ee_us``
(:class:`calib.acquisition.planning.Candidates`) as each target's calibration uses them:
a sphere's centre and a cone's tip one point per sweep, a wire's dot its two constraints
across the wire in every frame, an N pattern's diagonal point in every frame — with the
phantom's pose (as far as the targets see it) and, for wires, the pixel scale unknown
beside ``T_ee_us``, as their fits estimate them (:mod:`calib.calibration.targets`).
Used by ``uscal plan --optimize`` and by the sequential acquisition."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.observability import jacobians
from calib.acquisition.planning import (
    Candidates,
    NoiseModel,
    SweepPose,
    sweep_commands,
)
from calib.acquisition.protocol import facing_pose
from calib.localize.nwire import middle_wire_point
from calib.targets import WireTarget, constraint_rows

from .acquire_sim import teach_at, twin_nwire_phantom
from .config.geometry import TARGET_PHANTOMS, WIRED, lateral_axis
from .config.scenario import Scenario, layout_sigma_mm

__all__ = [
    "NOT_CLEAR",
    "OUT_OF_IMAGE",
    "PlanTarget",
    "candidate_set",
    "candidate_sweeps",
    "clear",
    "in_image",
    "observations",
    "path_clear",
    "sweep_of",
    "taught_target",
]

Array = NDArray[np.float64]
#: Why a candidate sweep is left out.
OUT_OF_IMAGE = "out of the image"
NOT_CLEAR = "unreachable or too close to the tank or phantom"


@dataclass(frozen=True, eq=False)
class PlanTarget:
    """A target a plan sweeps about: a sphere (``sphere_N``), the wires' centre
    (``wire``, ``nwire``) or the cone's tip (``apex``), at its taught pose."""

    name: str
    index: int  # into the plan's targets
    taught: Array  # T_base_ee of the taught pose (as the controller reports it)
    centre: Array  # where the coarse T_ee_us puts the target, base frame (m)
    taught_q: Array | None = None  # the taught joint angles (where its sweeps start from)
    #: The phantom's pose as the taught pose and the coarse mount put it (the target on
    #: the image's centre line, the phantom turned as the probe was taught across it):
    #: where a plan expects the wires; None for spheres.
    T_base_phantom: Array | None = None


def taught_target(
    scenario: Scenario, twin, coarse: Array, name: str, index: int, rng: np.random.Generator
) -> PlanTarget:
    """Teach the nominal pose at target ``name`` as the session's acquisition teaches it
    (its teaching error drawn from ``rng``, the session's protocol stream; across the
    wires for a wire phantom): a rig plans from the pose it was taught, so the twin's
    plan is the one its acquisition checks and moves through. The phantom's expected
    pose follows from the taught pose alone: the CAD target where the image's centre
    line puts it, the phantom turned relative to the probe as the scenario states it
    stands (never the truth)."""
    proto = scenario.protocol
    depth = proto.target_depth_mm * 1e-3
    axis = lateral_axis(scenario.phantom)
    taught = teach_at(
        twin,
        twin.truth.landmarks_base[name],
        depth,
        f"taught pose at {name}",
        rng,
        proto.teaching_error_mm,
        lateral_axis=axis,
    )
    T_us = taught.T_base_ee @ coarse
    centre = se3.apply(T_us, np.array([0.0, depth, 0.0]))
    phantom = None
    if scenario.phantom.kind in TARGET_PHANTOMS:
        P = scenario.phantom.T_base_phantom  # where the phantom is stated to stand
        stated = se3.apply(P, np.asarray(twin.phantom_cad.landmarks[name], dtype=float))
        phantom = T_us @ se3.invert(facing_pose(stated, depth, lateral_axis=axis)) @ P
    return PlanTarget(name, index, taught.T_base_ee, centre, taught.q, phantom)


def candidate_set(scenario: Scenario) -> list[SweepPose]:
    """The dense candidate sweeps (``planning`` grid). About wires, the turn about the
    image's lateral axis is the protocol's ``tilt_deg`` at most (−tilt, 0, +tilt): a
    wire's echo fades with that tilt as a mirror's does, while turns about the axial
    and elevational axes keep the beam across the wire."""
    dense = scenario.planning.candidates()
    if scenario.phantom.kind not in WIRED:
        return dense
    t = scenario.protocol.tilt_deg
    level = [p for p in dense if p.rotation_deg[0] == 0.0]
    tilts = (-t, 0.0, t) if t > 0 else (0.0,)
    return [replace(p, rotation_deg=(rx, *p.rotation_deg[1:])) for rx in tilts for p in level]


def _extent_mm(scenario: Scenario) -> float:
    """How far around the target the image must reach: a sphere's radius; the cone's
    surface echoes about its tip, as far as a sweep reaches (its half length); a wire's
    dot (the dots themselves are checked frame by frame, :func:`_wire_crossings`)."""
    kind = scenario.phantom.kind
    if kind == "cone":
        return scenario.protocol.sweep_half_length_mm
    if kind in WIRED:
        return 0.0
    return scenario.phantom.sphere_radius_mm


def in_image(scenario: Scenario, pose: SweepPose) -> bool:
    """The target, as the coarse mount predicts it, inside the image by the margin."""
    p = scenario.planning
    depth = scenario.protocol.target_depth_mm
    r = _extent_mm(scenario) + p.image_margin_mm
    x, y = -pose.lateral_mm, depth - pose.axial_mm
    return abs(x) + r <= scenario.imaging.width_mm / 2 and r <= y <= scenario.imaging.depth_mm - r


def sweep_of(
    scenario: Scenario,
    target: PlanTarget,
    coarse: Array,
    pose: SweepPose,
    n_frames: int | None = None,
) -> Array:
    """The flange commands of one sweep about ``target`` (``n_frames``: the protocol's,
    or e.g. 3 for its first, middle and last frames)."""
    proto = scenario.protocol
    return sweep_commands(
        target.taught,
        coarse,
        proto.target_depth_mm * 1e-3,
        pose,
        half_length=proto.sweep_half_length_mm * 1e-3,
        n_frames=proto.frames_per_sweep if n_frames is None else n_frames,
    )


def clear(scenario: Scenario, twin, commands: Array) -> bool:
    """Every pose reachable, with the clearance (``planning.clearance_mm``) from the tank
    and the phantom."""
    need = scenario.planning.clearance_mm * 1e-3
    return bool(np.all(twin.robot.clearances(commands, need + 1e-3) >= need))


def path_clear(scenario: Scenario, twin, commands: Array, q_start: Array) -> Array:
    """Per pose of ``commands`` (moved through in order from ``q_start``), whether the
    arm reaches it with the clearance, on the way the acquisition takes."""
    need = scenario.planning.clearance_mm * 1e-3
    return twin.robot.path_clearances(commands, need + 1e-3, q_start) >= need


def candidate_sweeps(scenario, twin, targets, coarse, poses_of, check: bool):
    """(target, pose, commands) of every candidate that passes the checks, and the
    count left out by each check (the reach and clearance of every candidate's first,
    middle and last frames in one batch; a wire's or N pattern's dots in every frame)."""
    out, left = [], {OUT_OF_IMAGE: 0, NOT_CLEAR: 0}
    for s in targets:
        for pose in poses_of(s):
            if check and not in_image(scenario, pose):
                left[OUT_OF_IMAGE] += 1
                continue
            out.append((s, pose, sweep_of(scenario, s, coarse, pose)))
    if check and out and scenario.phantom.kind in WIRED:
        seen = np.ones(len(out), dtype=bool)
        for s in targets:
            mine = [k for k, c in enumerate(out) if c[0] is s]
            _, ok = _wire_crossings(scenario, twin, coarse, s, [out[k] for k in mine])
            seen[mine] = ok.all(axis=(1, 2))
        left[OUT_OF_IMAGE] += int((~seen).sum())
        out = [c for c, k in zip(out, seen, strict=True) if k]
    if check and out:
        ends = np.array([C[[0, len(C) // 2, -1]] for _, _, C in out])
        need = scenario.planning.clearance_mm * 1e-3
        room = twin.robot.clearances(ends.reshape(-1, 4, 4), need + 1e-3).reshape(len(out), 3)
        keep = np.all(room >= need, axis=1)
        left[NOT_CLEAR] += int((~keep).sum())
        out = [c for c, k in zip(out, keep, strict=True) if k]
    return out, left


def observations(scenario, coarse, targets, found, multi: bool, twin=None) -> Candidates:
    """The candidates' information about ``T_ee_us`` as the target's calibration uses
    them: spheres (``multi``: their CAD layout, the phantom's pose unknown; else each
    centre unknown) and the cone's tip one point per sweep; wires frame by frame
    (:func:`_wire_observations`, which needs the ``twin``'s phantom CAD)."""
    kind = scenario.phantom.kind
    if kind in WIRED:
        return _wire_observations(scenario, twin, coarse, targets, found)
    depth = scenario.protocol.target_depth_mm * 1e-3
    T_ref = np.array([C[len(C) // 2] for _, _, C in found])
    p_us = np.array([pose.target_in_image(depth) for _, pose, _ in found])
    target = np.array([s.index for s, _, _ in found])
    if kind == "cone":
        p = scenario.planning
        noise = NoiseModel(*np.hypot(p.cone_tip_noise_mm, p.pose_noise_mm))
        return Candidates.build(T_ref, coarse, p_us, target, noise)
    layout = {s.index: s.centre for s in targets} if multi else None
    return Candidates.build(
        T_ref,
        coarse,
        p_us,
        target,
        scenario.planning.noise(),
        layout=layout,
        layout_sigma_mm=layout_sigma_mm(scenario),
    )


# ------------------------------------------------------------------------- wires


def _wire_crossings(scenario, twin, coarse, target: PlanTarget, found):
    """Where each frame's image plane cuts each of the phantom's wires, as the coarse
    mount and the expected phantom pose predict it: ``p_us`` (n, frames, wires, 3),
    metres, and ``ok`` (n, frames, wires): the dot inside the image by the margin and
    the crossing between the end plates by as much."""
    wires = twin.phantom_cad.wires
    P = target.T_base_phantom
    T = np.array([C for _, _, C in found]) @ coarse  # (n, F, 4, 4) T_base_us
    inv = se3.invert(T.reshape(-1, 4, 4)).reshape(T.shape)
    front = se3.apply(P, np.array([w.front for w in wires]))
    back = se3.apply(P, np.array([w.back for w in wires]))
    a = np.einsum("nfij,wj->nfwi", inv[..., :3, :3], front) + inv[..., None, :3, 3]
    b = np.einsum("nfij,wj->nfwi", inv[..., :3, :3], back) + inv[..., None, :3, 3]
    dz = b[..., 2] - a[..., 2]
    u = np.divide(-a[..., 2], dz, out=np.full(dz.shape, np.nan), where=np.abs(dz) > 1e-9)
    p_us = a + u[..., None] * (b - a)
    margin = scenario.planning.image_margin_mm * 1e-3
    length = np.linalg.norm(back - front, axis=1)  # (wires,)
    im = scenario.imaging
    with np.errstate(invalid="ignore"):
        ok = (
            (np.abs(p_us[..., 0]) <= im.width_mm * 1e-3 / 2 - margin)
            & (p_us[..., 1] >= margin)
            & (p_us[..., 1] <= im.depth_mm * 1e-3 - margin)
            & (u * length >= margin)
            & ((1 - u) * length >= margin)
        )
    return p_us, ok


def _point_noise(R_us: Array, lateral_mm: float, axial_mm: float, pose_mm: float) -> Array:
    """(…, 3, 3) covariance (mm²), base frame, of a dot in images at orientations
    ``R_us`` (…, 3, 3): its own noise in the image plane and the arm's, isotropic."""
    var = np.array([lateral_mm**2, axial_mm**2, 0.0])
    return np.einsum("...ij,j,...kj->...ik", R_us, var, R_us) + pose_mm**2 * np.eye(3)


def _whiten(rows: Array, cov: Array) -> Array:
    """C (…, m, 3): the constraint ``rows`` (…, m, 3) whitened by the covariance of
    their residuals, rows·cov·rowsᵀ."""
    L = np.linalg.cholesky(np.einsum("...ij,...jk,...lk->...il", rows, cov, rows))
    return np.linalg.solve(L, rows)


def _wire_observations(scenario, twin, coarse, targets, found) -> Candidates:
    """Candidates of a wire phantom, frame by frame as the wire calibration fits them
    (:mod:`calib.calibration.targets`): a single wire's dot gives its two constraints
    across the wire; an N pattern's three dots the diagonal's point (three, its position
    along the diagonal as uncertain as the dots' ratio). Unknown beside ``T_ee_us``: the
    phantom's pose (the directions the wires' constraints see) and the two pixel scales.
    A sweep's dots share an offset (``planning.dot_sweep_noise_mm``)."""
    p = scenario.planning
    sl, sa = p.dot_noise_mm
    shared_sd = np.asarray(p.dot_sweep_noise_mm, dtype=float)
    kind = scenario.phantom.kind
    parts = []
    for s in targets:
        mine = [c for c in found if c[0] is s]
        if not mine:
            continue
        p_us, _ = _wire_crossings(scenario, twin, coarse, s, mine)
        C = np.array([c[2] for c in mine])  # (n, F, 4, 4)
        n, F = C.shape[:2]
        R_P = s.T_base_phantom[:3, :3]
        T_us = C @ coarse
        R_us = T_us[..., :3, :3]
        if kind == "wire":
            x_us = p_us[:, :, 0]  # (n, F, 3)
            w = twin.phantom_cad.wires[0]
            rows = constraint_rows(WireTarget(w.name, w.front, w.back)) @ R_P.T  # base
            rows = np.broadcast_to(rows, (n, F, 2, 3))
            cov = _point_noise(R_us, sl, sa, p.pose_noise_mm)
            # The wire's foot: the crossing itself, in the base frame.
            point = np.einsum("nfij,nfj->nfi", R_us, x_us) + T_us[..., :3, 3]
        else:
            patterns = twin_nwire_phantom(twin).patterns
            xs, points, covs = [], [], []
            for j, pattern in enumerate(patterns):
                pa, pm, pb = (p_us[:, :, 3 * j + i] for i in range(3))
                mid = middle_wire_point(
                    pattern, pa[..., :2] * 1e3, pm[..., :2] * 1e3, pb[..., :2] * 1e3
                )
                t = np.linalg.norm(pm - pa, axis=-1) / np.linalg.norm(pb - pa, axis=-1)
                s3 = np.linalg.norm(pb - pa, axis=-1) * 1e3  # mm
                # The diagonal's point moves with the dots' ratio t, by g per unit of t
                # (an affine map of t: its value at t = 1 less that at 0).
                g = middle_wire_point(pattern, [0, 0], [1, 0], [1, 0]) - middle_wire_point(
                    pattern, [0, 0], [0, 0], [1, 0]
                )
                g = R_P @ g * 1e3  # base frame, mm
                var_t = sl**2 * (1 + t**2 + (1 - t) ** 2) / s3**2
                cov = _point_noise(R_us, sl, sa, p.pose_noise_mm)
                covs.append(cov + var_t[..., None, None] * np.outer(g, g))
                xs.append(pm)
                points.append(se3.apply(s.T_base_phantom, mid.reshape(-1, 3)).reshape(n, F, 3))
            x_us = np.stack(xs, axis=2).reshape(n, F * len(patterns), 3)
            point = np.stack(points, axis=2).reshape(n, F * len(patterns), 3)
            cov = np.stack(covs, axis=2).reshape(n, F * len(patterns), 3, 3)
            R_us = np.repeat(R_us, len(patterns), axis=1)
            C = np.repeat(C, len(patterns), axis=1)
            rows = np.broadcast_to(np.eye(3), cov.shape)
        m = C.shape[1]  # observations per sweep
        W = _whiten(rows, cov)  # (n, m, r, 3)
        r = W.shape[2]
        G = jacobians(C.reshape(-1, 4, 4), coarse, x_us.reshape(-1, 3)).reshape(n, m, 3, 6)
        J_theta = np.einsum("nmri,nmij->nmrj", W, G).reshape(n, m * r, 6)
        # The phantom's pose (a turn about the target's centre, mrad-scaled as θ's, and a
        # shift): the constraint moves with it, so the residual by minus as much.
        rel = (point - s.centre) * 1e3  # mm
        D = np.zeros((n, m, 3, 6))
        D[..., :3] = -se3.hat(rel)  # ω × rel
        D[..., 3:] = np.eye(3)
        J_phantom = -np.einsum("nmri,nmij->nmrj", W, D).reshape(n, m * r, 6)
        # The pixel scales: a dot's lateral (axial) coordinate stretched.
        S = R_us[..., :, :2] * (x_us[..., None, :2] * 1e3)
        J_scale = np.einsum("nmri,nmij->nmrj", W, S).reshape(n, m * r, 2)
        K = np.einsum("nmri,nmij->nmrj", W, R_us[..., :, :2] * shared_sd).reshape(n, m * r, 2)
        parts.append((J_theta, J_phantom, J_scale, K, np.full(n, s.index)))
    J_phantom = np.concatenate([q[1] for q in parts])
    # Only the directions of the phantom's pose the wires' constraints see (a lone wire's
    # slide along and turn about itself are exactly null about its centre).
    w, V = np.linalg.eigh(np.einsum("nri,nrj->ij", J_phantom, J_phantom))
    basis = V[:, w > 1e-9 * w.max()]
    return Candidates.from_rows(
        np.concatenate([q[0] for q in parts]),
        np.concatenate([J_phantom @ basis, np.concatenate([q[2] for q in parts])], axis=2),
        np.concatenate([q[4] for q in parts]),
        shared=np.concatenate([q[3] for q in parts]),
    )
