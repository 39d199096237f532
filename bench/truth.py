"""Comparisons with the twin's ground truth, in one place: how far an estimated
``T_ee_us`` (or any transform) is from the true one, in the three measures every report
uses, and the true sphere sections the report draws beside those found (DESIGN.md §3:
ground truth is kept apart from what the pipeline sees; these are only ever computed
after the pipeline has answered)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.calibration.alternation import AlternationResult
from calib.dh import DHTable
from calib.kinematics import kinematic_gauge
from calib.localize import SweepLocalization
from calib.records import Sweep

from .acquire_sim import SimulatedAcquisition
from .config.method import axial_scale, image_points, stated_radius
from .config.scenario import Scenario
from .snapshot import LocalizationSnapshot, dataset_snapshot

__all__ = [
    "image_error_mm",
    "localization_errors",
    "mount_error",
    "snapshot_of",
    "transform_difference",
    "true_centre_in_sweep",
]

Array = NDArray[np.float64]


def transform_difference(T_a: Array, T_b: Array) -> dict[str, float]:
    """Rotation angle (°) and translation distance (mm) between two transforms."""
    return {
        "rotation_deg": float(np.degrees(se3.rotation_angle(T_a, T_b))),
        "translation_mm": float(se3.translation_distance(T_a, T_b)) * 1e3,
    }


def image_error_mm(scenario: Scenario, T_est: Array, T_true: Array) -> float:
    """Mean distance (mm) over a grid covering the image between each image point mapped
    with the true and with the estimated ``T_ee_us``: the error a user sees."""
    P = image_points(scenario)
    d = np.linalg.norm(se3.apply(T_est, P) - se3.apply(T_true, P), axis=1)
    return float(np.mean(d)) * 1e3


def mount_error(scenario: Scenario, T_est: Array, T_true: Array) -> dict[str, float]:
    """An estimated ``T_ee_us`` against the truth: rotation (°), translation (mm) and
    the mean image error (mm, :func:`image_error_mm`)."""
    return transform_difference(T_est, T_true) | {
        "image_mm": image_error_mm(scenario, T_est, T_true)
    }


def snapshot_of(
    scenario: Scenario,
    acq: SimulatedAcquisition,
    alt: AlternationResult,
    truth=None,
) -> LocalizationSnapshot | None:
    """The report's look at the first sphere: its first accepted sweep's frames with the
    sections found by ``alt`` (and the true ones when ``truth`` is the twin's), and the
    sphere's radial profile over its sweeps."""
    true_centres = None
    if truth is not None:

        def true_centres(target: str, sweep) -> Array:
            T_true = acq.T_base_ee_true[(target, sweep.pose_id)] @ truth.T_ee_us
            return se3.apply(se3.invert(T_true), truth.landmarks_base[target])

    return dataset_snapshot(
        acq.dataset,
        alt,
        stated_radius(scenario),
        scenario.localization,
        axial_scale(scenario),
        true_centres,
    )


def true_centre_in_sweep(
    acq: SimulatedAcquisition, truth, target: str, sweep: Sweep
) -> NDArray[np.float64]:
    """Truth: a sphere's centre (3,) in the sweep's true reference frame (the true
    flange pose of its reference frame and the true mount), where a localization of it
    should land."""
    T = acq.T_base_ee_true[(target, sweep.pose_id)][sweep.reference_index] @ truth.T_ee_us
    return se3.apply(se3.invert(T), truth.landmarks_base[target])


def localization_errors(
    acq: SimulatedAcquisition,
    truth,
    localizations: Mapping[str, Sequence[SweepLocalization]],
) -> tuple[Array, int, int]:
    """Truth: the distance (mm) of each accepted localization from the true centre in its
    sweep's true reference frame (:func:`true_centre_in_sweep`), with how many sweeps
    there were and how many the localizer rejected."""
    errors, n, rejected = [], 0, 0
    for target, locs in localizations.items():
        for sweep, loc in zip(acq.dataset.of(target), locs, strict=True):
            n += 1
            if not loc.accepted:
                rejected += 1
                continue
            p_true = true_centre_in_sweep(acq, truth, target, sweep)
            errors.append(float(np.linalg.norm(loc.centre - p_true)) * 1e3)
    return np.array(errors), n, rejected


def equivalent_mount(
    scenario: Scenario, acq: SimulatedAcquisition, truth, model: DHTable | None = None
) -> Array | None:
    """Truth: the ``T_ee_us`` that best maps the image through the kinematic model the
    poses were computed with (``model``; default the controller's) when the twin's arm is
    not that model (the evaluation's kinematic gauge: a flange-side error of the model is
    indistinguishable from, and equivalent to, a mount error); None when it is."""
    model = scenario.robot.nominal_table if model is None else model
    if np.array_equal(model.as_array(), truth.dh_table.as_array()):
        return None
    q = np.concatenate([s.q[::10] for s in acq.dataset.sweeps])
    tool_points = se3.apply(truth.T_ee_us, image_points(scenario, 3))
    return kinematic_gauge(model, truth.dh_table, q, tool_points).G @ truth.T_ee_us
