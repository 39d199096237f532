"""Sweeps the twin renders frame by frame at chosen image poses (the localizer's tests
and the numba warm-up)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from calib import se3
from calib.records import Sweep


def render_sweep(
    twin, imager, T_base_us: Iterable[np.ndarray], pose_id: int = 0, target: str = "sphere_1"
) -> tuple[Sweep, np.ndarray]:
    """The arm moved so that the image lies at each pose of ``T_base_us`` (through the
    true mount), a frame grabbed at each: the sweep (the poses the arm reports, no joint
    angles) and the arm's true flange poses (n, 4, 4)."""
    T_us_ee = se3.invert(twin.truth.T_ee_us)
    images, poses, true = [], [], []
    for T in T_base_us:
        reading = twin.robot.move_to(T @ T_us_ee)
        images.append(imager.grab().image)
        poses.append(reading.T_base_ee)
        true.append(twin.robot.truth.T_base_ee)
    n = len(images)
    sweep = Sweep(
        target, pose_id, np.array(images), imager.spacing, np.zeros((n, 6)), np.array(poses)
    )
    return sweep, np.array(true)
