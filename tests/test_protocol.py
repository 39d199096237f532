"""The acquisition plan and its checks, with the twin's robot."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from calib import se3
from calib.acquisition.planning import SweepPose, paper_poses
from calib.acquisition.protocol import (
    PlannedSweep,
    ProtocolConfig,
    acquire,
    check_plan,
    facing_pose,
    plan_sweeps,
)
from calib.errors import CollisionError, UnreachablePoseError
from twin.phantoms import PhantomConfig
from twin.robot import RobotConfig
from twin.tools import ToolsConfig
from twin.world import build_twin

MM = 1e-3


def twin():
    r = np.random.default_rng(0).spawn(3)
    return build_twin(RobotConfig(dh_error_scale=0), ToolsConfig(), PhantomConfig(), *r)


def test_plan_is_the_papers_45_sweeps():
    t = twin()
    cfg = ProtocolConfig()
    T_ee_us = t.truth.T_ee_us
    centre = t.truth.landmarks_base["sphere_1"]
    taught = facing_pose(centre, 0.02) @ se3.invert(T_ee_us)
    plan = plan_sweeps("sphere_1", taught, T_ee_us, cfg)
    assert len(plan) == 45
    assert {p.pose for p in plan} == set(paper_poses(10.0, 3.0))
    assert {p.pose.rotation_deg for p in plan} == {
        (sx * 10.0, sy * 10.0, sz * 10.0) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)
    } | {(0.0, 0.0, 0.0)}
    for p in plan:
        T_us = p.T_base_ee @ T_ee_us
        assert len(T_us) == 21
        # 1 mm steps along the image's elevational axis, ±10 mm.
        steps = np.diff(T_us[:, :3, 3], axis=0)
        np.testing.assert_allclose(np.linalg.norm(steps, axis=1), 1 * MM, atol=1e-12)
        np.testing.assert_allclose(steps / MM, np.tile(T_us[0, :3, 2], (20, 1)), atol=1e-9)
        # The sphere stays on the image plane region near its target depth.
        p_us = se3.apply(se3.invert(T_us[10]), centre)
        assert (
            abs(p_us[2]) < 1e-9 and np.hypot(p_us[0], p_us[1] - 0.02) <= 3 * np.sqrt(2) * MM + 1e-9
        )
    # The orientations are the nominal one and the (±10°)³ extrinsic x-y-z corners.
    corners = [np.zeros(3)] + [10.0 * np.array(s) for s in itertools.product((-1, 1), repeat=3)]
    expected = sorted(
        np.degrees(se3.rotation_angle(np.eye(3), se3.matrix_from_euler(np.radians(c))))
        for c in corners
    )
    got = sorted(
        np.degrees(se3.rotation_angle(plan[0].T_base_ee[10], p.T_base_ee[10]))
        for p in plan
        if (p.pose.lateral_mm, p.pose.axial_mm) == (0.0, 0.0)
    )
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_check_plan_names_the_failing_pose():
    t = twin()
    T_ee_us = t.truth.T_ee_us
    centre = t.truth.landmarks_base["sphere_1"]
    # Taught so deep that the probe would sit inside the sphere.
    taught = facing_pose(centre, 0.002) @ se3.invert(T_ee_us)
    cfg = ProtocolConfig(target_depth_mm=2.0)
    with pytest.raises(CollisionError, match=r"sphere_1 sweep \d+ frame \d+ .* into sphere_1"):
        check_plan(t.robot, plan_sweeps("sphere_1", taught, T_ee_us, cfg))
    far = se3.make(np.eye(3), [0.9, 0.0, 0.1]) @ taught
    with pytest.raises(UnreachablePoseError, match=r"sphere_1 sweep 0 frame 0"):
        check_plan(t.robot, plan_sweeps("sphere_1", far, T_ee_us, ProtocolConfig()))


def test_parallel_sweeps_share_one_travel_direction():
    from calib.acquisition.protocol import (
        ProtocolConfig,
        facing_pose,
        plan_parallel_sweeps,
        plan_sweeps,
    )

    cfg = ProtocolConfig()
    X = se3.make(se3.matrix_from_euler(np.radians([91.0, -0.8, 1.5])), [0.8e-3, -1.2e-3, 0.158])
    taught = facing_pose([0.3, 0.0, 0.045], 0.02) @ se3.invert(X)
    ridge = np.array([1.0, 0.0, 0.0])
    plan = plan_parallel_sweeps("ridge", taught, X, cfg, travel=ridge)
    sphere_like = plan_sweeps("ridge", taught, X, cfg)
    assert len(plan) == 45
    for p, q in zip(plan, sphere_like, strict=True):
        t = p.T_base_ee[:, :3, 3]
        steps = np.diff(t, axis=0)
        # Every frame step is 1 mm along the ridge, whatever the probe's orientation.
        np.testing.assert_allclose(steps, np.tile(ridge * 1e-3, (len(steps), 1)), atol=1e-12)
        # Orientation fixed within a sweep, and the sphere protocol's pose at mid-sweep.
        np.testing.assert_allclose(p.T_base_ee[:, :3, :3], p.T_base_ee[:1, :3, :3].repeat(21, 0))
        np.testing.assert_allclose(p.T_base_ee[10], q.T_base_ee[10], atol=1e-12)
    # The starting poses differ in position and orientation.
    R = np.array([p.T_base_ee[10][:3, :3] for p in plan])
    assert len({tuple(np.round(r.ravel(), 6)) for r in R}) == 9


def test_an_interrupted_sweep_leaves_a_deferred_imager_clean():
    """A deferred imager (the twin's) notes frames and forms them after the sweep; when a
    move fails mid-sweep, the frames noted so far are formed and dropped, so the next
    sweep holds only its own frames."""
    from calib.acquisition.protocol import DeferredImager
    from calib.records import UsFrame

    class Reading:
        def __init__(self):
            self.q = np.zeros(6)
            self.T_base_ee = np.eye(4)

    class Robot:
        def __init__(self, fail_at=None):
            self.calls, self.fail_at = 0, fail_at

        def move_to(self, T, label=""):
            self.calls += 1
            if self.calls == self.fail_at:
                raise CollisionError(f"moving to {label} hits the tank")
            return Reading()

    class Imager:
        def __init__(self):
            self.noted, self.developed = 0, []

        def grab(self):  # pragma: no cover - the deferred path is taken
            raise AssertionError("grab")

        def capture(self):
            self.noted += 1

        def develop(self):
            frames = [
                UsFrame(np.full((4, 5), k, np.uint8), (1e-4, 1e-4)) for k in range(self.noted)
            ]
            self.developed.append(self.noted)
            self.noted = 0
            return frames

    imager = Imager()
    assert isinstance(imager, DeferredImager)
    sweep = PlannedSweep("sphere_1", 0, SweepPose(), np.repeat(np.eye(4)[None], 5, axis=0))
    with pytest.raises(CollisionError, match="frame 2"):
        acquire(Robot(fail_at=3), imager, [sweep])
    assert imager.developed == [2] and imager.noted == 0
    (done,) = acquire(Robot(), imager, [sweep])
    assert done.images.shape == (5, 4, 5) and imager.developed == [2, 5]


def test_a_large_turn_between_sweeps_passes_through_transits():
    from calib.acquisition.protocol import transit

    T0 = se3.make(np.eye(3), [0.3, 0.1, 0.2])
    T1 = se3.make(se3.matrix_from_euler(np.radians([70.0, 0.0, 60.0])), [0.32, 0.08, 0.25])
    path = transit(T0, T1, 40.0)
    angle = np.degrees(se3.rotation_angle(T0, T1))
    assert len(path) == int(np.ceil(angle / 40.0)) - 1 >= 1
    stops = [T0, *path, T1]
    steps = [np.degrees(se3.rotation_angle(a, b)) for a, b in itertools.pairwise(stops)]
    assert max(steps) <= 40.0 + 1e-9 and np.isclose(sum(steps), angle)
    assert len(transit(T0, T0 @ se3.make(np.eye(3), [0.01, 0, 0]), 40.0)) == 0
    # The paper's plan turns at most 35° between sweeps: no transits, as before.
    plan = plan_sweeps("sphere_1", T0, np.eye(4), ProtocolConfig())
    assert all(len(s.approach) == 0 for s in plan)
