"""The simulated robot and the scene: controller semantics, ground truth, collisions."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.acquisition.protocol import facing_pose
from calib.dh import forward_kinematics
from calib.errors import CollisionError
from twin.phantoms import PhantomConfig
from twin.robot import PLAN_MARGIN_M, RobotConfig
from twin.tools import ToolsConfig
from twin.world import build_twin

MM = 1e-3


def make(robot=None, tools=None, phantom=None, seed=0):
    r = np.random.default_rng(seed).spawn(3)
    return build_twin(
        robot or RobotConfig(), tools or ToolsConfig(), phantom or PhantomConfig(), *r
    )


def probe_pose_above(twin, name, depth=20 * MM):
    T_base_us = facing_pose(twin.truth.landmarks_base[name], depth)
    return T_base_us @ se3.invert(twin.truth.T_ee_us)


def test_without_errors_report_equals_truth():
    cfg = RobotConfig(dh_error_scale=0, joint_repeatability_deg=0, encoder_noise_deg=0)
    twin = make(cfg)
    T_cmd = probe_pose_above(twin, "sphere_2")
    reading = twin.robot.move_to(T_cmd)
    truth = twin.robot.truth
    assert se3.translation_distance(reading.T_base_ee, T_cmd) < 1e-9
    assert se3.translation_distance(truth.T_base_ee, T_cmd) < 1e-9
    assert se3.rotation_angle(truth.T_base_ee, T_cmd) < 1e-9


def test_controller_reports_nominal_fk_of_encoder_angles_while_true_arm_differs():
    twin = make(RobotConfig())  # paper-like errors
    T_cmd = probe_pose_above(twin, "sphere_1")
    reading = twin.robot.move_to(T_cmd)
    truth = twin.robot.truth
    nominal = RobotConfig().nominal_table
    np.testing.assert_allclose(
        reading.T_base_ee, forward_kinematics(nominal, reading.q), atol=1e-12
    )
    # The controller believes it arrived (encoder noise only) ...
    assert se3.translation_distance(reading.T_base_ee, T_cmd) < 0.1 * MM
    # ... the true flange is elsewhere by the DH errors (mm scale) ...
    assert 0.5 * MM < se3.translation_distance(truth.T_base_ee, T_cmd) < 30 * MM
    # ... and is what the true DH table gives for the true angles.
    np.testing.assert_allclose(
        truth.T_base_ee, forward_kinematics(twin.truth.dh_table, truth.q), atol=1e-12
    )
    # Encoder noise: reported and true angles differ at the configured scale.
    assert 0 < np.max(np.abs(reading.q - truth.q)) < np.radians(0.01)


def test_same_seed_same_truth_and_readings():
    a, b = make(seed=5), make(seed=5)
    T = probe_pose_above(a, "sphere_3")
    ra, rb = a.robot.move_to(T), b.robot.move_to(T)
    np.testing.assert_array_equal(ra.q, rb.q)
    np.testing.assert_array_equal(a.truth.dh_table.as_array(), b.truth.dh_table.as_array())
    c = make(seed=6)
    assert not np.array_equal(c.truth.dh_table.as_array(), a.truth.dh_table.as_array())


def test_explicit_dh_deltas_and_scale():
    cfg = RobotConfig(
        dh_delta_theta_deg=(1, 0, 0, 0, 0, 0),
        dh_delta_d_mm=(0,) * 6,
        dh_delta_a_mm=(0,) * 6,
        dh_delta_alpha_deg=(0,) * 6,
        dh_error_scale=2,
    )
    twin = make(cfg)
    np.testing.assert_allclose(twin.truth.dh_deltas.theta, np.radians([2, 0, 0, 0, 0, 0]))
    assert twin.truth.dh_deltas.a == (0.0,) * 6


def test_home_is_clear_and_probe_above_sphere_is_clear():
    twin = make()
    assert twin.scene.collisions(np.radians(RobotConfig().home_deg)) == []
    q = twin.robot.move_to(probe_pose_above(twin, "sphere_1")).q
    assert twin.scene.collisions(q) == []


def test_probe_pushed_into_sphere_collides():
    twin = make(RobotConfig(dh_error_scale=0))
    # Transducer face 3 mm below the top of sphere 4: the probe body is inside it.
    T = probe_pose_above(twin, "sphere_4", depth=2 * MM)
    with pytest.raises(CollisionError, match=r"probe_body .* mm into sphere_4"):
        twin.robot.move_to(T, "too deep")
    q = twin.robot.move_to(probe_pose_above(twin, "sphere_4")).q
    contacts = twin.scene.collisions(q)
    assert contacts == []


def test_a_plan_keeps_room_for_the_arms_placement_error():
    """A pose is checked where the controller's inverse kinematics put the arm, and the
    move lands off it by the arm's placement error: a pose that leaves less than
    PLAN_MARGIN_M is refused, with the room it leaves; one that leaves more is not."""
    twin = make(RobotConfig(dh_error_scale=0))

    def room(depth):
        q = twin.robot.move_to(probe_pose_above(twin, "sphere_4", depth)).q
        return twin.scene.clearance(q, 0.02)

    # The face's depth above the centre at which the probe would touch the sphere.
    touching = 12 * MM - room(12 * MM)
    assert room(touching + 3 * MM) == pytest.approx(3 * MM, abs=0.05 * MM)
    close = probe_pose_above(twin, "sphere_4", touching + 0.3 * MM)
    with pytest.raises(CollisionError, match=r"would leave 0\.[23]\d mm .* keeps 0\.5 mm"):
        twin.robot.check_pose(close, "close")
    twin.robot.check_pose(probe_pose_above(twin, "sphere_4", touching + PLAN_MARGIN_M + 0.2 * MM))


def test_a_taught_pose_in_the_phantom_says_which_and_what_leaves_room():
    """Teaching the probe too close above a sphere (the operator's jog into the phantom)
    is one error naming the taught pose and what to change, not a move to bare joint
    angles (seed 603 in gel at a 10 mm target: "moving to joints [...] puts probe_body 0.1
    mm into sphere_2")."""
    from bench.acquire_sim import teach_at

    twin = make(RobotConfig(dh_error_scale=0))
    centre = twin.truth.landmarks_base["sphere_4"]
    with pytest.raises(CollisionError) as caught:
        teach_at(twin, centre, 2 * MM, "taught pose at sphere_4")
    said = str(caught.value)
    assert said.startswith("moving to taught pose at sphere_4 (joints [")
    assert "mm into sphere_4" in said
    assert "cannot be 2 mm above that target" in said and "protocol.target_depth_mm" in said
    teach_at(twin, centre, 20 * MM, "taught pose at sphere_4")  # room enough: no error


def test_arm_into_tank_wall_collides():
    twin = make(RobotConfig(dh_error_scale=0))
    # Arm stretched out horizontally over the tank at shoulder height: the upper arm lies
    # across the near wall's rim.
    contacts = twin.scene.collisions(np.radians([180, 0, 0, -90, 90, 0]))
    assert any(
        c.robot_geom == "link2_a" and c.environment_geom == "tank_wall_xneg" for c in contacts
    )
    # Lifted by 30° it clears the rim.
    assert twin.scene.collisions(np.radians([180, -30, 0, -90, 90, 0])) == []


def test_clearances_measure_the_room_and_a_path_follows_the_arm():
    """The room a pose leaves (MuJoCo's geom distances, up to ``within``): the probe a
    few mm above a sphere has about that much; a probe pushed into it has less than none;
    a pose the controller cannot reach has −inf. Moved through in order, each pose is
    solved from the one before, and everything after an unreachable pose is −inf."""
    twin = make(RobotConfig(dh_error_scale=0))
    above = probe_pose_above(twin, "sphere_4", depth=20 * MM)
    deep = probe_pose_above(twin, "sphere_4", depth=2 * MM)
    far = se3.make(np.eye(3), [2.0, 0.0, 0.5])
    room = twin.robot.clearances(np.array([above, deep, far]), 0.05)
    assert 0 < room[0] <= 0.05 and room[1] < 0 and room[2] == -np.inf
    q0 = twin.robot.read().q
    way = np.array([above, above @ se3.make(np.eye(3), [0, 0, 0.002]), far, above])
    path = twin.robot.path_clearances(way, 0.05, q0)
    assert path[0] == pytest.approx(room[0], abs=1e-9) and np.isfinite(path[1])
    assert np.all(path[2:] == -np.inf)
    assert np.array_equal(twin.robot.read().q, q0)  # nothing moved


def test_clearance_asks_fewer_pairs_and_finds_the_same_distance(monkeypatch):
    """:meth:`SceneModel.clearance` skips the pairs whose bounding spheres are further
    apart than the nearest distance found: on random arm configurations (clear, close and
    overlapping) it returns exactly what asking MuJoCo for every arm/environment pair
    does, asking a fraction of the pairs."""
    import mujoco

    geom_distance, asked = mujoco.mj_geomDistance, []

    def counted(*args):
        asked.append(1)
        return geom_distance(*args)

    twin = make(RobotConfig(dh_error_scale=0))
    scene = twin.scene
    rng = np.random.default_rng(3)
    home = np.radians(RobotConfig().home_deg)
    seen = {"overlap": 0, "close": 0, "clear": 0}
    for k in range(300):
        q = home + rng.normal(0.0, 0.6 if k % 2 else 1.5, 6)
        for within in (0.005, 0.05, 0.5):
            with monkeypatch.context() as m:
                m.setattr(mujoco, "mj_geomDistance", counted)
                got = scene.clearance(q, within)
            every = within
            for g1 in sorted(scene._robot_geoms):
                for g2 in scene._environment_geoms:
                    d = geom_distance(scene.model, scene.data, g1, g2, within, None)
                    every = min(every, float(d))
            assert got == every, (q, within)
        seen["overlap" if every < 0 else "close" if every < 0.05 else "clear"] += 1
    assert min(seen.values()) >= 10, seen
    pairs = len(scene._robot_geoms) * len(scene._environment_geoms)
    assert len(asked) < 0.1 * 900 * pairs, (len(asked) / 900, pairs)


def test_stylus_tool_has_true_tip_site():
    twin = make(tools=ToolsConfig(mounted="stylus"))
    q = np.radians(RobotConfig().home_deg)
    twin.scene.set_q(q)
    T_tip = twin.scene.site_pose("tip")
    p_expected = se3.apply(twin.scene.flange_pose(q), twin.truth.p_ee_tip)
    np.testing.assert_allclose(T_tip[:3, 3], p_expected, atol=1e-12)


def test_robot_and_imager_behave_like_a_robot_with_a_scanner():
    """With no kinematic error the grabbed frame shows sphere 2's cap on the centre line
    at its apparent depth; the imager follows the *true* arm, not the report."""
    from sim_us import MediumConfig, ProbeConfig
    from sim_us.materials import water_speed_m_s
    from twin.imager import SimImager

    twin = make(RobotConfig(dh_error_scale=0, joint_repeatability_deg=0, encoder_noise_deg=0))
    probe = ProbeConfig()
    imager = SimImager(
        twin.robot, twin.truth.T_ee_us, probe, MediumConfig(), np.random.default_rng(1)
    )
    twin.robot.move_to(probe_pose_above(twin, "sphere_2", depth=20 * MM))
    frame = imager.grab().image
    assert frame.shape == probe.image_shape and frame.dtype == np.uint8
    centre = (frame.shape[1] - 1) // 2
    radius_mm = twin.truth.sphere_radii["sphere_2"] / MM
    apparent_mm = (20.0 - radius_mm) * 1540.0 / water_speed_m_s(20.0)
    column = frame[:, centre - 2 : centre + 3].mean(axis=1)
    assert abs(np.argmax(column[:300]) * 0.1 - apparent_mm) <= 0.2
    assert column.max() > 150  # a bright cap
    # The true arm with kinematic error looks elsewhere than the controller believes.
    twin_err = make(RobotConfig(dh_delta_theta_deg=(0, 1.5, 0, 0, 0, 0), dh_error_scale=1))
    imager_err = SimImager(
        twin_err.robot, twin_err.truth.T_ee_us, probe, MediumConfig(), np.random.default_rng(1)
    )
    twin_err.robot.move_to(probe_pose_above(twin_err, "sphere_2", depth=20 * MM))
    moved = imager_err.grab().image[:, centre - 2 : centre + 3].mean(axis=1)
    assert abs(np.argmax(moved[:300]) * 0.1 - apparent_mm) > 1.0


def test_teach_puts_the_true_flange_on_target():
    twin = make()  # paper-like kinematic errors
    T_target = probe_pose_above(twin, "sphere_3")
    reading = twin.robot.teach(T_target)
    assert se3.translation_distance(twin.robot.truth.T_base_ee, T_target) < 0.05 * MM
    # The controller reports a different pose: its nominal view of the same joints.
    assert se3.translation_distance(reading.T_base_ee, T_target) > 0.5 * MM


def _acquire_two_sweeps(overrides: list[str], one_by_one: bool):
    """Two planned sweeps of quick.yaml's sphere 1 with the twin, through ``acquire``;
    ``one_by_one`` hides the imager's deferred capture so every frame is grabbed alone."""
    from bench.acquire_sim import coarse_estimate, make_imager
    from bench.acquire_sim import make_twin as make_scenario_twin
    from bench.config.scenario import load_scenario
    from bench.sessions import dataset_rngs, stage_rngs
    from calib.acquisition.protocol import acquire, plan_sweeps

    sc = load_scenario("scenarios/quick.yaml", overrides, check_reach=False)
    rngs = dataset_rngs(sc, 0)
    twin = make_scenario_twin(sc, rngs["joints"])
    imager = make_imager(sc, twin, rngs["imaging"])
    coarse = coarse_estimate(twin.truth.T_ee_us, sc.calibration, stage_rngs(sc)["calibration"])
    T_face = facing_pose(twin.truth.landmarks_base["sphere_1"], 20 * MM)
    taught = twin.robot.teach(T_face @ se3.invert(twin.truth.T_ee_us), "taught")
    plan = plan_sweeps("sphere_1", taught.T_base_ee, coarse, sc.protocol)[:2]

    class OneByOne:
        def grab(self):
            return imager.grab()

    sweeps = acquire(twin.robot, OneByOne() if one_by_one else imager, plan)
    return np.array([s.images for s in sweeps]), np.array([s.q for s in sweeps])


def test_deferred_capture_renders_the_frames_grab_would():
    """The twin notes each frame's pose and renders a sweep in one call: the same frames
    and joint readings as grabbing frame by frame; with a drifting water temperature the
    sweep renders at its mean temperature (a millikelvin apart), which moves no more than
    the rounding of a few grey levels."""
    batch, q_batch = _acquire_two_sweeps([], one_by_one=False)
    single, q_single = _acquire_two_sweeps([], one_by_one=True)
    np.testing.assert_array_equal(batch, single)
    np.testing.assert_array_equal(q_batch, q_single)
    drift = ["medium.temperature_drift_c_per_h=1.0"]
    batch, _ = _acquire_two_sweeps(drift, one_by_one=False)
    single, _ = _acquire_two_sweeps(drift, one_by_one=True)
    diff = np.abs(batch.astype(int) - single.astype(int))
    assert (diff > 0).mean() < 1e-3 and diff.max() <= 8
