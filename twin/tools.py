"""Tools on the flange: the US probe in its holder, and the touch stylus.

Calibration scans carry the probe, touch measurements the stylus (paper, "Reference
Target Localization"); the scenario says which is mounted. The geometry here is the
twin's *truth*: the probe sits at the true ``T_ee_us`` and the stylus tip at the true tip
offset. Shapes are MuJoCo primitives so collisions can be checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from calib import se3

__all__ = ["ToolGeom", "ToolsConfig", "tool_geoms"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ToolsConfig:
    """Tools of the twin (true mounting and sizes)."""

    mounted: Literal["probe", "stylus"] = field(
        default="probe", metadata={"doc": "Tool on the flange: US probe or touch stylus."}
    )
    probe_mount_position_mm: tuple[float, float, float] = field(
        default=(0.8, -1.2, 158.0),
        metadata={"doc": "True origin of the image frame (transducer-face centre) in ee."},
    )
    probe_mount_rotation_deg: tuple[float, float, float] = field(
        default=(91.0, -0.8, 1.5),
        metadata={
            "doc": "True image-frame orientation in ee, extrinsic x-y-z Euler angles "
            "((90, 0, 0): image depth along the flange z axis)."
        },
    )
    probe_body_mm: tuple[float, float, float] = field(
        default=(45.0, 14.0, 100.0),
        metadata={
            "doc": "Probe housing: lateral width, elevational thickness, length.",
            "gt": 1,
            "le": 300,
        },
    )
    holder_radius_mm: float = field(
        default=30.0,
        metadata={"doc": "Radius of the holder between flange and probe.", "gt": 1, "le": 100},
    )
    stylus_tip_mm: tuple[float, float, float] = field(
        default=(0.5, -0.3, 165.0),
        metadata={
            "doc": "True stylus tip offset in ee (about as long as the probe, so the arm "
            "clears the tank walls)."
        },
    )
    stylus_radius_mm: float = field(
        default=4.0, metadata={"doc": "Stylus shaft radius.", "gt": 0.5, "le": 30}
    )
    contact_noise_mm: float = field(
        default=0.2,
        metadata={
            "doc": "Touch contact noise: 1 σ per axis of the true tip about the true vertex.",
            "ge": 0,
            "le": 5,
        },
    )

    @property
    def T_ee_us(self) -> Array:
        """True image-to-flange transform (4, 4)."""
        R = se3.matrix_from_euler(np.radians(self.probe_mount_rotation_deg))
        return se3.make(R, np.array(self.probe_mount_position_mm) * 1e-3)

    @property
    def p_ee_tip(self) -> Array:
        """True stylus tip (3,), metres, ee frame."""
        return np.array(self.stylus_tip_mm) * 1e-3


@dataclass(frozen=True)
class ToolGeom:
    """A primitive attached to the flange.

    ``shape`` is a MuJoCo primitive; ``size`` follows MuJoCo (box: half extents;
    cylinder/capsule: radius, half length along local z); ``T_ee_geom`` its pose.
    """

    name: str
    shape: Literal["box", "cylinder", "capsule"]
    size: tuple[float, ...]
    T_ee_geom: Array


def _segment(
    name: str, shape: Literal["cylinder", "capsule"], radius: float, a: Array, b: Array
) -> ToolGeom:
    """A cylinder or capsule from point a to point b (ee frame)."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length
    # Any rotation taking local z onto the axis will do for a body of revolution.
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return ToolGeom(name, shape, (radius, length / 2), se3.make(R, (a + b) / 2))


def tool_geoms(cfg: ToolsConfig) -> tuple[ToolGeom, ...]:
    """Primitives of the mounted tool, in the flange frame."""
    if cfg.mounted == "stylus":
        tip = cfg.p_ee_tip
        neck = 0.85 * tip
        direction = tip / np.linalg.norm(tip)
        r = cfg.stylus_radius_mm * 1e-3
        return (
            _segment("stylus_shaft", "cylinder", r, np.zeros(3), neck),
            # The needle's capsule ends exactly at the tip point.
            _segment("stylus_tip", "capsule", 1e-3, neck, tip - 1e-3 * direction),
        )
    width, thickness, length = (v * 1e-3 for v in cfg.probe_body_mm)
    T_ee_us = cfg.T_ee_us
    body = ToolGeom(
        "probe_body",
        "box",
        (width / 2, length / 2, thickness / 2),
        T_ee_us @ se3.make(np.eye(3), [0.0, -length / 2, 0.0]),
    )
    probe_top = se3.apply(T_ee_us, [0.0, -length, 0.0])
    holder = _segment(
        "probe_holder",
        "cylinder",
        cfg.holder_radius_mm * 1e-3,
        np.zeros(3),
        np.array([0.0, 0.0, max(probe_top[2], 1e-3)]),
    )
    return holder, body
