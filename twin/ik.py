"""Inverse kinematics of a UR arm: all closed-form branches, refined for any DH table.

The controller of the twin does what a UR controller does for ``moveL``: solve the
inverse kinematics with *its* model (the nominal table) and pick the solution closest
to the current configuration. The twin also needs IK of the *true* arm (to put the true
stylus tip on a true vertex), whose perturbed table breaks the closed form's structural
assumptions; there each closed-form branch of the nearest UR-structured table is followed
onto the full table by a fixed-point iteration of closed-form solves (see ``_refine``).

The closed form is written here because it must follow our DH tables (UR3, UR3e, any
nominal values) and return all eight branches; the IK packages on PyPI hard-code one
arm's constants or need a compiler. Derivation: K. P. Hawkins, "Analytic inverse
kinematics for the Universal Robots UR-5/UR-10 arms" (2013).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib import se3
from calib.dh import DHTable, forward_kinematics
from calib.errors import UnreachablePoseError

__all__ = [
    "JOINT_LIMITS_RAD",
    "describe_pose",
    "ik_solutions",
    "is_ur_structured",
    "solve_ik",
]

Array = NDArray[np.float64]

#: UR3 / UR3e joint ranges: ±360° on every joint (the UR3's wrist 3 is unlimited; the
#: controller still works in ±360°).
JOINT_LIMITS_RAD: tuple[float, float] = (-2 * np.pi, 2 * np.pi)

# Residual (position in m, rotation in rad) below which a refined solution counts as exact.
_IK_TOL = 1e-10
# |sin θ5| below this is the wrist singularity: θ6 is then free and kept at its seed.
_WRIST_SINGULAR = 1e-9
# How far a cosine may leave [-1, 1] in the structured table and still seed a refinement.
_SEED_SLACK = 0.1
_REFINE_ITERATIONS = 60


def describe_pose(T: ArrayLike) -> str:
    """One-line description of a pose for error messages: position in mm, rotvec in deg."""
    pose = se3.pose6_from_matrix(T)
    xyz = ", ".join(f"{1e3 * v:.1f}" for v in pose[:3])
    rv = ", ".join(f"{np.degrees(v):.1f}" for v in pose[3:])
    return f"(xyz [{xyz}] mm, rotvec [{rv}] deg)"


@functools.lru_cache(maxsize=64)
def is_ur_structured(table: DHTable, tol: float = 1e-12) -> bool:
    """True when the table has the UR geometry the closed form assumes."""
    p = table.as_array()
    alpha_ur = np.array([np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0])
    return bool(
        np.all(np.abs(p[:, 3] - alpha_ur) < tol)
        and np.all(np.abs(p[[0, 3, 4, 5], 2]) < tol)
        and np.all(np.abs(p[[1, 2], 1]) < tol)
    )


@functools.lru_cache(maxsize=64)
def _as_array(table: DHTable) -> Array:
    return table.as_array()


def _link(theta: float, d: float, a: float, alpha: float) -> Array:
    """One DH link transform for scalars (the closed form calls it 28 times per pose;
    :func:`calib.dh.link_transform` broadcasts arrays and costs ~10× more per call)."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def _invert(T: Array) -> Array:
    """Inverse of one rigid transform."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def _closed_form(table: DHTable, T: Array, slack: float = 1e-12) -> tuple[Array, list[str]]:
    """All closed-form branches (k, 6) for a UR-structured reading of ``table``.

    Returns the solutions (DH joint angles minus the table's theta offsets) and the
    reasons branches failed, for the error message when none survive. ``slack`` lets a
    cosine exceed 1 by that much and be clipped: seeds for a perturbed table may sit just
    outside the structured table's workspace while the true one reaches them.
    """
    p = _as_array(table)
    d1, d4, d5, d6 = p[0, 1], p[3, 1], p[4, 1], p[5, 1]
    a2, a3 = p[1, 2], p[2, 2]
    reasons: list[str] = []
    solutions: list[Array] = []

    p05 = T[:3, 3] - d6 * T[:3, 2]  # wrist centre (origin of frame 5)
    r05 = np.hypot(p05[0], p05[1])
    if r05 * (1.0 + slack) < abs(d4):
        return np.empty((0, 6)), [
            f"the wrist centre is {1e3 * r05:.1f} mm from the base axis, closer than the "
            f"shoulder offset d4 = {1e3 * abs(d4):.1f} mm"
        ]
    phi = np.arctan2(p05[1], p05[0])
    psi = np.arccos(np.clip(d4 / max(r05, abs(d4)), -1.0, 1.0))
    T_inv = _invert(T)
    for th1 in (phi + psi + np.pi / 2, phi - psi + np.pi / 2):
        s1, c1 = np.sin(th1), np.cos(th1)
        c5 = (T[0, 3] * s1 - T[1, 3] * c1 - d4) / d6
        if abs(c5) > 1.0 + slack:
            reasons.append("the flange cannot be oriented there (wrist 2 out of range)")
            continue
        th5_base = np.arccos(np.clip(c5, -1.0, 1.0))
        for th5 in (th5_base, -th5_base):
            s5 = np.sin(th5)
            if abs(s5) < _WRIST_SINGULAR:
                th6 = 0.0  # wrist singularity: θ6 is free; refinement/caller keep it
            else:
                X, Y = T_inv[:3, 0], T_inv[:3, 1]
                th6 = np.arctan2((-X[1] * s1 + Y[1] * c1) / s5, (X[0] * s1 - Y[0] * c1) / s5)
            A1 = _link(th1, d1, 0.0, np.pi / 2)
            A5 = _link(th5, d5, 0.0, -np.pi / 2)
            A6 = _link(th6, d6, 0.0, 0.0)
            T14 = _invert(A1) @ T @ _invert(A5 @ A6)
            # Joints 2 and 3 rotate about z1: a planar two-link arm in the x1-y1 plane
            # (the d4 offset lies along z1 and drops out).
            px, py = T14[0, 3], T14[1, 3]
            r14 = np.hypot(px, py)
            c3 = (r14**2 - a2**2 - a3**2) / (2 * a2 * a3)
            if abs(c3) > 1.0 + slack:
                reasons.append(
                    f"the elbow cannot span {1e3 * r14:.1f} mm "
                    f"(upper arm + forearm reach {1e3 * (abs(a2) + abs(a3)):.1f} mm)"
                )
                continue
            th3_base = np.arccos(np.clip(c3, -1.0, 1.0))
            for th3 in (th3_base, -th3_base):
                th2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(th3), a2 + a3 * np.cos(th3))
                A2 = _link(th2, 0.0, a2, 0.0)
                A3 = _link(th3, 0.0, a3, 0.0)
                T34 = _invert(A2 @ A3) @ T14
                th4 = np.arctan2(T34[1, 0], T34[0, 0])
                solutions.append(np.array([th1, th2, th3, th4, th5, th6]) - p[:, 0])
    return _wrap(np.array(solutions).reshape(-1, 6)), reasons


def _ur_structured_part(table: DHTable) -> DHTable:
    """The nearest UR-structured table: keep d1, a2, a3, d4, d5, d6 and theta offsets."""
    p = table.as_array().copy()
    p[:, 3] = [np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0]
    p[[0, 3, 4, 5], 2] = 0.0
    p[[1, 2], 1] = 0.0
    return DHTable.from_array(p, name=table.name)


def _wrap(q: Array) -> Array:
    """Angles wrapped into [−π, π)."""
    return (q + np.pi) % (2 * np.pi) - np.pi


def _seeds(table: DHTable, T: Array) -> tuple[Array, list[str]]:
    """Closed-form branches: exact for a UR-structured table, seeds for refinement else."""
    if is_ur_structured(table):
        return _closed_form(table, T)
    return _closed_form(_ur_structured_part(table), T, slack=_SEED_SLACK)


def _refine(table: DHTable, q0: Array, T_target: Array) -> Array | None:
    """Follow one closed-form branch onto the full (perturbed) table; None if it fails.

    Fixed-point iteration on the target: with ``S`` the structured table and
    ``E(q) = FK(q)^-1 · FK_S(q)`` (a small flange-local error), solve the structured IK
    for ``T · E(q_k)`` on the branch nearest ``q_k``. A fixed point satisfies
    ``FK(q) = T``. Each step is a closed-form solve, so the branch is kept and the
    iteration converges linearly at the (small) rate of the DH deltas.
    """
    structured = _ur_structured_part(table)
    q = q0
    for _ in range(_REFINE_ITERATIONS):
        T_q = forward_kinematics(table, q)
        err = se3.log(se3.invert(T_target) @ T_q)
        if np.max(np.abs(err)) < _IK_TOL:
            return q
        E = se3.invert(T_q) @ forward_kinematics(structured, q)
        branches, _ = _closed_form(structured, T_target @ E, slack=_SEED_SLACK)
        if len(branches) == 0:
            return None
        branches = _shift_near(branches, q, (-np.inf, np.inf))
        q = branches[np.argmin(np.linalg.norm(branches - q, axis=1))]
    return None


def ik_solutions(table: DHTable, T_base_ee: ArrayLike, pose_label: str = "") -> Array:
    """All inverse-kinematics solutions (k ≤ 8, 6), radians in (−π, π].

    Raises
    ------
    UnreachablePoseError
        With the pose (and ``pose_label``) and why no branch exists.
    """
    T = np.asarray(T_base_ee, dtype=float)
    seeds, reasons = _seeds(table, T)
    if not is_ur_structured(table):
        refined = [_refine(table, q0, T) for q0 in seeds]
        seeds = _wrap(np.array([q for q in refined if q is not None]).reshape(-1, 6))
        if len(seeds) == 0 and not reasons:
            reasons = ["the refinement on the full DH table did not converge"]
    if len(seeds) == 0:
        label = f"{pose_label} " if pose_label else ""
        why = "; ".join(dict.fromkeys(reasons))
        raise UnreachablePoseError(f"pose {label}{describe_pose(T)} is unreachable: {why}")
    return seeds


@functools.lru_cache(maxsize=4096)
def _cached_solutions(table: DHTable, T_bytes: bytes, pose_label: str) -> Array:
    """:func:`ik_solutions` of a pose given as bytes, memoised: a plan checks every frame
    pose before moving to the same poses (the controller's branch choice stays per call)."""
    out = ik_solutions(table, np.frombuffer(T_bytes).reshape(4, 4), pose_label)
    out.setflags(write=False)
    return out


def solve_ik(
    table: DHTable,
    T_base_ee: ArrayLike,
    q_near: ArrayLike,
    limits: tuple[float, float] = JOINT_LIMITS_RAD,
    pose_label: str = "",
) -> Array:
    """The IK solution closest to ``q_near`` within joint limits, as a controller picks it.

    Each branch is shifted by multiples of 2π joint by joint to lie nearest to
    ``q_near`` inside ``limits``; the branch with the smallest joint-space distance wins.

    Returns
    -------
    q : (6,) float, radians
    """
    q_near = np.asarray(q_near, dtype=float)
    T = np.asarray(T_base_ee, dtype=float)
    label = f"{pose_label} " if pose_label else ""
    if is_ur_structured(table):
        candidates = _cached_solutions(table, T.tobytes(), pose_label)
    else:
        # A controller needs only the nearest branch that lands: refine seeds in order of
        # distance instead of all eight.
        seeds, reasons = _seeds(table, T)
        order = np.argsort(np.linalg.norm(_shift_near(seeds, q_near, limits) - q_near, axis=1))
        candidates = np.empty((0, 6))
        for k in order:
            q = _refine(table, seeds[k], T)
            if q is not None and _within(_shift_near(q[None], q_near, limits), limits).all():
                candidates = _wrap(q[None])
                break
        if len(candidates) == 0:
            why = "; ".join(dict.fromkeys(reasons)) or "no IK branch converges within the limits"
            raise UnreachablePoseError(f"pose {label}{describe_pose(T)} is unreachable: {why}")
    shifted = _shift_near(candidates, q_near, limits)
    ok = _within(shifted, limits)
    if not np.any(ok):
        lo, hi = limits
        raise UnreachablePoseError(
            f"pose {label}{describe_pose(T)} is unreachable: every IK branch "
            f"violates the joint limits [{np.degrees(lo):.0f}°, {np.degrees(hi):.0f}°]"
        )
    shifted = shifted[ok]
    return shifted[np.argmin(np.linalg.norm(shifted - q_near, axis=1))]


def _shift_near(q: Array, q_near: Array, limits: tuple[float, float] = JOINT_LIMITS_RAD) -> Array:
    """Shift each joint by the multiple of 2π that brings it nearest ``q_near``, and by
    one more turn where that leaves the limits; (k, 6)."""
    lo, hi = limits
    shifted = q + 2 * np.pi * np.round((q_near - q) / (2 * np.pi))
    shifted = np.where(shifted > hi, shifted - 2 * np.pi, shifted)
    return np.where(shifted < lo, shifted + 2 * np.pi, shifted)


def _within(q: Array, limits: tuple[float, float]) -> Array:
    """(k,) bool: every joint of each row inside the limits."""
    lo, hi = limits
    return np.all((q >= lo) & (q <= hi), axis=-1)
