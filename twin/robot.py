"""The simulated UR3: a controller with the nominal model driving the true arm.

``SimRobot.move_to(T_base_ee)`` does what a UR controller does for a linear move: solve
the inverse kinematics with *its* (nominal) DH table, pick the solution closest to the
current configuration, and drive the joints there. The *true* arm (nominal + per-joint
DH deltas, built in MuJoCo) lands at the commanded angles plus the joint repeatability
error; the encoders report the true angles plus encoder noise; the controller reports
those angles and the pose its nominal forward kinematics gives them. Ground truth (the
true angles and the true flange pose) is kept apart, in :attr:`SimRobot.truth`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib.dh import NOMINAL_TABLES, DHDeltas, DHTable, forward_kinematics
from calib.errors import CollisionError
from calib.records import RobotReading

from .ik import describe_pose, solve_ik
from .scene import SceneModel

__all__ = ["RobotConfig", "RobotTruth", "SimRobot", "true_dh_deltas"]

Array = NDArray[np.float64]


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
    joint_repeatability_deg: float = field(
        default=0.002,
        metadata={
            "doc": "1 σ error of a true joint angle about the commanded one.",
            "ge": 0,
            "le": 1,
        },
    )
    encoder_noise_deg: float = field(
        default=0.001,
        metadata={
            "doc": "1 σ noise of reported joint angles about the true ones.",
            "ge": 0,
            "le": 1,
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
        Joint repeatability and encoder noise.
    check_collisions : bool
        Raise :class:`CollisionError` when the true arm or tool ends up inside the phantom
        or the tank (a real robot would have hit them).
    """

    def __init__(
        self,
        cfg: RobotConfig,
        scene: SceneModel,
        rng: np.random.Generator,
        check_collisions: bool = True,
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

    def mount(self, scene: SceneModel) -> None:
        """Change the tool: from now on collisions are checked in ``scene`` (the same arm
        with another tool on the flange)."""
        self.scene = scene

    def _settle(self, q_cmd: Array, label: str, ignore: tuple[str, ...] = ()) -> RobotReading:
        q_true = q_cmd + self._rng.normal(0.0, 1.0, 6) * self._repeat
        if self.check_collisions:
            contacts = self.scene.collisions(q_true, ignore)
            if contacts:
                c = contacts[0]
                raise CollisionError(
                    f"moving to {label} puts {c.robot_geom} {1e3 * c.depth:.1f} mm into "
                    f"{c.environment_geom}"
                    + (f" (and {len(contacts) - 1} more contacts)" if len(contacts) > 1 else "")
                )
        self._q_true = q_true
        self._q_reported = q_true + self._rng.normal(0.0, 1.0, 6) * self._encoder
        return self.read()

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
        return self._settle(q_cmd, pose_label or describe_pose(T))

    def check_pose(self, T_base_ee: ArrayLike, pose_label: str = "") -> None:
        """Raise if the controller cannot reach a pose or the true arm would hit something
        there (planning check before any motion; nothing moves)."""
        T = np.asarray(T_base_ee, dtype=float)
        q = solve_ik(self.nominal, T, self._q_reported, pose_label=pose_label)
        contacts = self.scene.collisions(q)
        if contacts:
            c = contacts[0]
            raise CollisionError(
                f"pose {pose_label or describe_pose(T)} would put {c.robot_geom} "
                f"{1e3 * c.depth:.1f} mm into {c.environment_geom}"
            )

    def teach(self, T_base_ee_true: ArrayLike, pose_label: str = "") -> RobotReading:
        """Emulate an operator jogging the arm until the *true* flange sits at a pose (the
        operator looks at the live image, not at the controller's numbers).

        Solves the inverse kinematics of the true arm; the controller then reports its own
        (nominal) view of where it is, which is what a taught pose records.
        """
        return self.place_tool(T_base_ee_true, pose_label)

    def move_joints(self, q: ArrayLike, ignore: tuple[str, ...] = ()) -> RobotReading:
        """Joint move to commanded angles ``q`` (6,), radians; contacts of the geoms named in
        ``ignore`` are intended (a stylus tip on a vertex)."""
        q_cmd = np.asarray(q, dtype=float)
        return self._settle(q_cmd, f"joints {np.round(np.degrees(q_cmd), 1).tolist()} deg", ignore)

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
        return self.move_joints(q, ignore)

    @property
    def home(self) -> Array:
        """The start configuration (radians)."""
        return np.radians(np.asarray(self.cfg.home_deg, dtype=float))

    def read(self) -> RobotReading:
        """Reported joint angles and the controller's (nominal-FK) flange pose."""
        q = self._q_reported.copy()
        return RobotReading(q=q, T_base_ee=forward_kinematics(self.nominal, q))

    @property
    def truth(self) -> RobotTruth:
        """True joint angles and true flange pose (MuJoCo, true DH). Never reported."""
        return RobotTruth(q=self._q_true.copy(), T_base_ee=self.scene.flange_pose(self._q_true))
