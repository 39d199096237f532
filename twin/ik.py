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
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib import se3
from calib.dh import DHTable, forward_kinematics, link_transform
from calib.errors import UnreachablePoseError

__all__ = [
    "JOINT_LIMITS_RAD",
    "describe_pose",
    "ik_solutions",
    "is_ur_structured",
    "solve_ik",
    "solve_poses",
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


@dataclass(frozen=True)
class _Branches:
    """The closed form's eight branches for each of n poses: ``q`` (n, 8, 6) (DH joint
    angles minus the table's theta offsets, wrapped), ``ok`` (n, 8) which exist, and what
    the failures' messages need."""

    q: Array
    ok: NDArray[np.bool_]
    r05: Array  # (n,) the wrist centre's distance from the base axis
    bad_r05: NDArray[np.bool_]  # (n,) closer than the shoulder offset
    bad_c5: NDArray[np.bool_]  # (n, 2) per shoulder branch: wrist 2 out of range
    r14: Array  # (n, 2, 2) per shoulder and wrist branch: the elbow's span
    bad_c3: NDArray[np.bool_]  # (n, 2, 2)
    d4: float
    reach: float  # |a2| + |a3|

    def of(self, i: int) -> Array:
        """The existing branches of pose i, (k ≤ 8, 6), in branch order."""
        return self.q[i][self.ok[i]]

    def reasons(self, i: int) -> list[str]:
        """Why branches of pose i fail, in branch order (an error message's words)."""
        if self.bad_r05[i]:
            return [
                f"the wrist centre is {1e3 * self.r05[i]:.1f} mm from the base axis, closer "
                f"than the shoulder offset d4 = {1e3 * abs(self.d4):.1f} mm"
            ]
        out = []
        for s in range(2):
            if self.bad_c5[i, s]:
                out.append("the flange cannot be oriented there (wrist 2 out of range)")
                continue
            out += [
                f"the elbow cannot span {1e3 * self.r14[i, s, w]:.1f} mm "
                f"(upper arm + forearm reach {1e3 * self.reach:.1f} mm)"
                for w in range(2)
                if self.bad_c3[i, s, w]
            ]
        return out


def _closed_form_many(table: DHTable, T: Array, slack: float = 1e-12) -> _Branches:
    """All closed-form branches of a UR-structured reading of ``table`` for the poses
    ``T`` (n, 4, 4), vectorised over the poses: a plan's frames are solved in one call
    (numpy calls cost ≈ 0.15 ms per pose one by one; a 945-pose plan ≈ 6 ms at once).

    ``slack`` lets a cosine exceed 1 by that much and be clipped: seeds for a perturbed
    table may sit just outside the structured table's workspace while the true one
    reaches them.
    """
    p = _as_array(table)
    d1, d4, d5, d6 = p[0, 1], p[3, 1], p[4, 1], p[5, 1]
    a2, a3 = p[1, 2], p[2, 2]
    n = len(T)
    q = np.zeros((n, 2, 2, 2, 6))
    ok = np.zeros((n, 2, 2, 2), dtype=bool)
    bad_c5 = np.zeros((n, 2), dtype=bool)
    bad_c3 = np.zeros((n, 2, 2), dtype=bool)
    r14_all = np.zeros((n, 2, 2))
    p05 = T[:, :3, 3] - d6 * T[:, :3, 2]  # wrist centre (origin of frame 5)
    r05 = np.hypot(p05[:, 0], p05[:, 1])
    bad_r05 = r05 * (1.0 + slack) < abs(d4)
    phi = np.arctan2(p05[:, 1], p05[:, 0])
    psi = np.arccos(np.clip(d4 / np.maximum(r05, abs(d4)), -1.0, 1.0))
    T_inv = se3.invert(T)
    X, Y = T_inv[:, :3, 0], T_inv[:, :3, 1]
    for i, th1 in enumerate((phi + psi + np.pi / 2, phi - psi + np.pi / 2)):
        s1, c1 = np.sin(th1), np.cos(th1)
        c5 = (T[:, 0, 3] * s1 - T[:, 1, 3] * c1 - d4) / d6
        bad_c5[:, i] = ~bad_r05 & (np.abs(c5) > 1.0 + slack)
        th5_base = np.arccos(np.clip(c5, -1.0, 1.0))
        A1_inv = se3.invert(link_transform(th1, d1, 0.0, np.pi / 2))
        for j, th5 in enumerate((th5_base, -th5_base)):
            s5 = np.sin(th5)
            # At the wrist singularity θ6 is free: 0 (the refinement or the caller keep it).
            singular = np.abs(s5) < _WRIST_SINGULAR
            s5 = np.where(singular, 1.0, s5)
            th6 = np.where(
                singular,
                0.0,
                np.arctan2((-X[:, 1] * s1 + Y[:, 1] * c1) / s5, (X[:, 0] * s1 - Y[:, 0] * c1) / s5),
            )
            A56 = link_transform(th5, d5, 0.0, -np.pi / 2) @ link_transform(th6, d6, 0.0, 0.0)
            T14 = A1_inv @ T @ se3.invert(A56)
            # Joints 2 and 3 rotate about z1: a planar two-link arm in the x1-y1 plane
            # (the d4 offset lies along z1 and drops out).
            px, py = T14[:, 0, 3], T14[:, 1, 3]
            r14_all[:, i, j] = r14 = np.hypot(px, py)
            c3 = (r14**2 - a2**2 - a3**2) / (2 * a2 * a3)
            bad_c3[:, i, j] = ~bad_r05 & ~bad_c5[:, i] & (np.abs(c3) > 1.0 + slack)
            th3_base = np.arccos(np.clip(c3, -1.0, 1.0))
            for k, th3 in enumerate((th3_base, -th3_base)):
                th2 = np.arctan2(py, px) - np.arctan2(a3 * np.sin(th3), a2 + a3 * np.cos(th3))
                A23 = link_transform(th2, 0.0, a2, 0.0) @ link_transform(th3, 0.0, a3, 0.0)
                T34 = se3.invert(A23) @ T14
                th4 = np.arctan2(T34[:, 1, 0], T34[:, 0, 0])
                q[:, i, j, k] = np.stack([th1, th2, th3, th4, th5, th6], axis=1) - p[:, 0]
                ok[:, i, j, k] = ~bad_r05 & ~bad_c5[:, i] & ~bad_c3[:, i, j]
    return _Branches(
        _wrap(q.reshape(n, 8, 6)),
        ok.reshape(n, 8),
        r05,
        bad_r05,
        bad_c5,
        r14_all,
        bad_c3,
        float(d4),
        float(abs(a2) + abs(a3)),
    )


def _closed_form(table: DHTable, T: Array, slack: float = 1e-12) -> tuple[Array, list[str]]:
    """All closed-form branches (k, 6) of one pose, and the reasons branches failed (for
    the error message when none survive); see :func:`_closed_form_many`."""
    branches = _closed_form_many(table, np.asarray(T, dtype=float)[None], slack)
    return branches.of(0), branches.reasons(0)


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


# Closed-form branches of poses already solved, by (table, pose bytes): a plan's frame
# poses are checked before any motion and then moved to. Least recently used first out.
_SOLVED: OrderedDict[tuple[DHTable, bytes], Array] = OrderedDict()
_SOLVED_MAX = 16384


def _remember(table: DHTable, key: bytes, solutions: Array) -> None:
    solutions.setflags(write=False)
    _SOLVED[(table, key)] = solutions
    _SOLVED.move_to_end((table, key))
    while len(_SOLVED) > _SOLVED_MAX:
        _SOLVED.popitem(last=False)


def _cached_solutions(table: DHTable, T: Array, pose_label: str) -> Array:
    """:func:`ik_solutions` of a UR-structured table, memoised (a pose without a branch
    is not: its error names the pose)."""
    key = T.tobytes()
    out = _SOLVED.get((table, key))
    if out is None:
        out = ik_solutions(table, T, pose_label)
        _remember(table, key, out)
    else:
        _SOLVED.move_to_end((table, key))
    return out


def solve_poses(table: DHTable, T_base_ee: ArrayLike) -> None:
    """Solve many poses of a UR-structured table at once (a plan's frames, in one
    vectorised closed form) and keep their branches for :func:`solve_ik`; poses without a
    branch are left to it (its error names them). Other tables: nothing to do."""
    if not is_ur_structured(table):
        return
    T = np.ascontiguousarray(np.asarray(T_base_ee, dtype=float).reshape(-1, 4, 4))
    branches = _closed_form_many(table, T)
    for i in np.nonzero(branches.ok.any(axis=1))[0]:
        _remember(table, T[i].tobytes(), branches.of(i))


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
        candidates = _cached_solutions(table, T, pose_label)
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
