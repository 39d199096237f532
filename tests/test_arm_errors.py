"""Error sources of the real arm beyond its DH table, each against the twin's truth:
off ⇒ identical to the plain twin; on ⇒ the modelled size and direction; a seed ⇒ the
same draws."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bench.acquire_sim import make_twin
from bench.config.scenario import load_scenario
from calib import se3
from calib.acquisition.protocol import acquire, facing_pose, plan_sweeps
from calib.dh import forward_kinematics
from calib.records import UsFrame
from twin.arm_errors import (
    ALUMINIUM_EXPANSION_PER_K,
    HARMONIC_DRIVE_STIFFNESS,
    JointErrors,
    harmonic_drive_twist,
    robot_stream,
    thermal_rise_k,
    thermal_table,
)
from twin.phantoms import PhantomConfig
from twin.robot import RobotConfig
from twin.tools import ToolsConfig, holder_deflection
from twin.touch import SimTouchGuide
from twin.world import build_twin

from .conftest import QUICK

MM = 1e-3
ARCMIN = np.pi / (180 * 60)
#: A move of the arm off its home configuration (radians), clear of the tank.
STEP = np.radians([4.0, 6.0, -5.0, 3.0, 2.0, 10.0])
QUIET = {"joint_repeatability_deg": 0.0, "encoder_noise_deg": 0.0, "dh_error_scale": 0.0}


def make(robot=None, tools=None, seed=0, **quiet):
    """A twin (collision checks off: these tests move the arm freely above the tank)."""
    r = np.random.default_rng(seed).spawn(3)
    twin = build_twin(
        RobotConfig(**(robot or {})),
        ToolsConfig(**(tools or {})),
        PhantomConfig(),
        *r,
        robot_stream(seed),
    )
    twin.robot.check_collisions = False
    return twin


def moves(twin, n=4):
    """Readings, truths and frame poses of a few joint moves (and a second grab)."""
    out = []
    for k in range(n):
        reading = twin.robot.move_joints(twin.robot.home + (k + 1) / n * STEP)
        out.append((reading.q, reading.T_base_ee, twin.robot.truth.T_base_ee))
        out.append((twin.robot.frame_pose(), twin.robot.frame_pose()))
    return out


# ------------------------------------------------------------------------------ off


def test_sources_off_give_the_plain_twin_bit_for_bit():
    twin = make()
    cfg = twin.robot.cfg
    # The plain twin: true = commanded + repeatability, reported = true + encoder noise,
    # both from the joint stream in that order; truth = MuJoCo flange; frame = truth.
    ref = np.random.default_rng(0).spawn(3)[2]
    for k in range(4):
        q_cmd = twin.robot.home + (k + 1) / 4 * STEP
        reading = twin.robot.move_joints(q_cmd)
        q_true = q_cmd + ref.normal(0.0, 1.0, 6) * np.radians(cfg.joint_repeatability_deg)
        q_rep = q_true + ref.normal(0.0, 1.0, 6) * np.radians(cfg.encoder_noise_deg)
        assert np.array_equal(reading.q, q_rep)
        assert np.array_equal(twin.robot.truth.q, q_true)
        assert np.array_equal(twin.robot.truth.T_base_ee, twin.scene.flange_pose(q_true))
        assert np.array_equal(twin.robot.frame_pose(), twin.robot.truth.T_base_ee)
    # The clock runs whether or not anything reads it.
    assert twin.robot.clock_s > 0
    tools = ToolsConfig()
    assert tools.stylus_bending_m == 0
    assert np.array_equal(holder_deflection(np.eye(3)[[1, 2, 0]], tools), np.eye(4))


def test_explicit_zeros_equal_the_defaults():
    zeros = {
        "joint_compliance_scale": 0.0,
        "transmission_error_arcmin": 0.0,
        "lost_motion_arcmin": 0.0,
        "thermal_rise_k": 0.0,
        "residual_vibration_mm": 0.0,
        "stale_frame_probability": 0.0,
        "joint_encoders_output_side": True,
    }
    a, b = moves(make()), moves(make(zeros, {"probe_mass_kg": 0.4}))
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True):
            assert np.array_equal(u, v)


# ---------------------------------------------------------------- pose repeatability


def test_repeatability_doc_conversion_gives_the_datasheet_figure():
    # σ_q = 0.0041° (the doc's CB-series value) must give ISO 9283 RP ≈ ±0.1 mm at
    # the probe's image origin; RP = mean + 3 σ of the distance from the mean position.
    twin = make({"joint_repeatability_deg": 0.0041, "encoder_noise_deg": 0.0})
    T_ee_us = twin.truth.T_ee_us
    P = []
    for _ in range(400):
        twin.robot.move_joints(twin.robot.home)
        P.append((twin.robot.truth.T_base_ee @ T_ee_us)[:3, 3])
    d = np.linalg.norm(np.array(P) - np.mean(P, axis=0), axis=1)
    rp = d.mean() + 3 * d.std()
    assert 0.085 * MM < rp < 0.115 * MM


# ------------------------------------------------------------------- joint compliance


def test_gravity_torque_is_the_derivative_of_potential_energy():
    # qfrc_bias at rest against an independent route: τ_i = ∂V/∂q_i with
    # V = g Σ m z_com (MuJoCo's body masses and centres, finite differences).
    twin = make(tools={"probe_mass_kg": 0.4})
    sm = twin.scene
    m = sm.model

    def potential(q):
        sm.set_q(q)
        return 9.81 * float(np.sum(m.body_mass * sm.data.xipos[:, 2]))

    q = twin.robot.home + STEP
    h = 1e-6
    tau_fd = np.array([(potential(q + h * e) - potential(q - h * e)) / (2 * h) for e in np.eye(6)])
    np.testing.assert_allclose(sm.gravity_torque(q), tau_fd, atol=1e-5)
    # The published masses are in: the shoulder holds ≈ 5–30 N m with the probe on.
    assert 5 < abs(tau_fd[1]) < 30
    # The payload adds m g × its lever at the shoulder.
    bare = make().scene.gravity_torque(q)
    assert abs(sm.gravity_torque(q)[1] - bare[1]) > 0.4 * 9.81 * 0.2


def test_catalogue_twist_curve():
    T1, T2, K1, K2, K3 = HARMONIC_DRIVE_STIFFNESS[20]
    sizes = (20,) * 6
    tau = np.array([0.5 * T1, -T1, 10.0, -30.0, 0.0, T2])
    expect = [
        0.5 * T1 / K1,
        -T1 / K1,
        T1 / K1 + (10 - T1) / K2,
        -(T1 / K1 + (T2 - T1) / K2 + (30 - T2) / K3),
        0.0,
        T1 / K1 + (T2 - T1) / K2,
    ]
    np.testing.assert_allclose(harmonic_drive_twist(tau, sizes), expect, rtol=1e-12)


def test_compliance_sags_the_arm_by_torque_over_stiffness():
    twin = make({**QUIET, "joint_compliance_scale": 1.0}, {"probe_mass_kg": 0.4})
    q = twin.robot.home + STEP
    reading = twin.robot.move_joints(q)
    truth = twin.robot.truth
    # The motors (and their encoders) are at the command; the links lag by τ/K(τ).
    np.testing.assert_allclose(reading.q, q, atol=1e-15)
    expect = -harmonic_drive_twist(twin.scene.gravity_torque(truth.q))
    np.testing.assert_allclose(truth.q - q, expect, atol=1e-12)
    assert 2e-4 < np.max(np.abs(expect)) < 3e-3  # ≈ 1 mrad at the shoulder
    # Gravity wins: the loaded tool goes down, by 0.1–1 mm at the probe.
    T_ee_us = twin.truth.T_ee_us
    rigid = forward_kinematics(twin.truth.dh_table, q) @ T_ee_us
    sagged = truth.T_base_ee @ T_ee_us
    assert -1.0 * MM < sagged[2, 3] - rigid[2, 3] < -0.05 * MM
    # Twice as soft: twice the twist (below the curve's first knee up to the second).
    soft = make({**QUIET, "joint_compliance_scale": 2.0}, {"probe_mass_kg": 0.4})
    soft.robot.move_joints(q)
    np.testing.assert_allclose(soft.robot.truth.q - q, 2 * expect, rtol=0.02, atol=1e-7)


def test_output_side_encoders_report_the_deflection():
    cfg = {**QUIET, "joint_compliance_scale": 1.0, "joint_encoders_output_side": True}
    twin = make(cfg, {"probe_mass_kg": 0.4})
    reading = twin.robot.move_joints(twin.robot.home + STEP)
    np.testing.assert_array_equal(reading.q, twin.robot.truth.q)
    np.testing.assert_allclose(
        reading.T_base_ee, twin.robot.truth.T_base_ee, atol=1e-12
    )  # nominal = true table here


def test_hand_guided_links_sit_where_placed_and_the_motors_lag():
    twin = make({**QUIET, "joint_compliance_scale": 1.0}, {"stylus_mass_kg": 0.3})
    T_goal = forward_kinematics(twin.truth.dh_table, twin.robot.home + STEP)
    reading = twin.robot.place_tool(T_goal, q_near=twin.robot.home + STEP)
    truth = twin.robot.truth
    assert se3.translation_distance(truth.T_base_ee, T_goal) < 1e-9
    np.testing.assert_allclose(
        truth.q - reading.q,
        -harmonic_drive_twist(twin.scene.gravity_torque(truth.q)),
        atol=1e-10,
    )


# ------------------------------------------------------- transmission error, lost motion


def test_transmission_error_is_bounded_periodic_and_fixed_per_robot():
    a = JointErrors.create(0.0, 1.0, 0.0, robot_stream(3))
    b = JointErrors.create(0.0, 1.0, 0.0, robot_stream(3))
    c = JointErrors.create(0.0, 1.0, 0.0, robot_stream(4))
    assert np.array_equal(a.te_phases, b.te_phases)
    assert not np.allclose(a.te_phases, c.te_phases)
    q = np.linspace(-np.pi, np.pi, 200_001)[:, None] * np.ones(6)
    te = np.array([a.transmission_error(row) for row in q[::7]])
    pp = te.max(axis=0) - te.min(axis=0)
    # Peak-to-peak at most the catalogue's value, and most of it.
    assert np.all(pp <= 1.0 * ARCMIN + 1e-12)
    assert np.all(pp > 0.6 * ARCMIN)
    # Periodic in the wave generator's angle (101 × the joint's) up to the output line.
    q0 = np.full(6, 0.3)
    d = a.transmission_error(q0 + 2 * np.pi / 101) - a.transmission_error(q0)
    assert np.max(np.abs(d)) < 0.25 * ARCMIN * 2 * np.pi / 101 * 1.01


def test_lost_motion_follows_the_approach_direction():
    twin = make({**QUIET, "lost_motion_arcmin": 1.0})
    q = twin.robot.home + STEP
    twin.robot.move_joints(q - np.radians(1.0))
    twin.robot.move_joints(q)
    from_below = twin.robot.truth.q
    twin.robot.move_joints(q + np.radians(1.0))
    twin.robot.move_joints(q)
    from_above = twin.robot.truth.q
    np.testing.assert_allclose(from_below - q, 0.5 * ARCMIN, atol=1e-15)
    np.testing.assert_allclose(from_above - q, -0.5 * ARCMIN, atol=1e-15)


# ------------------------------------------------------------ thermal drift and clock


def test_thermal_drift_scales_the_arm_with_the_session_clock():
    cfg = {**QUIET, "thermal_rise_k": 10.0, "thermal_time_constant_min": 1.0}
    twin = make(cfg)
    q = twin.robot.home + STEP
    # Cold: DH kinematics of the true table, which is MuJoCo's flange pose.
    cold = twin.scene.flange_pose(q)
    np.testing.assert_allclose(cold, forward_kinematics(twin.truth.dh_table, q), atol=1e-12)
    while twin.robot.clock_s < 60.0:  # one time constant of grabs at the same pose
        twin.robot.move_joints(q)
        twin.robot.frame_pose()
    twin.robot.move_joints(q)
    t = twin.robot.clock_s
    rise = thermal_rise_k(t, 10.0, 60.0)
    assert 6.0 < rise < 10.0
    warm = twin.robot.truth.T_base_ee
    # Every length grows by α ΔT, angles stay: the flange position scales about the base.
    s = 1 + ALUMINIUM_EXPANSION_PER_K * rise
    np.testing.assert_allclose(warm[:3, 3], s * cold[:3, 3], atol=1e-12)
    np.testing.assert_allclose(warm[:3, :3], cold[:3, :3], atol=1e-12)
    assert np.array_equal(
        warm, forward_kinematics(thermal_table(twin.truth.dh_table, rise), twin.robot.truth.q)
    )
    # ≈ 0.05–0.1 mm at the flange for 7 K.
    assert 0.03 * MM < np.linalg.norm(warm[:3, 3] - cold[:3, 3]) < 0.15 * MM


class _ClockImager:
    """A frame grabber that only reads the robot's frame pose (and so its clock)."""

    def __init__(self, robot):
        self.robot = robot

    def grab(self):
        self.robot.frame_pose()
        return UsFrame(np.zeros((2, 2), np.uint8), (1e-4, 1e-4))


