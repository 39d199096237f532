"""Comparisons with the twin's ground truth, in one place: how far an estimated
``T_ee_us`` (or any transform) is from the true one, in the three measures every report
uses (DESIGN.md §3: ground truth is kept apart from what the pipeline sees; these are
only ever computed after the pipeline has answered)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calib import se3

from .experiment import image_points
from .scenario import Scenario

__all__ = ["image_error_mm", "mount_error", "transform_difference"]

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
