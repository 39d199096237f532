"""The simulated UR3: a controller with the nominal model driving the true arm.

``SimRobot.move_to(T_base_ee)`` does what a UR controller does for a linear move: solve
the inverse kinematics with *its* (nominal) DH table, pick the solution closest to the
current configuration, and drive the joints there. The *true* arm (nominal + per-joint
DH deltas, built in MuJoCo) lands at the commanded angles plus the joint repeatability
error; the encoders report the true angles plus encoder noise; the controller reports
those angles and the pose its nominal forward kinematics gives them. Ground truth (the
true angles and the true flange pose) is kept apart, in :attr:`SimRobot.truth`.

Beyond the DH table the true arm can carry what a real one does (each off at zero, see
:mod:`twin.arm_errors`): joint compliance under gravity and payload, gear transmission
error and lost motion between motor and link (the reports see them only with
output-side encoders), thermal growth of the links over the session's clock, residual
vibration and stale frames at the grab instant (:meth:`SimRobot.frame_pose`), and the
printed holder's deflection under the probe's weight.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib import se3
from calib.dh import NOMINAL_TABLES, DHDeltas, DHTable, forward_kinematics
from calib.errors import CollisionError, UnreachablePoseError
from calib.records import RobotReading

from .arm_errors import (
    JointErrors,
    robot_stream,
    thermal_rise_k,
    thermal_table,
    trapezoid_time_s,
)
from .ik import describe_pose, solve_ik, solve_poses
from .scene import SceneModel
from .tools import holder_deflection

__all__ = ["PLAN_MARGIN_M", "RobotConfig", "RobotTruth", "SimRobot", "true_dh_deltas"]

Array = NDArray[np.float64]

#: The room (m) a planned pose must leave between the arm or tool and the phantom or
#: tank. A pose is checked where the controller's inverse kinematics put the true arm;
#: the move then lands off it by the arm's placement error (UR3: ±0.1 mm repeatability,
#: ISO 9283, and the joints' transmission error and lost motion, about 0.1 mm each at
#: the tool). A sweep checked with no room at all (quick.yaml, seed 22, a 12 mm target)
#: passed the check and then stopped the acquisition, the probe 0.0 mm into a sphere.
PLAN_MARGIN_M = 0.5e-3


@dataclass(frozen=True)
class RobotConfig:
    """The simulated arm: model, kinematic errors (truth) and joint noise."""

    model: Literal["ur3", "ur3e"] = field(
        default="ur3", metadata={"doc": "Arm model whose published DH table is the nominal one."}
    )
    dh_error_scale: float = field(
        default=1.0,
        metadata={
            "doc": "Multiplies every kinematic error below (0 = the true arm is nominal).",
            "ge": 0,
            "le": 10,
        },
    )
    dh_rms_theta_deg: float = field(
        default=2.51, metadata={"doc": "RMS of drawn joint-offset errors Δθ.", "ge": 0, "le": 10}
    )
    dh_rms_d_mm: float = field(
        default=0.24, metadata={"doc": "RMS of drawn Δd.", "ge": 0, "le": 20}
    )
    dh_rms_a_mm: float = field(
        default=1.51, metadata={"doc": "RMS of drawn Δa.", "ge": 0, "le": 20}
    )
    dh_rms_alpha_deg: float = field(
        default=0.27, metadata={"doc": "RMS of drawn Δα.", "ge": 0, "le": 10}
    )
    dh_delta_theta_deg: tuple[float, ...] | None = field(
        default=None,
        metadata={"doc": "Explicit per-joint Δθ (replaces the drawn ones).", "len": 6},
    )
    dh_delta_d_mm: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Explicit per-joint Δd.", "len": 6}
    )
    dh_delta_a_mm: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Explicit per-joint Δa.", "len": 6}
    )
    dh_delta_alpha_deg: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Explicit per-joint Δα.", "len": 6}
    )
    # ISO 9283 pose repeatability RP = mean + 3 σ of the distance l of the attained
    # positions from their mean. With an isotropic 3-D Gaussian of per-axis σ_p, l is
    # Maxwell distributed: mean 2σ_p √(2/π) = 1.596 σ_p, σ_l = σ_p √(3 − 8/π) = 0.674 σ_p,
    # so RP = 3.617 σ_p. Independent joint errors σ_q give σ_p = σ_q √(tr(J Jᵀ)/3), with
    # √(tr(J Jᵀ)/3) = 0.382 m/rad at the probe's image origin over the tank (UR3, home
    # configuration; 0.391 for the UR3e). Hence σ_q = RP / (3.617 · 0.382 m):
    #   UR3 CB-series datasheet ±0.1 mm  → σ_p 0.028 mm → σ_q 0.0041°,
    #   UR3e datasheet          ±0.03 mm → σ_p 0.0083 mm → σ_q 0.0012°;
    # the default 0.002° is RP ≈ 0.048 mm, between the two.
    joint_repeatability_deg: float = field(
        default=0.002,
        metadata={
            "doc": "Pose repeatability: 1 σ error of each true joint angle about the "
            "commanded one, drawn at every move. Plausible 0.0012° (UR3e datasheet, "
            "ISO 9283 ±0.03 mm) to 0.0041° (UR3 CB-series datasheet, ±0.1 mm), converted "
            "as RP = mean + 3σ of the position scatter at the probe (RP ≈ 3.6 σ_p per "
            "axis, σ_p ≈ 0.38 m × σ_q).",
            "ge": 0,
            "le": 1,
        },
    )
    encoder_noise_deg: float = field(
        default=0.001,
        metadata={
            "doc": "1 σ noise of reported joint angles about the true ones. Plausible "
            "0.0005–0.002° (joint encoder resolution of the order of 0.001°; quantisation "
            "alone gives resolution / √12).",
            "ge": 0,
            "le": 1,
        },
    )
    joint_compliance_scale: float = field(
        default=0.0,
        metadata={
            "doc": "Joint compliance: each joint's gear twists by its gravity and payload "
            "torque (MuJoCo's qfrc_bias at rest, UR's published link masses plus the "
            "tool's mass) along the Harmonic Drive catalogue's torque–twist curve "
            "(sizes 20/20/17/14/14/14, K ≈ 5e3–3e4 N m/rad); this scales the twist "
            "(0 = rigid joints, 1 = catalogue stiffness; ≈ 1 mrad, 0.4 mm at the tool "
            "for the shoulder). Plausible 0.5–2 (the catalogue gives typical values; "
            "bearings and housing add compliance).",
            "ge": 0,
            "le": 10,
        },
    )
    joint_encoders_output_side: bool = field(
        default=False,
        metadata={
            "doc": "Whether the reported joint angles come from output-side (link) "
            "encoders: then compliance, transmission error and lost motion are measured "
            "and reported (no error to the pipeline, the arm only lands elsewhere); "
            "false: motor-side encoders, the reports miss them."
        },
    )
    transmission_error_arcmin: float = field(
        default=0.0,
        metadata={
            "doc": "Peak-to-peak transmission error of each joint's strain-wave gear: "
            "lines at 1× and 2× the wave-generator revolution (101 × the joint angle) and "
            "1× the output revolution, phases fixed per robot (0 = off). Catalogue: "
            "< 1 arcmin (sizes 14, 17), < 0.8 arcmin (20, 25); ≈ 0.05–0.09 mm at the "
            "tool per joint.",
            "ge": 0,
            "le": 10,
        },
    )
    lost_motion_arcmin: float = field(
        default=0.0,
        metadata={
            "doc": "Lost motion of each joint's gear: the link lags by half of it "
            "against the direction the joint last moved (0 = off). Catalogue: "
            "< 1 arcmin.",
            "ge": 0,
            "le": 10,
        },
    )
    thermal_rise_k: float = field(
        default=0.0,
        metadata={
            "doc": "Thermal drift: the arm warms by ΔT(t) = ΔT∞ (1 − e^(−t/τ)) over the "
            "session (t = clock since the dataset's acquisition started) and every DH "
            "length (a, d) grows by 23e-6/K (aluminium) × ΔT; this is ΔT∞ in kelvin "
            "(0 = off). Plausible 5–15 K (estimate: joint motors and drives warming from "
            "cold; 0.05–0.15 mm in the first hour).",
            "ge": 0,
            "le": 40,
        },
    )
    thermal_time_constant_min: float = field(
        default=45.0,
        metadata={
            "doc": "Time constant τ of the arm's warm-up (estimate 30–60 min).",
            "gt": 0,
            "le": 600,
        },
    )
    residual_vibration_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Residual vibration after a move: amplitude of the damped oscillation "
            "of the flange along the move's direction at the instant a frame is grabbed "
            "(its phase there random per frame); 0 = off. Plausible 0.02–0.1 mm: UR3 "
            "first mode 10–20 Hz, ζ 0.02–0.05, excited by ≈ a/ω² ≈ 0.1 mm at 1.2 m/s² and "
            "decayed by e^(−ζω t) over the settle time.",
            "ge": 0,
            "le": 2,
        },
    )
    stale_frame_probability: float = field(
        default=0.0,
        metadata={
            "doc": "Probability that a frame grabbed after a move still shows the pose "
            "before it (the scanner's display lags; video latency of ≈ 0.1–0.3 s "
            "reported by temporal calibrations); 0 = off. Plausible 0–0.05 with "
            "stop-and-settle.",
            "ge": 0,
            "le": 1,
        },
    )
    tool_speed_mm_s: float = field(
        default=250.0,
        metadata={
            "doc": "Session clock: tool speed of linear moves (UR default 250 mm/s).",
            "gt": 0,
            "le": 1000,
        },
    )
    tool_acceleration_mm_s2: float = field(
        default=1200.0,
        metadata={
            "doc": "Session clock: tool acceleration of linear moves (UR default 1200 mm/s²).",
            "gt": 0,
            "le": 10000,
        },
    )
    joint_speed_deg_s: float = field(
        default=60.0,
        metadata={
            "doc": "Session clock: joint speed limit (UR default 60°/s).",
            "gt": 0,
            "le": 360,
        },
    )
    joint_acceleration_deg_s2: float = field(
        default=80.0,
        metadata={
            "doc": "Session clock: joint acceleration limit (UR default 80°/s²).",
            "gt": 0,
            "le": 1000,
        },
    )
    settle_s: float = field(
        default=0.255,
        metadata={
            "doc": "Session clock: wait after each move before a frame is grabbed "
            "(with the default speeds one sphere's 45 sweeps × 21 frames take ≈ 350 s, "
            "the paper's 349.5 ± 7.1 s).",
            "ge": 0,
            "le": 10,
        },
    )
    grab_s: float = field(
        default=0.04,
        metadata={
            "doc": "Session clock: time to grab one frame (≈ one video frame period).",
            "ge": 0,
            "le": 5,
        },
    )
    home_deg: tuple[float, ...] = field(
        default=(22.0, -85.0, -98.0, -87.0, 90.0, -158.0),
        metadata={
            "doc": "Start configuration (elbow up, flange pointing down above the tank).",
            "len": 6,
        },
    )

    @property
    def nominal_table(self) -> DHTable:
        """The published DH table of ``model``: the controller's kinematic model."""
        return NOMINAL_TABLES[self.model]


