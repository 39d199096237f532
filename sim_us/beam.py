"""The beam: point spread function and elevation profile (slice thickness vs depth).

Lateral and axial resolution are the configured FWHM of the envelope PSF (Gaussian,
σ = FWHM / 2.355). The elevation profile is Gaussian with a depth-dependent FWHM, the
slice thickness ``ST(y) = sqrt(ST_f² + (H · |y − F| / F)²)``: the aperture height ``H`` at
the face, ``ST_f`` at the focus ``F``, growing linearly past it (geometric beam). Laterally
the first side lobe of the aperture sits at a fixed multiple of the lateral FWHM.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .probe import ProbeConfig

__all__ = [
    "FWHM_PER_SIGMA",
    "SIDE_LOBE_OFFSET_PER_FWHM",
    "elevation_offsets",
    "elevation_weights",
    "slab_edge_shares",
    "slice_thickness",
]

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))  # 2.355

# Lateral beam of a rectangular aperture D at depth z: one-way amplitude sinc(π D x / λz).
# The first side lobe sits at the first maximum of |sinc|, u = 4.4934 (tan u = u), i.e.
# x = 1.4303 λz/D; the two-way (transmit × receive) envelope sinc² is at half maximum at
# u = 1.3916, a FWHM of 0.8859 λz/D. With a constant F-number (dynamic receive focus,
# growing aperture) λz/D is the same at every depth, so the side lobe sits at a fixed
# multiple of the configured lateral FWHM: 1.4303 / 0.8859 = 1.6145.
SIDE_LOBE_OFFSET_PER_FWHM = 4.493409457909064 / (2.0 * 1.3915573782515103)

# Sub-planes cover ± this many half slice thicknesses of the widest beam in view
# (the two-way intensity weight there is 2^(-2c²) ≈ 0.11 of the centre's).
_COVERAGE = 1.25


def slice_thickness(
    probe: ProbeConfig, depth_m: NDArray[np.float64] | float
) -> NDArray[np.float64]:
    """Elevation FWHM (m) at depth(s) ``depth_m``."""
    H = probe.elevation_aperture_mm * 1e-3
    F = probe.elevation_focus_mm * 1e-3
    st_f = probe.slice_thickness_mm * 1e-3
    return np.sqrt(st_f**2 + (H * np.abs(np.asarray(depth_m) - F) / F) ** 2)


def elevation_offsets(
    probe: ProbeConfig, max_depth_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Elevation offsets z (m) of the sub-planes and the slab width each stands for.

    The planes crowd near z = 0, where the focal slice is thin, and thin out towards the
    wide beam near the face and far past the focus.
    """
    n = probe.elevation_planes
    if n == 1:
        return np.zeros(1), np.ones(1)
    st_max = float(np.max(slice_thickness(probe, np.array([0.0, max_depth_m]))))
    half = _COVERAGE * st_max / 2
    # Symmetric, denser near the centre: z = half · sinh(a u) / sinh(a), u uniform in [-1, 1].
    # a = 3 puts the first planes within ≈ 0.3 mm of the centre for a 4 mm aperture, so the
    # focal slice (≈ 0.7 mm) is sampled by more than one plane.
    a = 3.0
    u = np.linspace(-1.0, 1.0, n)
    z = half * np.sinh(a * u) / np.sinh(a)
    edges = np.concatenate(
        [[z[0] - (z[1] - z[0]) / 2], (z[1:] + z[:-1]) / 2, [z[-1] + (z[-1] - z[-2]) / 2]]
    )
    return z, np.diff(edges)


def elevation_weights(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    dz: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Intensity weights (planes, depths) of each sub-plane at each depth.

    The two-way elevation amplitude profile is ``b(z; y) = exp(−4 ln2 z² / ST(y)²)``; a
    sub-plane of width dz holds ``b² dz`` of the beam's energy. Weights are normalised
    per depth so that a flat reflector across the whole beam echoes with its full
    strength at every depth (a smaller object is dimmed: partial volume).
    """
    st = slice_thickness(probe, depths_m)[None, :]
    b2 = np.exp(-8.0 * np.log(2.0) * z[:, None] ** 2 / st**2)
    energy = b2 * dz[:, None]
    return energy / energy.sum(axis=0, keepdims=True)


def slab_edge_shares(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    dz: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Share (planes, depths) of a slab's beam-profile density at its low-z edge.

    Sub-plane k stands for the slab ``z_k ± dz_k / 2``; within it the two-way intensity
    profile ``b²(z)`` is taken linear between its values at the two edges (piecewise-linear
    integration over elevation). Returns ``b²(lo) / (b²(lo) + b²(hi))``: 0.5 for the slab in
    the middle of the beam, less for slabs on its positive flank, more on its negative one.
    """
    st = slice_thickness(probe, depths_m)[None, :]
    lo = np.exp(-8.0 * np.log(2.0) * (z - dz / 2)[:, None] ** 2 / st**2)
    hi = np.exp(-8.0 * np.log(2.0) * (z + dz / 2)[:, None] ** 2 / st**2)
    return lo / np.maximum(lo + hi, 1e-300)
