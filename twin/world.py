"""Assembling the twin: true arm, true phantom, tools and tank, and the ground truth.

The ground truth is returned next to the simulated robot, never through it: localization
and calibration never receive it; only evaluation compares estimates with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calib.dh import DHDeltas, DHTable

from .phantoms import Phantom, PhantomConfig, build_tank, phantom_pair
from .robot import RobotConfig, SimRobot, true_dh_deltas
from .scene import Scene, SceneModel
from .tools import ToolsConfig

__all__ = ["GroundTruth", "Twin", "build_twin"]

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What only the twin knows.

    Attributes
    ----------
    dh_table : DHTable
        The true arm (nominal + ``dh_deltas``).
    dh_deltas : DHDeltas
    T_ee_us : (4, 4) float
        True image-to-flange transform (the holder unloaded: with
        ``tools.holder_deflection_mm`` the scanner images through the mount bent by the
        probe's weight, which coincides with it when the probe points down).
    p_ee_tip : (3,) float, metres, ee frame
        True stylus tip offset.
    T_base_phantom : (4, 4) float
        True phantom pose.
    landmarks_base : dict of (3,) float, metres, base frame
        True sphere centres / touch vertices / apex / ridge ends of the printed phantom.
    sphere_radii : dict of float, metres
        True (printed) sphere radii.
    """

    dh_table: DHTable
    dh_deltas: DHDeltas
    T_ee_us: Array
    p_ee_tip: Array
    T_base_phantom: Array
    landmarks_base: dict[str, Array]
    sphere_radii: dict[str, float]


@dataclass(frozen=True, eq=False)
class Twin:
    """A built twin: the MuJoCo scene of the true world, the robot, the CAD phantom the
    pipeline may know, and the ground truth kept apart."""

    scene: SceneModel
    robot: SimRobot
    phantom_cad: Phantom
    truth: GroundTruth
    _scenes: dict[str, SceneModel] = field(default_factory=dict, repr=False)

    def mount(self, tool: Literal["probe", "stylus"]) -> None:
        """Put ``tool`` on the flange: the robot's collision checks use a scene with it
        (built once per tool). The imager needs no change (it looks through the true
        probe mount whenever the probe is on)."""
        if not self._scenes:
            self._scenes[self.scene.scene.tools.mounted] = self.scene
        if tool not in self._scenes:
            base = self.scene.scene
            self._scenes[tool] = SceneModel(replace(base, tools=replace(base.tools, mounted=tool)))
        self.robot.mount(self._scenes[tool])


def build_twin(
    robot_cfg: RobotConfig,
    tools_cfg: ToolsConfig,
    phantom_cfg: PhantomConfig,
    rng_dh: np.random.Generator,
    rng_phantom: np.random.Generator,
    rng_joints: np.random.Generator,
    rng_robot: np.random.Generator | None = None,
) -> Twin:
    """Draw the truth (DH errors, printed phantom) and build scene and robot.

    ``rng_robot``: fixed properties of this arm beyond its DH table, the same in every
    session (:func:`twin.arm_errors.robot_stream`; drawn from only where they are on).
    """
    deltas = true_dh_deltas(robot_cfg, rng_dh)
    table = robot_cfg.nominal_table.with_deltas(deltas)
    cad, printed = phantom_pair(phantom_cfg, rng_phantom)
    scene = SceneModel(
        Scene(
            table,
            tools_cfg,
            printed,
            phantom_cfg.T_base_phantom,
            build_tank(phantom_cfg),
            phantom_cfg.T_base_tank,
            robot_cfg.model,
        )
    )
    truth = GroundTruth(
        dh_table=table,
        dh_deltas=deltas,
        T_ee_us=tools_cfg.T_ee_us,
        p_ee_tip=tools_cfg.p_ee_tip,
        T_base_phantom=phantom_cfg.T_base_phantom,
        landmarks_base=printed.landmarks_in(phantom_cfg.T_base_phantom),
        sphere_radii=dict(printed.sphere_radii),
    )
    robot = SimRobot(robot_cfg, scene, rng_joints, robot_rng=rng_robot)
    return Twin(scene, robot, cad, truth)