def true_dh_deltas(cfg: RobotConfig, rng: np.random.Generator) -> DHDeltas:
    """The true arm's per-joint DH errors: explicit where given, else drawn N(0, rms²),
    all times ``dh_error_scale``."""
    drawn = {
        "theta": (cfg.dh_delta_theta_deg, np.radians(cfg.dh_rms_theta_deg), np.radians),
        "d": (cfg.dh_delta_d_mm, cfg.dh_rms_d_mm * 1e-3, lambda v: np.asarray(v) * 1e-3),
        "a": (cfg.dh_delta_a_mm, cfg.dh_rms_a_mm * 1e-3, lambda v: np.asarray(v) * 1e-3),
        "alpha": (cfg.dh_delta_alpha_deg, np.radians(cfg.dh_rms_alpha_deg), np.radians),
    }
    columns = {}
    for name, (explicit, rms, to_si) in drawn.items():
        # Draw every column even when explicit so the stream (and the other columns) stay
        # the same whichever keys a scenario sets.
        values = rng.normal(0.0, 1.0, 6) * rms
        if explicit is not None:
            values = to_si(np.asarray(explicit, dtype=float))
        columns[name] = tuple(float(v) for v in cfg.dh_error_scale * values)
    return DHDeltas(**columns)


@dataclass(frozen=True, eq=False)
class RobotTruth:
    """Ground truth of the arm after a motion: true joint angles and flange pose."""

    q: Array
    T_base_ee: Array