def test_one_sphere_takes_the_papers_robot_time():
    sc = load_scenario(QUICK, check_reach=False)
    twin = make_twin(sc)
    twin.robot.check_collisions = False
    T_ee_us = twin.truth.T_ee_us
    centre = twin.truth.landmarks_base["sphere_1"]
    taught = twin.robot.teach(facing_pose(centre, 20 * MM) @ se3.invert(T_ee_us))
    proto = replace(sc.protocol, frames_per_sweep=21, sweep_half_length_mm=10.0)
    plan = plan_sweeps("sphere_1", taught.T_base_ee, T_ee_us, proto)
    assert sum(len(p.T_base_ee) for p in plan) == 45 * 21
    t0 = twin.robot.clock_s
    acquire(twin.robot, _ClockImager(twin.robot), plan)
    # The paper: 349.5 ± 7.1 s of robot time per sphere.
    assert 342 < twin.robot.clock_s - t0 < 357


# --------------------------------------------------------------- image ↔ pose at a grab


def _linear_steps(twin, n, step_mm=1.0):
    """n linear 1 mm moves along base x from the step pose; frame minus truth each."""
    q = twin.robot.home + STEP
    twin.robot.move_joints(q)
    twin.robot.frame_pose()
    T = twin.robot.read().T_base_ee
    out = []
    for k in range(n):
        T_k = T.copy()
        T_k[0, 3] += ((k + 1) % 2) * step_mm * MM  # back and forth along x
        before = twin.robot.truth.T_base_ee
        twin.robot.move_to(T_k)
        settled = twin.robot.truth.T_base_ee
        out.append((before, settled, twin.robot.frame_pose()))
        assert np.array_equal(twin.robot.frame_pose(), settled)  # no move, no disturbance
    return out


