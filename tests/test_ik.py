"""Inverse kinematics: closed-form round trips, branch choice, limits, errors."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.dh import NOMINAL_TABLES, forward_kinematics
from calib.errors import UnreachablePoseError
from twin.ik import ik_solutions, is_ur_structured, solve_ik

from .conftest import perturbed_table

N_POSES = 1000
TOL = 1e-9


def pose_error(table, q, T):
    T_q = forward_kinematics(table, q)
    return max(se3.translation_distance(T_q, T), se3.rotation_angle(T_q, T))


@pytest.mark.parametrize("model", ["ur3", "ur3e"])
@pytest.mark.slow
def test_round_trip_on_random_reachable_poses(rng, model):
    table = NOMINAL_TABLES[model]
    assert is_ur_structured(table)
    worst_q = worst_pose = 0.0
    for q in rng.uniform(-np.pi, np.pi, (N_POSES, 6)):
        T = forward_kinematics(table, q)
        q_back = solve_ik(table, T, q)
        worst_q = max(worst_q, np.max(np.abs(q_back - q)))
        worst_pose = max(worst_pose, max(pose_error(table, s, T) for s in ik_solutions(table, T)))
    assert worst_q < TOL
    assert worst_pose < TOL


def test_eight_branches_in_general_position():
    table = NOMINAL_TABLES["ur3"]
    q = np.radians([20, -80, -100, -90, 80, 10])
    sols = ik_solutions(table, forward_kinematics(table, q))
    assert len(sols) == 8
    assert len({tuple(np.round(s, 6)) for s in sols}) == 8


def test_picks_branch_nearest_current_configuration():
    table = NOMINAL_TABLES["ur3"]
    q = np.radians([20, -80, -100, -90, 80, 10])
    T = forward_kinematics(table, q)
    for other in ik_solutions(table, T):
        np.testing.assert_allclose(solve_ik(table, T, other + 0.05), other, atol=TOL)


def test_joint_shift_by_full_turn_follows_current_configuration():
    table = NOMINAL_TABLES["ur3"]
    q = np.radians([20, -80, -100, -90, 80, 10])
    q_near = q.copy()
    q_near[5] -= 2 * np.pi  # wrist 3 one turn back (still within ±360°)
    q_back = solve_ik(table, forward_kinematics(table, q), q_near)
    assert q_back[5] == pytest.approx(q[5] - 2 * np.pi, abs=TOL)
    np.testing.assert_allclose(q_back[:5], q[:5], atol=TOL)


def test_perturbed_table_solutions_are_exact(rng):
    table = perturbed_table(rng)
    assert not is_ur_structured(table)
    checked = 0
    for q in rng.uniform(-np.pi, np.pi, (400, 6)):
        # Away from the folded-elbow and wrist singularities, where branches merge.
        if abs(q[2]) > 2.6 or abs(np.sin(q[4])) < 0.2:
            continue
        T = forward_kinematics(table, q)
        assert pose_error(table, solve_ik(table, T, q), T) < TOL
        checked += 1
    assert checked > 100


def test_unreachable_pose_names_pose_and_reason():
    T = se3.make(np.eye(3), [0.9, 0.0, 0.2])
    with pytest.raises(
        UnreachablePoseError,
        match=r"sphere_9 .*xyz \[900\.0, 0\.0, 200\.0\] mm.*"
        r"elbow cannot span",
    ):
        solve_ik(NOMINAL_TABLES["ur3"], T, np.zeros(6), pose_label="sphere_9")


def test_joint_limits_are_enforced():
    table = NOMINAL_TABLES["ur3"]
    q = np.radians([20, -80, -100, -90, 80, 10])
    with pytest.raises(UnreachablePoseError, match="joint limits"):
        solve_ik(table, forward_kinematics(table, q), q, limits=(-0.1, 0.1))


def test_many_poses_at_once_match_one_by_one(rng):
    """The vectorised closed form a plan is checked with gives, pose by pose, the same
    branches (bit for bit) and the same failure reasons as a single pose."""
    from twin.ik import _closed_form, _closed_form_many

    table = NOMINAL_TABLES["ur3"]
    T = np.array([forward_kinematics(table, q) for q in rng.uniform(-np.pi, np.pi, (200, 6))])
    far = T[:20].copy()
    far[:, :3, 3] = [0.9, 0.0, 0.2]  # beyond the elbow's reach (UR3: 0.5 m)
    near_axis = T[:20].copy()
    # The wrist centre on the base axis, inside the shoulder offset.
    near_axis[:, :2, 3] = table.as_array()[5, 1] * near_axis[:, :2, 2]
    poses = np.concatenate([T, far, near_axis])
    branches = _closed_form_many(table, poses)
    # Every random pose has branches, some all eight, some only part (reasons compared).
    all_eight = branches.ok[:200].all(axis=1)
    assert branches.ok[:200].any(axis=1).all() and 0 < all_eight.sum() < 200
    assert not branches.ok[200:220].any() and not branches.ok[220:].any()
    for i, T_i in enumerate(poses):
        single, reasons = _closed_form(table, T_i)
        np.testing.assert_array_equal(branches.of(i), single)
        assert branches.reasons(i) == reasons
    assert "elbow cannot span" in branches.reasons(200)[0]
    assert "closer than the shoulder offset" in branches.reasons(220)[0]


def test_poses_solved_ahead_are_what_solve_ik_returns(rng):
    from twin.ik import solve_poses

    table = NOMINAL_TABLES["ur3e"]
    qs = rng.uniform(-np.pi, np.pi, (50, 6))
    T = np.array([forward_kinematics(table, q) for q in qs])
    before = [solve_ik(table, T_i + 0.0, q) for T_i, q in zip(T, qs, strict=True)]
    solve_poses(table, T)
    after = [solve_ik(table, T_i, q) for T_i, q in zip(T, qs, strict=True)]
    np.testing.assert_array_equal(before, after)
    np.testing.assert_allclose(after, qs, atol=TOL)
