"""The twin's stand-in for an operator touching cone vertices with the stylus.

An operator hand-guides the real arm until the stylus tip sits on a vertex; the twin does
the same from the truth: the *true* tip goes onto the *true* vertex (plus contact noise:
where on the rounded tip and how firmly it seats; and the shaft bent by the hand's
force, when that is on), at the planned flange orientation,
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
    """Implements ``calib.acquisition.protocol.TouchGuide`` on the twin.

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
    bending_m : float
        Deflection of the stylus tip across the shaft under the hand-guiding force
        (:attr:`twin.tools.ToolsConfig.stylus_bending_m`); its direction is drawn per
        touch from a stream spawned off ``rng`` (only when it is on).
    """

    def __init__(
        self,
        robot: SimRobot,
        vertices_true: dict[str, Array],
        p_ee_tip_true: Array,
        contact_noise_mm: float,
        rng: np.random.Generator,
        bending_m: float = 0.0,
    ) -> None:
        self.robot = robot
        self.vertices = vertices_true
        self.tip = np.asarray(p_ee_tip_true, dtype=float)
        self.noise = contact_noise_mm * 1e-3
        self.rng = rng
        self.bending = bending_m
        self._bend_rng: np.random.Generator | None = None

    def loaded_tip(self) -> Array:
        """The tip offset (3,) in ee with the shaft bent by the hand's force: ``bending``
        across the shaft in a direction drawn uniformly about it (the operator's push
        has no preferred side)."""
        if self.bending == 0:
            return self.tip
        if self._bend_rng is None:
            self._bend_rng = self.rng.spawn(1)[0]
        axis = self.tip / np.linalg.norm(self.tip)
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        phi = self._bend_rng.uniform(0.0, 2 * np.pi)
        return self.tip + self.bending * (np.cos(phi) * e1 + np.sin(phi) * e2)

    def place(self, vertex: str, index: int, R_base_ee: Array) -> None:
        target = self.vertices[vertex] + self.rng.normal(0.0, 1.0, 3) * self.noise
        R = np.asarray(R_base_ee, dtype=float)
        # The tip sits on the vertex; the bent shaft holds the flange off by the bending
        # (a cantilever from the flange, end-loaded at the tip: δ = F L³ / 3EI).
        T = se3.make(R, target - R @ self.loaded_tip())
        # The tip touches the vertex on purpose: its contact is not a collision. An operator
        # lifts the stylus and re-approaches between touches: the arm takes the branch
        # nearest its start configuration (elbow up, wrist unwound), not one wound up by
        # the previous touches.
        self.robot.place_tool(
            T, f"touch {index} of {vertex}", ignore=("stylus_tip",), q_near=self.robot.home
        )