def test_residual_vibration_along_the_move_at_the_configured_amplitude():
    amp = 0.05
    twin = make({**QUIET, "residual_vibration_mm": amp})
    offsets = []
    for before, settled, frame in _linear_steps(twin, 200):
        d = frame[:3, 3] - settled[:3, 3]
        u = settled[:3, 3] - before[:3, 3]
        u /= np.linalg.norm(u)
        assert np.linalg.norm(np.cross(d, u)) < 1e-12  # along the move
        assert np.array_equal(frame[:3, :3], settled[:3, :3])
        offsets.append(float(d @ u))
    offsets = np.array(offsets)
    assert np.max(np.abs(offsets)) <= amp * MM + 1e-15
    # A cos φ with φ uniform: RMS A/√2.
    assert abs(np.sqrt(np.mean(offsets**2)) - amp * MM / np.sqrt(2)) < 0.1 * amp * MM


def test_stale_frames_show_the_pose_before_the_move():
    twin = make({**QUIET, "stale_frame_probability": 1.0})
    for before, settled, frame in _linear_steps(twin, 3):
        assert np.array_equal(frame, before)
        assert not np.array_equal(frame, settled)
    twin = make({**QUIET, "stale_frame_probability": 0.3})
    stale = [np.array_equal(f, b) for b, _s, f in _linear_steps(twin, 300)]
    # Binomial(300, 0.3): 90 ± 8 (σ); 5 σ bounds.
    assert 50 < sum(stale) < 130


