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

__all__ = ["ToolGeom", "ToolsConfig", "holder_deflection", "tool_geoms", "tool_mass_kg"]

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
            "doc": "Touch contact noise: 1 σ per axis of the true tip about the true vertex "
            "(where the rounded tip seats on a printed, slightly blunt vertex). Plausible "
            "0.1–0.3 mm: four-point tool-calibration residuals of 0.13–0.27 mm mean in robot "
            "tool-calibration reports, ≈ 0.3 mm RMS for pivot calibration.",
            "ge": 0,
            "le": 5,
        },
    )

    probe_mass_kg: float = field(
        default=0.0,
        metadata={
            "doc": "Mass of probe, cable share and holder on the flange: the payload whose "
            "weight loads the joints (robot.joint_compliance_scale), spread over the "
            "probe and holder shapes (0 = massless tool). Plausible 0.3–0.5 kg "
            "(a linear probe with its cable ≈ 0.2–0.3 kg plus a printed holder).",
            "ge": 0,
            "le": 3,
        },
    )
    stylus_mass_kg: float = field(
        default=0.0,
        metadata={
            "doc": "Mass of the touch stylus and its adapter (payload during touches; "
            "0 = massless). Plausible 0.2–0.4 kg (a steel shaft and an aluminium flange "
            "adapter).",
            "ge": 0,
            "le": 3,
        },
    )
    holder_deflection_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Probe-holder compliance: the printed holder is a cantilever from the "
            "flange to the probe's clamp bent by the probe's weight, δ = F L³/(3EI) with "
            "tip tilt θ = F L²/(2EI) = 3δ/(2L); F is the weight's component across the "
            "holder axis, so it depends on the direction of gravity in the flange "
            "frame. This is δ with gravity fully across the holder (0 = rigid). The "
            "scanner images through the loaded mount; the ground-truth T_ee_us is the "
            "unloaded one (with the probe pointing down they coincide). Plausible "
            "0.04–0.1 mm (0.25 kg at 12 cm on a 20 × 20 mm solid PLA arm, E 2.0–2.9 GPa), "
            "more with sparse infill.",
            "ge": 0,
            "le": 2,
        },
    )
    stylus_force_n: float = field(
        default=0.0,
        metadata={
            "doc": "Hand-guiding force across the stylus while its tip sits on a vertex: "
            "the shaft bends by δ = F L³/(3EI) (L the tip's distance from the flange, I "
            "of a solid round shaft of stylus_radius_mm) in a direction drawn per touch; "
            "on top of contact_noise_mm (0 = off). Plausible 2–5 N.",
            "ge": 0,
            "le": 50,
        },
    )
    stylus_modulus_gpa: float = field(
        default=200.0,
        metadata={
            "doc": "Young's modulus of the stylus shaft (steel 200 GPa, aluminium 70, "
            "carbon-fibre tube ≈ 70–130).",
            "gt": 1,
            "le": 1000,
        },
    )

    @property
    def holder_length_m(self) -> float:
        """Length of the probe holder along the flange z axis (flange to the top of the
        probe housing), metres."""
        length = self.probe_body_mm[2] * 1e-3
        probe_top = se3.apply(self.T_ee_us, [0.0, -length, 0.0])
        return float(max(probe_top[2], 1e-3))

    @property
    def stylus_bending_m(self) -> float:
        """Tip deflection (m) of the stylus shaft under ``stylus_force_n`` across it: a
        cantilever of length |tip| and solid round section, δ = F L³ / (3 E I),
        I = π r⁴ / 4."""
        if self.stylus_force_n == 0:
            return 0.0
        length = float(np.linalg.norm(self.p_ee_tip))
        inertia = np.pi * (self.stylus_radius_mm * 1e-3) ** 4 / 4
        return self.stylus_force_n * length**3 / (3 * self.stylus_modulus_gpa * 1e9 * inertia)

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
    holder = _segment(
        "probe_holder",
        "cylinder",
        cfg.holder_radius_mm * 1e-3,
        np.zeros(3),
        np.array([0.0, 0.0, cfg.holder_length_m]),
    )
    return holder, body


def tool_mass_kg(cfg: ToolsConfig) -> float:
    """Mass of the mounted tool (payload), kg."""
    return cfg.stylus_mass_kg if cfg.mounted == "stylus" else cfg.probe_mass_kg


def holder_deflection(R_base_ee: Array, cfg: ToolsConfig) -> Array:
    """The printed holder's elastic deflection under the probe's weight at a flange
    orientation: ``T_ee_loaded`` (4, 4), the loaded mount is ``T_ee_loaded @ T_ee_us``.

    A cantilever along the flange z axis from the flange to the clamp (length L =
    :attr:`ToolsConfig.holder_length_m`), end-loaded by the weight's component across the
    axis, F = m g sin β (β the angle between gravity and the axis): the clamp moves by
    δ = F L³/(3EI) along that component and the probe tilts by θ = F L²/(2EI) = 3δ/(2L)
    about ẑ × û (the holder's end turns towards the load). δ at β = 90° is
    ``holder_deflection_mm``; the probe beyond the clamp is rigid.
    """
    g_ee = np.asarray(R_base_ee, dtype=float).T @ np.array([0.0, 0.0, -1.0])
    across = g_ee - g_ee[2] * np.array([0.0, 0.0, 1.0])
    s = float(np.linalg.norm(across))  # sin β
    if s < 1e-12 or cfg.holder_deflection_mm == 0:
        return np.eye(4)
    u = across / s
    length = cfg.holder_length_m
    delta = cfg.holder_deflection_mm * 1e-3 * s
    theta = 1.5 * delta / length
    R = se3.matrix_from_rotvec(theta * np.cross([0.0, 0.0, 1.0], u))
    c = np.array([0.0, 0.0, length])
    # p' = c + δ u + R (p − c): the clamp moves by δ u, the probe turns about it.
    return se3.make(R, c + delta * u - R @ c)
