"""Frozen records that flow between the pipeline's stages (DESIGN.md §4).

What they hold is what the hardware gives: frames as a frame grabber delivers them and
poses and joint angles as the controller reports them. Ground truth never enters a record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["Dataset", "RobotReading", "Sweep", "Touch", "UsFrame"]

Array = NDArray[np.float64]


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

    q: Array
    T_base_ee: Array


@dataclass(frozen=True, eq=False)
class UsFrame:
    """One B-mode frame as a frame grabber delivers it.

    Attributes
    ----------
    image : (H, W) uint8
        Rows are axial (row 0 at the transducer face), columns lateral.
    spacing : (sx, sy), metres
        Pixel spacing as the scanner displays it (axial at its assumed speed of sound).
    """

    image: NDArray[np.uint8]
    spacing: tuple[float, float]


@dataclass(frozen=True, eq=False)
class Sweep:
    """A linear elevational sweep at one pose of the acquisition plan.

    Attributes
    ----------
    target : str
        What the sweep images (``sphere_1`` …).
    pose_id : int
        Index in the plan (0–44 for the paper's protocol).
    images : (n, H, W) uint8
    spacing : (sx, sy), metres (displayed)
    q : (n, 6) float, radians
        Reported joint angles at each frame.
    T_base_ee : (n, 4, 4) float
        Reported flange pose at each frame.
    """

    target: str
    pose_id: int
    images: NDArray[np.uint8]
    spacing: tuple[float, float]
    q: Array
    T_base_ee: Array

    @property
    def n_frames(self) -> int:
        return len(self.images)

    @property
    def reference_index(self) -> int:
        """The centre frame, whose ``us`` frame is the sweep's reference frame."""
        return self.n_frames // 2


@dataclass(frozen=True, eq=False)
class Touch:
    """One stylus touch of a cone vertex, as the controller reports it.

    Attributes
    ----------
    vertex : str
        The touched vertex (``vertex_1`` …).
    index : int
        Touch number at that vertex (its orientation in the touch plan).
    q : (6,) float, radians
        Reported joint angles with the tip on the vertex.
    T_base_ee : (4, 4) float
        Reported flange pose (controller's model).
    """

    vertex: str
    index: int
    q: Array
    T_base_ee: Array


@dataclass(frozen=True, eq=False)
class Dataset:
    """Everything one acquisition produced.

    Attributes
    ----------
    name : str
    sweeps : tuple of Sweep
    touches : tuple of Touch
        Stylus touches of the phantom's cone vertices (empty when none were taken).
    meta : dict
        Acquisition settings a reader needs (probe, medium temperature, ...).
    """

    name: str
    sweeps: tuple[Sweep, ...]
    meta: dict[str, object] = field(default_factory=dict)
    touches: tuple[Touch, ...] = ()

    def targets(self) -> list[str]:
        """Targets in order of first appearance."""
        return list(dict.fromkeys(s.target for s in self.sweeps))

    def of(self, target: str) -> tuple[Sweep, ...]:
        """The sweeps of one target."""
        return tuple(s for s in self.sweeps if s.target == target)
