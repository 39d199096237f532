"""Every error source of the twin, declared in one place.

A source is a physical imperfection of the real rig that the twin can switch on and off:
one or more scenario keys and the value of each that turns the source off (an ideal rig in
that respect). ``uscal budget`` switches them one at a time; ``docs/scenarios.md`` and
``docs/paper-comparison.md`` give each key's plausible range and where it comes from.

What is *not* here is the measurement itself (probe resolution, speckle, pixel size,
the acquisition plan): those stay as the scenario sets them in every budget run, so the
error-free rig still images through a real beam.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .scenario import Scenario

__all__ = ["ERROR_SOURCES", "ErrorSource", "source_named", "value_at"]


@dataclass(frozen=True)
class ErrorSource:
    """One source: ``name`` (as ``--sources`` takes it), a short ``title``, and the
    scenario keys with the value that switches the source off."""

    name: str
    title: str
    off: tuple[tuple[str, Any], ...]

    def present_in(self, scenario: Scenario) -> bool:
        """Whether any of the source's keys differs from its off value in ``scenario``."""
        return any(not _same(value_at(scenario, key), value) for key, value in self.off)

    def overrides(self) -> list[tuple[str, Any]]:
        """``(key path, off value)`` pairs that switch the source off."""
        return list(self.off)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def value_at(scenario: Scenario, key: str) -> Any:
    """The value of a key path (``section.key``) in a validated scenario."""
    node: Any = scenario
    for part in key.split("."):
        node = getattr(node, part)
    return node


#: The twin's error sources, grouped as the rig is: arm, tools and touches, the image
#: against the pose, scanner and medium, printed phantom.
ERROR_SOURCES: tuple[ErrorSource, ...] = (
    # ---- the arm
    ErrorSource("kinematics", "arm kinematics (DH) off nominal", (("robot.dh_error_scale", 0.0),)),
    ErrorSource("repeatability", "joint repeatability", (("robot.joint_repeatability_deg", 0.0),)),
    ErrorSource("encoder_noise", "joint encoder noise", (("robot.encoder_noise_deg", 0.0),)),
    ErrorSource(
        "joint_compliance",
        "joints twisted by gravity and payload torques",
        (("robot.joint_compliance_scale", 0.0),),
    ),
    ErrorSource(
        "gear_error",
        "harmonic-drive transmission error and lost motion",
        (("robot.transmission_error_arcmin", 0.0), ("robot.lost_motion_arcmin", 0.0)),
    ),
    ErrorSource("thermal_drift", "arm warming up over a session", (("robot.thermal_rise_k", 0.0),)),
    # ---- the image against the pose
    ErrorSource(
        "vibration", "residual vibration at the grab", (("robot.residual_vibration_mm", 0.0),)
    ),
    ErrorSource(
        "stale_frames",
        "frames showing the pose before the move",
        (("robot.stale_frame_probability", 0.0),),
    ),
    # ---- tools and touches
    ErrorSource(
        "holder_compliance",
        "printed holder bending under the probe's weight",
        (("tools.holder_deflection_mm", 0.0),),
    ),
    ErrorSource("stylus_contact", "stylus seating on a vertex", (("tools.contact_noise_mm", 0.0),)),
    ErrorSource(
        "stylus_bending", "stylus bending under the hand's force", (("tools.stylus_force_n", 0.0),)
    ),
    # ---- scanner and medium
    ErrorSource(
        "speed_of_sound",
        "speed of sound not corrected (water vs the scanner's 1540 m/s)",
        (("imaging.sound_speed_correction", True),),
    ),
    ErrorSource(
        "water_drift",
        "water temperature drifting during a session",
        (("medium.temperature_drift_c_per_h", 0.0),),
    ),
    ErrorSource(
        "scanner_scale",
        "pixel spacing off its reported value",
        (("imaging.pixel_scale_error_pct", [0.0, 0.0]),),
    ),
    ErrorSource(
        "image_offsets",
        "image origin below the face, image centre off the array centre",
        (("imaging.image_origin_offset_mm", 0.0), ("imaging.lateral_offset_mm", 0.0)),
    ),
    ErrorSource("side_lobes", "side lobes of the lateral beam", (("imaging.side_lobe_db", None),)),
    ErrorSource("ring_down", "ring-down below strong echoes", (("imaging.ring_down_cycles", 0.0),)),
    ErrorSource("electronic_noise", "electronic noise", (("imaging.noise_db", -200.0),)),
    # ---- printed phantom
    ErrorSource(
        "print_surface",
        "print layer lines and surface roughness",
        (("phantom.print_layer_mm", 0.0), ("phantom.print_roughness_ra_um", 0.0)),
    ),
    ErrorSource(
        "print_shape",
        "printed cone and prism off their CAD shape (shrinkage, warp, sag)",
        (
            ("phantom.print_shrinkage_pct", 0.0),
            ("phantom.print_shrinkage_z_pct", 0.0),
            ("phantom.print_warp_mm", 0.0),
            ("phantom.print_sag_mm", 0.0),
        ),
    ),
    ErrorSource(
        "sphere_roundness", "printed spheres out of round", (("phantom.sphere_roundness_mm", 0.0),)
    ),
    ErrorSource(
        "session_shift",
        "phantom moved between a dataset's touches and its sweeps",
        (("evaluation.session_shift_mm", 0.0),),
    ),
    ErrorSource(
        "print_tolerance",
        "sphere radii and positions off the CAD",
        (("phantom.tolerance_radius_mm", 0.0), ("phantom.tolerance_position_mm", 0.0)),
    ),
)


def source_named(name: str) -> ErrorSource:
    """The source called ``name`` (KeyError when there is none)."""
    for s in ERROR_SOURCES:
        if s.name == name:
            return s
    raise KeyError(name)