# ----------------------------------------------------------------------- probe holder


def test_holder_bends_by_the_weight_across_it():
    tools = ToolsConfig(holder_deflection_mm=0.1)
    L = tools.holder_length_m
    down = se3.matrix_from_euler(np.radians([180.0, 0.0, 0.0]))  # flange z down
    assert np.allclose(holder_deflection(down, tools), np.eye(4), atol=1e-15)
    for beta in (90.0, 30.0, 10.0):
        R = se3.matrix_from_euler(np.radians([180.0 - beta, 0.0, 0.0]))
        T = holder_deflection(R, tools)
        g_ee = R.T @ [0.0, 0.0, -1.0]
        across = g_ee - g_ee[2] * np.array([0.0, 0.0, 1.0])
        u = across / np.linalg.norm(across)
        delta = 0.1 * MM * np.sin(np.radians(beta))
        clamp = se3.apply(T, [0.0, 0.0, L])
        # δ = F L³/3EI along the weight's cross component, F ∝ sin β.
        np.testing.assert_allclose(clamp - [0.0, 0.0, L], delta * u, atol=1e-12)
        # θ = F L²/2EI = 3δ/(2L), the end turning towards the load.
        assert abs(se3.rotation_angle(T, np.eye(4)) - 1.5 * delta / L) < 1e-12
        tip_axis = T[:3, :3] @ [0.0, 0.0, 1.0]
        assert tip_axis @ u > 0


