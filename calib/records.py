"""Frozen records that flow between the pipeline's stages (DESIGN.md §4).

Started with what the robot reports; the acquisition records (``UsFrame``, ``Sweep``,
``TouchSet``, ``Dataset``) join them with the acquisition protocol.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["RobotReading"]


@dataclass(frozen=True, eq=False)
class RobotReading:
    """What a robot controller reports after a motion settles.

    Attributes
    ----------
    q : (6,) float, radians
        Joint angles as the encoders report them.
    T_base_ee : (4, 4) float
        Flange pose as the controller computes it (its own kinematic model, TCP offset 0).
    """

    q: NDArray[np.float64]
    T_base_ee: NDArray[np.float64]