class SimRobot:
    """A UR3 controller (nominal model) driving the true arm of a MuJoCo scene.

    Parameters
    ----------
    cfg : RobotConfig
    scene : SceneModel
        The scene built from the *true* DH table.
    rng : numpy.random.Generator
        Joint repeatability and encoder noise (and, spawned from it only when they are
        on, the per-frame draws of residual vibration and stale frames).
    check_collisions : bool
        Raise :class:`CollisionError` when the true arm or tool ends up inside the phantom
        or the tank (a real robot would have hit them).
    robot_rng : numpy.random.Generator, optional
        Fixed properties of this arm (the phases of its gears' transmission error),
        the same for every session of the robot (:func:`twin.arm_errors.robot_stream`).

    Attributes
    ----------
    clock_s : float
        Seconds since the session (this robot's dataset acquisition) started: advanced
        by every move (motion time at the configured speeds + the settle time) and every
        frame grab (:meth:`frame_pose`).
    """

    def __init__(
        self,
        cfg: RobotConfig,
        scene: SceneModel,
        rng: np.random.Generator,
        check_collisions: bool = True,
        robot_rng: np.random.Generator | None = None,
    ) -> None:
        self.cfg = cfg
        self.scene = scene
        self.nominal = cfg.nominal_table
        self._rng = rng
        self._repeat = np.radians(cfg.joint_repeatability_deg)
        self._encoder = np.radians(cfg.encoder_noise_deg)
        self.check_collisions = check_collisions
        self._q_true = np.radians(np.asarray(cfg.home_deg, dtype=float))
        self._q_reported = self._q_true.copy()
        self._q_motor = self._q_true.copy()  # motor-side angles (joint errors between)
        self.clock_s = 0.0
        self._settled_at_s = 0.0  # clock of the last settle (the truth's temperature)
        self._q_cmd = self._q_true.copy()  # last commanded angles (the clock's moves)
        self._joints = JointErrors.create(
            cfg.joint_compliance_scale,
            cfg.transmission_error_arcmin,
            cfg.lost_motion_arcmin,
            robot_stream(0) if robot_rng is None else robot_rng,
        )
        self._approach = np.zeros(6)  # sign of each joint's last motion (lost motion)
        self._frame_rng: np.random.Generator | None = None  # vibration, stale frames
        self._T_before_move: Array | None = None
        self._moved = False
        self._truth_T: Array | None = None  # the truth's flange pose, until the next settle

    def mount(self, scene: SceneModel) -> None:
        """Change the tool: from now on collisions are checked in ``scene`` (the same arm
        with another tool on the flange)."""
        self.scene = scene
        self._truth_T = None

    # ------------------------------------------------------------------ settling a move

    def _settle(
        self,
        q_cmd: Array,
        label: str,
        ignore: tuple[str, ...] = (),
        guided: bool = False,
        linear: bool = False,
    ) -> RobotReading:
        q_target = q_cmd + self._rng.normal(0.0, 1.0, 6) * self._repeat
        q_true, q_motor = q_target, q_target
        if self._joints is not None:
            moved = q_target - (self._q_true if guided else self._q_motor)
            self._approach = np.where(np.abs(moved) > 1e-9, np.sign(moved), self._approach)
            q_true, q_motor = self._joints.settle(
                q_target, guided, self._approach, self.scene.gravity_torque
            )
        if self.check_collisions:
            contacts = self.scene.collisions(q_true, ignore)
            if contacts:
                c = contacts[0]
                raise CollisionError(
                    f"moving to {label} puts {c.robot_geom} {1e3 * c.depth:.1f} mm into "
                    f"{c.environment_geom}"
                    + (f" (and {len(contacts) - 1} more contacts)" if len(contacts) > 1 else "")
                )
        if self._frames_disturbed:
            self._T_before_move = self.truth.T_base_ee
        self._advance_clock(q_cmd, linear)
        self._q_true = q_true
        self._truth_T = None
        self._q_motor = q_motor
        self._moved = True
        seen = q_true if self._joints is None or self.cfg.joint_encoders_output_side else q_motor
        self._q_reported = seen + self._rng.normal(0.0, 1.0, 6) * self._encoder
        return self.read()

    def _advance_clock(self, q_cmd: Array, linear: bool) -> None:
        """Move time plus the settle time; the truth's temperature is taken then.

        Trapezoidal velocity profiles as the UR controller plans them: a linear move
        (``movel``) by the tool's path length at the tool speed and acceleration, its
        turn at the joint limits; a joint move (``movej``, hand-guiding) by the joint
        that moves furthest."""
        cfg = self.cfg
        if linear:
            T0 = forward_kinematics(self.nominal, self._q_cmd)
            T1 = forward_kinematics(self.nominal, q_cmd)
            path_mm = 1e3 * float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
            turn_deg = float(np.degrees(se3.rotation_angle(T0, T1)))
            t_move = max(
                trapezoid_time_s(path_mm, cfg.tool_speed_mm_s, cfg.tool_acceleration_mm_s2),
                trapezoid_time_s(turn_deg, cfg.joint_speed_deg_s, cfg.joint_acceleration_deg_s2),
            )
        else:
            dq = float(np.max(np.abs(np.degrees(q_cmd - self._q_cmd))))
            t_move = trapezoid_time_s(dq, cfg.joint_speed_deg_s, cfg.joint_acceleration_deg_s2)
        self.clock_s += t_move + cfg.settle_s
        self._settled_at_s = self.clock_s
        self._q_cmd = np.array(q_cmd, dtype=float)

    # ---------------------------------------------------------------------- the motions

    def move_to(self, T_base_ee: ArrayLike, pose_label: str = "") -> RobotReading:
        """Linear move to a flange pose (controller model); returns the settled reading.

        Raises
        ------
        UnreachablePoseError
            When the nominal model has no solution within the joint limits.
        CollisionError
            When the true arm would end up in the phantom or tank.
        """
        T = np.asarray(T_base_ee, dtype=float)
        q_cmd = solve_ik(self.nominal, T, self._q_reported, pose_label=pose_label)
        return self._settle(q_cmd, pose_label or describe_pose(T), linear=True)

    def check_pose(self, T_base_ee: ArrayLike, pose_label: str = "") -> None:
        """Raise if the controller cannot reach a pose or the true arm would hit something
        there (planning check before any motion; nothing moves)."""
        T = np.asarray(T_base_ee, dtype=float)
        q = solve_ik(self.nominal, T, self._q_reported, pose_label=pose_label)
        # The clearance is taken over the same arm/tool and phantom/tank geoms as the
        # contacts: only a pose short of the margin is asked which geoms touch.
        room = self.scene.clearance(q, PLAN_MARGIN_M)
        if room >= PLAN_MARGIN_M:
            return
        contacts = self.scene.collisions(q)
        if contacts:
            c = contacts[0]
            raise CollisionError(
                f"pose {pose_label or describe_pose(T)} would put {c.robot_geom} "
                f"{1e3 * c.depth:.1f} mm into {c.environment_geom}"
            )
        raise CollisionError(
            f"pose {pose_label or describe_pose(T)} would leave {1e3 * room:.2f} mm between "
            f"the arm or tool and the phantom or tank; a plan keeps "
            f"{1e3 * PLAN_MARGIN_M:g} mm (the arm's placement error)"
        )

    def clearances(self, T_base_ee: ArrayLike, within: float) -> Array:
        """How far (m, up to ``within``) the arm and tool stay from the phantom and tank
        at each of the poses (n, 4, 4) — −inf where the controller cannot reach one: the
        room a plan leaves for another session's taught pose and mount. Nothing moves."""
        T = np.asarray(T_base_ee, dtype=float).reshape(-1, 4, 4)
        out = np.full(len(T), -np.inf)
        for k, pose in enumerate(T):
            if k % 4096 == 0:  # solved in batches the IK's memo holds
                solve_poses(self.nominal, T[k : k + 4096])
            try:
                q = solve_ik(self.nominal, pose, self._q_reported)
            except UnreachablePoseError:
                continue
            out[k] = self.scene.clearance(q, within)
        return out

    def path_clearances(self, T_base_ee: ArrayLike, within: float, q_start: ArrayLike) -> Array:
        """:meth:`clearances` of poses moved through in order from the joint angles
        ``q_start``, each solved nearest the one before as the controller's moves solve
        them: the arm's configuration depends on the way it came (a wrist that wraps on
        the way may meet a wall the same pose taught directly clears). −inf from the
        first pose the controller cannot reach."""
        T = np.asarray(T_base_ee, dtype=float).reshape(-1, 4, 4)
        out = np.full(len(T), -np.inf)
        q = np.asarray(q_start, dtype=float)
        for k, pose in enumerate(T):
            if k % 4096 == 0:
                solve_poses(self.nominal, T[k : k + 4096])
            try:
                q = solve_ik(self.nominal, pose, q)
            except UnreachablePoseError:
                break
            out[k] = self.scene.clearance(q, within)
        return out

    def check_poses(self, T_base_ee: ArrayLike, pose_labels: Sequence[str]) -> None:
        """:meth:`check_pose` of many poses (n, 4, 4) in order, their inverse kinematics
        solved at once (kept for the moves to them)."""
        T = np.asarray(T_base_ee, dtype=float).reshape(-1, 4, 4)
        if len(pose_labels) != len(T):
            raise ValueError(f"{len(pose_labels)} labels for {len(T)} poses")
        solve_poses(self.nominal, T)
        for pose, label in zip(T, pose_labels, strict=True):
            self.check_pose(pose, label)

    def teach(self, T_base_ee_true: ArrayLike, pose_label: str = "") -> RobotReading:
        """Emulate an operator jogging the arm until the *true* flange sits at a pose (the
        operator looks at the live image, not at the controller's numbers).

        Solves the inverse kinematics of the true arm; the controller then reports its own
        (nominal) view of where it is, which is what a taught pose records.
        """
        return self.place_tool(T_base_ee_true, pose_label)

    def move_joints(
        self, q: ArrayLike, ignore: tuple[str, ...] = (), guided: bool = False
    ) -> RobotReading:
        """Joint move to commanded angles ``q`` (6,), radians; contacts of the geoms named in
        ``ignore`` are intended (a stylus tip on a vertex). ``guided``: the *links* are
        put at ``q`` by hand (the motors sit where the joints' compliance, transmission
        error and lost motion leave them) instead of the motors being driven there."""
        q_cmd = np.asarray(q, dtype=float)
        return self._settle(q_cmd, _joints_label(q_cmd), ignore, guided)

    def place_tool(
        self,
        T_base_ee_true: ArrayLike,
        pose_label: str = "",
        ignore: tuple[str, ...] = (),
        q_near: ArrayLike | None = None,
    ) -> RobotReading:
        """Emulate hand-guiding the arm until the *true* flange sits at a pose (inverse
        kinematics of the true arm, on the branch nearest ``q_near``, default the current
        configuration); the controller reports its own view of it."""
        near = self._q_reported if q_near is None else np.asarray(q_near, dtype=float)
        q = solve_ik(self.scene.scene.table, T_base_ee_true, near, pose_label=pose_label)
        label = f"{pose_label} ({_joints_label(q)})" if pose_label else _joints_label(q)
        return self._settle(q, label, ignore, guided=True)

    @property
    def home(self) -> Array:
        """The start configuration (radians)."""
        return np.radians(np.asarray(self.cfg.home_deg, dtype=float))

    def read(self) -> RobotReading:
        """Reported joint angles and the controller's (nominal-FK) flange pose."""
        q = self._q_reported.copy()
        return RobotReading(q=q, T_base_ee=forward_kinematics(self.nominal, q))

    # ---------------------------------------------------------------------- the truth

    def true_table(self) -> DHTable:
        """The true arm's DH table now: the scene's, grown by the thermal drift at the
        last settle (the scene's own when the drift is off)."""
        table = self.scene.scene.table
        if self.cfg.thermal_rise_k == 0:
            return table
        rise = thermal_rise_k(
            self._settled_at_s, self.cfg.thermal_rise_k, 60.0 * self.cfg.thermal_time_constant_min
        )
        return thermal_table(table, rise)

    @property
    def truth(self) -> RobotTruth:
        """True joint angles and true flange pose (MuJoCo, true DH; with thermal drift the
        DH kinematics of the warmed table, which MuJoCo's model does not carry). Never
        reported."""
        # It changes only when the arm settles or the tool changes (both clear the memo);
        # a frame reads it up to three times: the move, the grab, the simulator's log.
        if self._truth_T is None:
            if self.cfg.thermal_rise_k == 0:
                self._truth_T = self.scene.flange_pose(self._q_true)
            else:
                self._truth_T = forward_kinematics(self.true_table(), self._q_true)
        return RobotTruth(q=self._q_true.copy(), T_base_ee=self._truth_T.copy())

    @property
    def _frames_disturbed(self) -> bool:
        return self.cfg.residual_vibration_mm > 0 or self.cfg.stale_frame_probability > 0

    def frame_pose(self) -> Array:
        """The true flange pose (4, 4) at the instant a frame is grabbed, as the scanner
        images it, and advance the clock by the grab.

        This differs from the settled :attr:`truth` (which a simulator logs as the frame's
        ground truth) only where the probe moved since the last grab:

        - with probability ``stale_frame_probability`` the frame still shows the pose
          before the move (returned as it settled there);
        - otherwise residual vibration: the flange is displaced along the move's
          direction by A cos φ, A = ``residual_vibration_mm``, φ uniform (the grab's
          timing jitter of a video frame period covers a 10–20 Hz mode's period).

        With the probe mounted the printed holder's elastic deflection under the probe's
        weight is composed on (:func:`twin.tools.holder_deflection`): the scanner images
        through the loaded mount ``T_base_ee @ T_ee_loaded @ T_ee_us``.
        """
        T = self.truth.T_base_ee
        moved, self._moved = self._moved, False
        if moved and self._frames_disturbed and self._T_before_move is not None:
            if self._frame_rng is None:
                # Spawned, not drawn: the joint stream's own draws stay as they were.
                self._frame_rng = self._rng.spawn(1)[0]
            before = self._T_before_move
            stale = self._frame_rng.random() < self.cfg.stale_frame_probability
            phase = self._frame_rng.uniform(0.0, 2 * np.pi)
            step = T[:3, 3] - before[:3, 3]
            distance = float(np.linalg.norm(step))
            if stale:
                T = before.copy()
            elif self.cfg.residual_vibration_mm > 0 and distance > 1e-6:
                T = T.copy()
                T[:3, 3] += 1e-3 * self.cfg.residual_vibration_mm * np.cos(phase) * step / distance
        tools = self.scene.scene.tools
        if tools.mounted == "probe" and tools.holder_deflection_mm > 0:
            T = T @ holder_deflection(T[:3, :3], tools)
        self.clock_s += self.cfg.grab_s
        return T


def _joints_label(q: Array) -> str:
    """A move's target as its errors name it: the joint angles in degrees."""
    return f"joints {np.round(np.degrees(q), 1).tolist()} deg"