def test_scanner_images_through_the_loaded_mount_truth_stays_unloaded():
    twin = make(QUIET, {"holder_deflection_mm": 0.1})
    twin.robot.move_joints(twin.robot.home + STEP)
    settled = twin.robot.truth.T_base_ee
    frame = twin.robot.frame_pose()
    np.testing.assert_array_equal(
        frame, settled @ holder_deflection(settled[:3, :3], twin.scene.scene.tools)
    )
    np.testing.assert_array_equal(twin.truth.T_ee_us, ToolsConfig().T_ee_us)


# -------------------------------------------------------------------------- touches


def test_stylus_bending_is_the_cantilever_formula():
    tools = ToolsConfig(stylus_force_n=3.0, stylus_radius_mm=2.0, stylus_tip_mm=(0, 0, 100))
    # 4 mm steel rod, 100 mm, 3 N: 3 · 0.1³ / (3 · 200e9 · π 0.002⁴ / 4) ≈ 0.40 mm.
    expect = 3.0 * 0.1**3 / (3 * 200e9 * np.pi * 0.002**4 / 4)
    assert tools.stylus_bending_m == pytest.approx(expect, rel=1e-12)
    assert 0.3 * MM < expect < 0.5 * MM
    assert replace(tools, stylus_modulus_gpa=100.0).stylus_bending_m == pytest.approx(2 * expect)


def test_touch_tip_is_held_off_by_the_bending_across_the_shaft():
    tools = {"mounted": "stylus", "stylus_force_n": 3.0}
    twin = make(QUIET, tools)
    bending = twin.scene.scene.tools.stylus_bending_m
    vertex = forward_kinematics(twin.truth.dh_table, twin.robot.home)[:3, 3] - [0, 0, 0.2]
    R = se3.matrix_from_euler(np.radians([180.0, 0.0, 0.0]))

    def touches(seed):
        guide = SimTouchGuide(
            twin.robot, {"v": vertex}, twin.truth.p_ee_tip, 0.0,
            np.random.default_rng(seed), bending,
        )  # fmt: skip
        offs = []
        for k in range(6):
            guide.place("v", k, R)
            T = twin.robot.truth.T_base_ee
            offs.append(se3.apply(T, twin.truth.p_ee_tip) - vertex)
        return np.array(offs)

    offs = touches(7)
    axis = R @ twin.truth.p_ee_tip / np.linalg.norm(twin.truth.p_ee_tip)
    np.testing.assert_allclose(np.linalg.norm(offs, axis=1), bending, atol=1e-9)
    np.testing.assert_allclose(offs @ axis, 0.0, atol=1e-9)
    assert np.ptp(offs[:, 0]) > 0.5 * bending  # drawn directions differ per touch
    np.testing.assert_allclose(touches(7), offs, atol=1e-9)


# ---------------------------------------------------------------------- determinism


ALL_ON = {
    "joint_repeatability_deg": 0.0041,
    "joint_compliance_scale": 1.0,
    "transmission_error_arcmin": 0.8,
    "lost_motion_arcmin": 1.0,
    "thermal_rise_k": 10.0,
    "residual_vibration_mm": 0.05,
    "stale_frame_probability": 0.2,
}


def test_all_sources_deterministic_for_a_seed():
    tools = {"probe_mass_kg": 0.4, "holder_deflection_mm": 0.1}
    a, b = moves(make(ALL_ON, tools, seed=5)), moves(make(ALL_ON, tools, seed=5))
    c = moves(make(ALL_ON, tools, seed=6))
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True):
            assert np.array_equal(u, v)
    assert not np.array_equal(a[0][0], c[0][0])
