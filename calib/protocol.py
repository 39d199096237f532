"""Multi-pose sphere acquisition (paper, "Multi-Pose Sphere Acquisition").

From a nominal pose facing a sphere, the plan is the nominal orientation plus the eight
(±10°, ±10°, ±10°) corners about the probe axes (9 orientations), each crossed with the
nominal and four (±3, ±3) mm in-plane positions (5 positions): 45 poses, each a ±10 mm
elevational sweep of 21 frames. Rotations turn about the sphere centre so it stays in view.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import se3

__all__ = ["ProtocolConfig", "facing_pose", "orientation_offsets", "rotated_about_target"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ProtocolConfig:
    """The acquisition plan (defaults: the paper's numbers)."""

    rotation_deg: float = field(
        default=10.0,
        metadata={"doc": "Orientation corners: ± this about each probe axis.", "ge": 0, "le": 45},
    )
    translation_mm: float = field(
        default=3.0,
        metadata={
            "doc": "In-plane position corners: ± this laterally and axially.",
            "ge": 0,
            "le": 20,
        },
    )
    sweep_half_length_mm: float = field(
        default=10.0,
        metadata={"doc": "Each sweep runs ± this along the elevational axis.", "gt": 0, "le": 50},
    )
    frames_per_sweep: int = field(
        default=21, metadata={"doc": "Frames per sweep (evenly spaced).", "ge": 3, "le": 401}
    )
    target_depth_mm: float = field(
        default=20.0,
        metadata={
            "doc": "Depth of the target (sphere centre, cone apex) in the image at the "
            "nominal pose.",
            "gt": 0,
            "le": 200,
        },
    )
    teaching_error_mm: float = field(
        default=2.0,
        metadata={
            "doc": "Simulation: 1 σ error of the operator-taught nominal pose.",
            "ge": 0,
            "le": 20,
        },
    )
    touches_per_vertex: int = field(
        default=6, metadata={"doc": "Stylus touches per cone vertex.", "ge": 1, "le": 50}
    )
    touch_tilt_deg: float = field(
        default=20.0,
        metadata={"doc": "Tilt of the stylus from vertical across the touches.", "ge": 0, "le": 60},
    )


def orientation_offsets(rotation_deg: float) -> Array:
    """The nine orientations of the plan as rotations about the probe axes, (9, 3, 3).

    Index 0 is the nominal orientation; 1–8 the (±r, ±r, ±r) corners as extrinsic x-y-z
    Euler angles in the image frame.
    """
    r = np.radians(rotation_deg)
    corners = [np.zeros(3)] + [np.array(s) * r for s in itertools.product((-1, 1), repeat=3)]
    return se3.matrix_from_euler(np.array(corners))


def facing_pose(
    p_base_target: ArrayLike, depth: float, lateral_axis: ArrayLike = (0, 1, 0)
) -> Array:
    """``T_base_us`` (4, 4) of a probe looking straight down at a target.

    The image's axial axis (y) points down (−z of base), its lateral axis (x) along
    ``lateral_axis`` (projected horizontal), and the target lies on the image's centre
    line ``depth`` metres below the transducer face.
    """
    y = np.array([0.0, 0.0, -1.0])
    x = np.asarray(lateral_axis, dtype=float)
    x = x - x.dot(y) * y
    x /= np.linalg.norm(x)
    R = np.column_stack([x, y, np.cross(x, y)])
    return se3.make(R, np.asarray(p_base_target, dtype=float) - depth * y)


def rotated_about_target(T_base_us: Array, R_offset: Array, depth: float) -> Array:
    """Turn a facing pose by ``R_offset`` (about the image axes) about the target point at
    ``(0, depth, 0)`` in the image, so the target stays where it is in the image."""
    T_us_target = se3.make(np.eye(3), [0.0, depth, 0.0])
    return T_base_us @ T_us_target @ se3.make(R_offset, np.zeros(3)) @ se3.invert(T_us_target)
