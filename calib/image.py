"""The image frame ``us`` and its pixels (DESIGN.md §3): the one place that maps them.

Origin at the centre of the transducer face; x lateral (increasing column), y axial
(increasing row = depth), z = x × y (elevational). Pixel (row r, col c) of a W-column
image with spacing (sx, sy) sits at ``x = (c − (W − 1) / 2) · sx``, ``y = r · sy``, ``z = 0``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["pixel_axes", "pixel_to_us", "sphere_section", "us_to_pixel"]


def pixel_to_us(
    rows: ArrayLike, cols: ArrayLike, width_px: int, spacing: tuple[float, float]
) -> NDArray[np.float64]:
    """Points (..., 3), metres, us frame, of pixel coordinates (fractional allowed).

    Parameters
    ----------
    rows, cols : array_like, broadcast together
        Row (axial) and column (lateral) pixel coordinates.
    width_px : int
        Image width W in pixels.
    spacing : (sx, sy), metres

    Examples
    --------
    The centre column of a 151-pixel-wide image at row 100, 0.2 mm pixels: on the beam
    axis, 20 mm deep; :func:`us_to_pixel` maps it back.

    >>> p = pixel_to_us(100, 75, 151, (0.2e-3, 0.2e-3))
    >>> p.round(6)
    array([0.  , 0.02, 0.  ])
    >>> [float(v) for v in us_to_pixel(p, 151, (0.2e-3, 0.2e-3))]
    [100.0, 75.0]
    """
    rows, cols = np.broadcast_arrays(np.asarray(rows, dtype=float), np.asarray(cols, dtype=float))
    x, y = pixel_axes(rows, cols, width_px, spacing)
    return np.stack([x, y, np.zeros_like(rows)], axis=-1)


def pixel_axes(
    rows: ArrayLike, cols: ArrayLike, width_px: int, spacing: tuple[float, float]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The us-frame coordinates of columns and rows as separate axes: (x of each of
    ``cols``, y of each of ``rows``), metres (the mapping is separable, so a block of
    pixels needs only these; :func:`pixel_to_us` is built on it).

    Examples
    --------
    >>> x, y = pixel_axes([0, 100], [0, 75, 150], 151, (0.2e-3, 0.2e-3))
    >>> x.round(6), y.round(6)
    (array([-0.015,  0.   ,  0.015]), array([0.  , 0.02]))
    """
    sx, sy = spacing
    x = (np.asarray(cols, dtype=float) - (width_px - 1) / 2) * sx
    return x, np.asarray(rows, dtype=float) * sy


def us_to_pixel(
    P_us: ArrayLike, width_px: int, spacing: tuple[float, float]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fractional (rows, cols) of points (..., 3) in the us frame (z is ignored)."""
    P_us = np.asarray(P_us, dtype=float)
    sx, sy = spacing
    return P_us[..., 1] / sy, P_us[..., 0] / sx + (width_px - 1) / 2


def sphere_section(centre_us: ArrayLike, radius: float) -> tuple[float, float, float] | None:
    """Where a sphere (centre in the us frame, metres) cuts the image plane z = 0: the
    circle's centre (x, y) and radius, metres; None when it misses the plane.

    Examples
    --------
    A 5 mm sphere 20 mm deep, its centre 3 mm off the plane, shows a 4 mm section:

    >>> [round(v, 6) for v in sphere_section([0.0, 0.02, 0.003], 0.005)]
    [0.0, 0.02, 0.004]
    >>> sphere_section([0.0, 0.02, 0.006], 0.005) is None
    True
    """
    x, y, z = (float(v) for v in np.asarray(centre_us, dtype=float))
    if abs(z) >= radius:
        return None
    return x, y, float(np.sqrt(radius**2 - z**2))
