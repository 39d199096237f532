"""A scenario's settings as the method's (:mod:`calib.pipeline`): the one place the test
bench maps its scenario onto what the method takes."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from calib.calibration.uncertainty import UncertaintyInputs, image_grid
from calib.calibration.verdict import Requirements
from calib.pipeline import MethodInputs, MethodSettings, declared_uncertainty
from calib.sound import speed_ratio
from sim_us.beam import axial_fwhm_m

from .scenario import Scenario, layout_sigma_mm

__all__ = [
    "axial_scale",
    "image_points",
    "method_inputs",
    "method_settings",
    "requirements",
    "scenario_uncertainty",
    "stated_radius",
]

Array = NDArray[np.float64]


def stated_radius(scenario: Scenario) -> float:
    """The sphere radius (m) the pipeline is given: the CAD's, off by
    ``phantom.stated_radius_error_mm`` when a user's mistake is simulated."""
    p = scenario.phantom
    return (p.sphere_radius_mm + p.stated_radius_error_mm) * 1e-3


def axial_scale(scenario: Scenario) -> float:
    """The axial spacing's correction factor of a scenario (:func:`calib.sound.
    speed_ratio`)."""
    return speed_ratio(
        correction=scenario.imaging.sound_speed_correction,
        medium=scenario.medium.kind,
        temperature_c=scenario.medium.temperature_c,
        assumed_speed_m_s=scenario.imaging.assumed_speed_m_s,
    )


def image_points(scenario: Scenario, n: int = 21) -> Array:
    """An n × n grid of points (n², 3) covering the scenario's image, metres in the
    ``us`` frame (:func:`calib.calibration.uncertainty.image_grid`)."""
    return image_grid(scenario.imaging.width_mm * 1e-3, scenario.imaging.depth_mm * 1e-3, n=n)


def method_settings(scenario: Scenario) -> MethodSettings:
    """The method's settings of a scenario: its localizer, alternation and layout
    settings, touch-based refinement, the phantom's print specification, the probe's
    axial resolution and the arm's nominal model (a twin's own, or the settings ``uscal
    calibrate`` runs a recorded dataset with)."""
    return MethodSettings(
        localizer=scenario.localization,
        max_alternations=scenario.calibration.max_alternations,
        layout_sigma_mm=layout_sigma_mm(scenario),
        evaluation=scenario.evaluation,
        print_tolerance_mm=scenario.phantom.tolerance_position_mm,
        radius_tolerance_mm=scenario.phantom.tolerance_radius_mm,
        axial_fwhm_mm=axial_fwhm_m(scenario.imaging) * 1e3,
        mount_error_mm=scenario.calibration.mount_error_mm,
        mount_error_deg=scenario.calibration.mount_error_deg,
        nominal_dh=scenario.robot.nominal_table,
    )


def method_inputs(
    scenario: Scenario, *, cad_centres: Mapping[str, Array], T_coarse: Array | None
) -> MethodInputs:
    """The inputs of one acquisition's calibration under a scenario: its CAD sphere
    radius and axial scale (:func:`axial_scale`), the CAD centres and coarse mount
    given."""
    return MethodInputs(
        stated_radius(scenario),
        cad_centres,
        T_coarse,
        method_settings(scenario).alternation(axial_scale=axial_scale(scenario)),
    )


def requirements(scenario: Scenario) -> Requirements:
    """What the scenario asks of its calibrations' 95 % bounds (the verdict's last
    question; :mod:`calib.calibration.verdict`)."""
    return Requirements(
        scenario.calibration.require_image_mm, scenario.calibration.require_rotation_deg
    )


def scenario_uncertainty(
    scenario: Scenario,
    kinematic_residual_rms_mm: float = 0.0,
    kinematic_modes: Mapping[tuple[str, int], Array] | None = None,
) -> UncertaintyInputs:
    """:func:`calib.pipeline.declared_uncertainty` of a twin's scenario: its phantom's
    print tolerance as the print specification, its medium and speed-of-sound setting,
    and a DH refinement's residual and error at the sweeps' poses where one was made."""
    return declared_uncertainty(
        print_tolerance_mm=scenario.phantom.tolerance_position_mm,
        sound_speed_correction=scenario.imaging.sound_speed_correction,
        medium=scenario.medium.kind,
        temperature_c=scenario.medium.temperature_c,
        assumed_speed_m_s=scenario.imaging.assumed_speed_m_s,
        kinematic_residual_rms_mm=kinematic_residual_rms_mm,
        radius_tolerance_mm=scenario.phantom.tolerance_radius_mm,
        axial_fwhm_mm=axial_fwhm_m(scenario.imaging) * 1e3,
        kinematic_modes=kinematic_modes,
        mount_error_mm=scenario.calibration.mount_error_mm,
        mount_error_deg=scenario.calibration.mount_error_deg,
    )
