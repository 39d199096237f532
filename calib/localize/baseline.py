"""The baseline the paper argues against: sphere localization with one fixed intensity
threshold (as in Li et al. and Ryu et al.).

Per sweep: the frames are stacked at their offsets (as :func:`calib.localize.stack_sweep`
does), every pixel at or above one absolute grey level ``fixed_threshold`` is a bright
voxel, and a least-squares sphere of the known radius (scipy) is fitted to each of the
largest 3D-connected sets of bright voxels; the set it fits best is the sphere's echo.
The threshold is tuned once, at the nominal gain and depth
(``scenarios/tune_fixed_threshold.yaml``), and then kept — which is exactly what breaks
when the gain, depth or machine changes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage, optimize

from ..image import pixel_to_us
from ..records import Sweep
from .settings import LocalizerConfig, SweepLocalization, frame_offsets

__all__ = ["localize_sphere_fixed_threshold"]

Array = NDArray[np.float64]

#: Fewer bright voxels than this in a set: not a sphere's echo (a cap of 5 mm radius
#: gives hundreds).
_MIN_VOXELS = 20
#: The largest bright sets tried; the one a sphere of the known radius fits best wins
#: (the tank floor or the base plate can be larger than the cap).
_CANDIDATES = 5


def _fit_sphere(P: Array, radius: float) -> tuple[Array, float]:
    """Least-squares centre of a sphere of known radius through points (n, 3); its RMS
    residual. Starts one radius below the points' centroid: the echo is the cap facing
    the probe (smaller y)."""
    start = P.mean(axis=0) + np.array([0.0, radius, 0.0])
    fit = optimize.least_squares(
        lambda c: np.linalg.norm(P - c, axis=1) - radius, start, method="lm", x_scale=radius
    )
    return fit.x, float(np.sqrt(np.mean(fit.fun**2)))


def _localize_one(
    sweep: Sweep, T_ee_us: Array | None, radius: float, level: int, axial_scale: float
) -> SweepLocalization:
    bright = sweep.images >= level
    labels, n = ndimage.label(bright, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return _rejected(sweep, f"no pixel at or above the threshold {level}")
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    candidates = [int(c) for c in np.argsort(sizes)[::-1][:_CANDIDATES] if sizes[c] >= _MIN_VOXELS]
    if not candidates:
        return _rejected(sweep, f"largest bright set {sizes.max()} voxels < {_MIN_VOXELS}")
    W = sweep.images.shape[2]
    sx, sy = sweep.spacing
    offsets = frame_offsets(sweep, T_ee_us)
    objects = ndimage.find_objects(labels)
    best = None
    for c in candidates:
        # The set's voxels (within its bounding box), as points in the reference frame.
        box = objects[c - 1]
        j, rows, cols = np.nonzero(labels[box] == c)
        j, rows, cols = j + box[0].start, rows + box[1].start, cols + box[2].start
        P = pixel_to_us(rows, cols, W, (sx, sy * axial_scale)) + offsets[j]
        centre, rms = _fit_sphere(P, radius)
        if best is None or rms < best[1]:
            best = (centre, rms)
    centre, rms = best
    return SweepLocalization(
        sweep.target, sweep.pose_id, centre, -rms, float("nan"), float("nan"), True
    )


def _rejected(sweep: Sweep, reason: str) -> SweepLocalization:
    return SweepLocalization(
        sweep.target,
        sweep.pose_id,
        np.full(3, np.nan),
        float("-inf"),
        float("nan"),
        float("nan"),
        False,
        reason,
    )


def localize_sphere_fixed_threshold(
    sweeps: Sequence[Sweep],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    *,
    axial_scale: float = 1.0,
) -> list[SweepLocalization]:
    """Localize one sphere in each sweep with the fixed threshold ``cfg.fixed_threshold``
    (grey level); centres in each sweep's reference frame, as
    :func:`calib.localize.localize_sphere` returns them (``score`` is minus the fit's
    RMS residual, metres)."""
    return [_localize_one(s, T_ee_us, radius, cfg.fixed_threshold, axial_scale) for s in sweeps]
