"""The twin's stand-in for an operator touching cone vertices with the stylus.

An operator hand-guides the real arm until the stylus tip sits on a vertex; the twin does
the same from the truth: the *true* tip goes onto the *true* vertex (plus contact noise:
where on the rounded tip and how firmly it seats), at the planned flange orientation,
through the inverse kinematics of the *true* arm. The controller then reports its own
view (joint angles, nominal-model pose); nothing of the truth enters the record.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calib import se3

from .robot import SimRobot

__all__ = ["SimTouchGuide"]

Array = NDArray[np.float64]


class SimTouchGuide:
    """Implements ``calib.protocol.TouchGuide`` on the twin.

    Parameters
    ----------
    robot : SimRobot
        With the stylus mounted.
    vertices_true : dict of (3,) float
        True vertex positions in the base frame.
    p_ee_tip_true : (3,) float
        True stylus tip offset in the flange frame.
    contact_noise_mm : float
        1 σ per axis of where the true tip ends up about the true vertex.
    rng : numpy.random.Generator
    """

    def __init__(
        self,
        robot: SimRobot,
        vertices_true: dict[str, Array],
        p_ee_tip_true: Array,
        contact_noise_mm: float,
        rng: np.random.Generator,
    ) -> None:
        self.robot = robot
        self.vertices = vertices_true
        self.tip = np.asarray(p_ee_tip_true, dtype=float)
        self.noise = contact_noise_mm * 1e-3
        self.rng = rng

    def place(self, vertex: str, index: int, R_base_ee: Array) -> None:
        target = self.vertices[vertex] + self.rng.normal(0.0, 1.0, 3) * self.noise
        R = np.asarray(R_base_ee, dtype=float)
        T = se3.make(R, target - R @ self.tip)
        # The tip touches the vertex on purpose: its contact is not a collision. An operator
        # lifts the stylus and re-approaches between touches: the arm takes the branch
        # nearest its start configuration (elbow up, wrist unwound), not one wound up by
        # the previous touches.
        self.robot.place_tool(
            T, f"touch {index} of {vertex}", ignore=("stylus_tip",), q_near=self.robot.home
        )
