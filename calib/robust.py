"""Robust statistics of sphere centres: which localizations of one sphere agree.

Used by the calibration's outlier stage (paper, "Calibration") and by the localizer's
consensus step, which searches a sweep whose centre disagrees with its siblings' again
about their consensus.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["outlier_limit", "robust_inliers"]

Array = NDArray[np.float64]
_MM = 1e3


def outlier_limit(dist_mm: Array, floor_mm: float) -> float:
    """Distance from the centroid beyond which a centre is an outlier:
    ``max(floor_mm, 3 · 1.4826 · MAD)`` of the distances (a robust 3σ)."""
    mad = float(np.median(np.abs(dist_mm - np.median(dist_mm)))) if len(dist_mm) else 0.0
    return max(floor_mm, 3.0 * 1.4826 * mad)


def robust_inliers(points: Array, *, floor_mm: float = 2.0) -> NDArray[np.bool_]:
    """Centres (n, 3, metres) of one sphere that agree with their centroid: the outlier
    test of :func:`calibrate`, repeated with the centroid of the retained ones until the
    retained set settles."""
    keep = np.ones(len(points), dtype=bool)
    for _ in range(10):
        if not keep.any():
            break
        d = np.linalg.norm(points - points[keep].mean(axis=0), axis=1) * _MM
        new = d <= outlier_limit(d[keep], floor_mm)
        if np.array_equal(new, keep):
            break
        keep = new
    return keep
