"""The beam: point spread function and elevation profile (slice thickness vs depth).

By default every width follows from the transducer (:mod:`sim_us.transducer`): the axial
FWHM from the pulse, the lateral profile (main lobe and side lobes) per depth from the
focused aperture, the elevation profile (slice thickness, and the side lobes through which
a bright reflector beside the slice still shows) per depth from the lensed element height,
and the echo of a surface against its tilt from both apertures (:func:`mirror_of`). A
probe measured on a wire can state its widths instead: a Gaussian PSF (σ = FWHM / 2.355)
of the stated lateral and axial FWHM, and the geometric slice ``ST(y) = sqrt(ST_f² + (H ·
|y − F| / F)²)`` (the aperture height ``H`` at the face, ``ST_f`` at the focus ``F``) with
a Gaussian elevation profile. Laterally the first side lobe of a two-way sinc² beam sits at
a fixed multiple of its FWHM.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .materials import Material, attenuation_db_per_m
from .probe import ProbeConfig
from .transducer import (
    BeamTables,
    MirrorTables,
    band_loss,
    beam_tables,
    mirror_tables,
    transducer,
)
from .transducer import axial_fwhm_m as pulse_axial_fwhm_m

__all__ = [
    "FWHM_PER_SIGMA",
    "SIDE_LOBE_OFFSET_PER_FWHM",
    "SURFACE_KERNEL_FLOOR",
    "axial_fwhm_m",
    "band_attenuation_db",
    "beam_of",
    "elevation_amplitude",
    "elevation_amplitude_at",
    "elevation_delay_at",
    "elevation_offsets",
    "elevation_weights",
    "flat_echo_gain",
    "lateral_amplitude",
    "lateral_fwhm_m",
    "mirror_of",
    "narrowest_lateral_fwhm_m",
    "scanline_step",
    "slab_edge_shares",
    "slice_thickness",
    "speckle_cell_gain",
]

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))  # 2.355

# Lateral beam of a rectangular aperture D at depth z: one-way amplitude sinc(π D x / λz).
# The first side lobe sits at the first maximum of |sinc|, u = 4.4934 (tan u = u), i.e.
# x = 1.4303 λz/D; the two-way (transmit × receive) envelope sinc² is at half maximum at
# u = 1.3916, a FWHM of 0.8859 λz/D. With a constant F-number (dynamic receive focus,
# growing aperture) λz/D is the same at every depth, so the side lobe sits at a fixed
# multiple of the configured lateral FWHM: 1.4303 / 0.8859 = 1.6145.
SIDE_LOBE_OFFSET_PER_FWHM = 4.493409457909064 / (2.0 * 1.3915573782515103)

# Sub-planes cover ± this many half slice thicknesses of the widest beam in view (the
# Gaussian's two-way intensity weight there is 2^(-2c²) ≈ 0.11 of the centre's; the lensed
# aperture's side lobes reach further: at 35 mm the paper probe's is -28 dB 3 mm out).
_COVERAGE = 1.25


def beam_of(probe: ProbeConfig, medium_speed_m_s: float | None = None) -> BeamTables:
    """The transducer's beam tables over the probe's depth range (cached): the imaging
    depth with room for a scale error (±10 %) and an image origin offset (≤ 5 mm).
    ``medium_speed_m_s``: the speed of sound where it images (None: the scanner's assumed
    speed); a scanner focuses for its own, so elsewhere its beam is out of focus
    (:mod:`sim_us.transducer`)."""
    return beam_tables(transducer(probe, medium_speed_m_s), _depth_range_m(probe))


def _depth_range_m(probe: ProbeConfig) -> float:
    return round(probe.depth_mm * 1.12e-3 + 5e-3, 4)


def mirror_of(probe: ProbeConfig, medium_speed_m_s: float | None = None) -> MirrorTables:
    """The echo of a tilted surface element through the probe's apertures (cached), from
    its datasheet figures whatever widths it states, in a medium of that speed (None: the
    scanner's)."""
    return mirror_tables(transducer(probe, medium_speed_m_s), _depth_range_m(probe))


def axial_fwhm_m(probe: ProbeConfig) -> float:
    """Axial FWHM (m): stated, or the pulse's."""
    if probe.axial_fwhm_mm is not None:
        return probe.axial_fwhm_mm * 1e-3
    return pulse_axial_fwhm_m(transducer(probe))


def lateral_fwhm_m(
    probe: ProbeConfig,
    depth_m: NDArray[np.float64] | float,
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Two-way lateral FWHM (m) at depth(s): stated, or the focused aperture's (in a
    medium of that speed; None: the scanner's)."""
    if probe.lateral_fwhm_mm is not None:
        return np.full(np.shape(depth_m), probe.lateral_fwhm_mm * 1e-3)
    return beam_of(probe, medium_speed_m_s).at("lateral_fwhm", depth_m)


def speckle_cell_gain(
    probe: ProbeConfig,
    depth_m: NDArray[np.float64] | float,
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Mean speckle intensity relative to a flat reflector's echo at depth(s), re the
    elevation focus. From the transducer (:func:`sim_us.transducer.speckle_per_flat`):
    the speckle sums the resolution cell's scatterers incoherently where a flat reflector
    sums the field over its plane coherently, so in focus their ratio goes as 1 / (lateral
    × elevation FWHM), and away from the lens focus the flat reflector loses more (its
    plane meets a curved wavefront). With stated widths: 1 / (lateral × elevation FWHM)
    alone (the axial width is the same at every depth)."""
    focus = probe.elevation_focus_mm * 1e-3
    c = medium_speed_m_s
    if probe.lateral_fwhm_mm is None and probe.slice_thickness_mm is None:
        tables = beam_of(probe, c)
        return tables.at("speckle_per_flat", depth_m) / tables.at("speckle_per_flat", focus)
    cell = lateral_fwhm_m(probe, depth_m, c) * slice_thickness(probe, depth_m, c)
    return lateral_fwhm_m(probe, focus, c) * slice_thickness(probe, focus, c) / cell


def flat_echo_gain(
    probe: ProbeConfig,
    depth_m: NDArray[np.float64] | float,
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Echo amplitude of a perfect flat reflector facing the probe at displayed depth(s),
    relative to one at the elevation focus (:func:`sim_us.transducer.flat_echo`): from
    the transducer's datasheet figures, whatever widths it states (the level against
    depth is the apertures', not a width)."""
    return beam_of(probe, medium_speed_m_s).at("flat_echo", depth_m)


def band_attenuation_db(probe: ProbeConfig, medium: Material, depth_m: Any) -> Any:
    """Two-way loss (dB) of the probe's broadband echo from depth(s) in a medium with
    power-law attenuation (its spectrum shifts down: less than at the centre frequency)."""
    fc_db = 2.0 * attenuation_db_per_m(medium, probe.f_mhz) * np.asarray(depth_m, float)
    return band_loss(transducer(probe), medium.attenuation_power).loss(fc_db)


def scanline_step(probe: ProbeConfig, pixel_m: float) -> float:
    """Columns between scanlines (≥ 1) at a column spacing ``pixel_m``: the stated
    spacing, or half the narrowest lateral FWHM over the image, in whole columns."""
    if probe.scanline_spacing_mm is not None:
        return max(1.0, probe.scanline_spacing_mm * 1e-3 / pixel_m)
    return float(max(1, int(np.floor(narrowest_lateral_fwhm_m(probe) / 2.0 / pixel_m + 1e-9))))


def narrowest_lateral_fwhm_m(probe: ProbeConfig) -> float:
    """The lateral FWHM (m) where the beam is narrowest over the imaging depth."""
    return float(np.min(lateral_fwhm_m(probe, np.linspace(0.0, probe.depth_mm * 1e-3, 41))))


def slice_thickness(
    probe: ProbeConfig,
    depth_m: NDArray[np.float64] | float,
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Elevation FWHM (m) at depth(s) ``depth_m``: the geometric beam of a stated slice
    thickness, or the lensed aperture's diffraction (in a medium of that speed)."""
    if probe.slice_thickness_mm is None:
        return beam_of(probe, medium_speed_m_s).at("elevation_fwhm", depth_m)
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
    st_max = float(np.max(slice_thickness(probe, np.linspace(0.0, max_depth_m, 81))))
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


def elevation_amplitude(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Two-way elevation amplitude (len(z), depths), 1 on the axis: the lensed aperture's
    own profile (main lobe and side lobes), or a Gaussian ``exp(−4 ln2 z² / ST²)`` of a
    stated slice thickness."""
    depths = np.asarray(depths_m, float)
    z = np.asarray(z, float)
    if probe.slice_thickness_mm is None:
        tables = beam_of(probe, medium_speed_m_s)
        profile = tables.elevation_profile(depths, z).T
        on_axis = tables.elevation_profile(depths, np.zeros(1)).T
        return profile / np.maximum(on_axis, 1e-30)
    st = slice_thickness(probe, depths, medium_speed_m_s)[None, :]
    return np.exp(-4.0 * np.log(2.0) * z[:, None] ** 2 / st**2)


def elevation_amplitude_at(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Two-way elevation amplitude at per-row offsets (``depths_m`` (N,), ``z`` (N, m)),
    as :func:`elevation_amplitude` (up to a factor per row)."""
    depths = np.asarray(depths_m, float)
    if probe.slice_thickness_mm is None:
        return beam_of(probe, medium_speed_m_s).elevation_at(depths, z)
    st = slice_thickness(probe, depths, medium_speed_m_s)[:, None]
    return np.exp(-4.0 * np.log(2.0) * np.asarray(z, float) ** 2 / st**2)


def elevation_delay_at(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """How much deeper (m of displayed depth) echoes at displayed depths ``depths_m`` and
    elevation offsets ``z`` (arrays alike, m) are drawn than the same points in the image
    plane: the lensed aperture's longer paths to them
    (:func:`sim_us.transducer.elevation_delay`). From the aperture and its lens, also
    where a slice thickness is stated (the delay is the paths', not the profile's)."""
    return beam_of(probe, medium_speed_m_s).delay_at(np.asarray(depths_m, float), z)


def elevation_weights(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    dz: NDArray[np.float64],
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Intensity weights (planes, depths) of each sub-plane at each depth.

    A sub-plane of width dz at elevation z holds ``b(z)² dz`` of the beam's energy, b the
    two-way elevation amplitude (:func:`elevation_amplitude`). Weights are normalised per
    depth so that a flat reflector across the whole beam echoes with its full strength at
    every depth (a smaller object is dimmed: partial volume).
    """
    energy = elevation_amplitude(probe, depths_m, z, medium_speed_m_s) ** 2 * dz[:, None]
    return energy / energy.sum(axis=0, keepdims=True)


def slab_edge_shares(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    z: NDArray[np.float64],
    dz: NDArray[np.float64],
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Share (planes, depths) of a slab's beam-profile density at its low-z edge.

    Sub-plane k stands for the slab ``z_k ± dz_k / 2``; within it the two-way intensity
    profile ``b²(z)`` is taken linear between its values at the two edges (piecewise-linear
    integration over elevation). Returns ``b²(lo) / (b²(lo) + b²(hi))``: 0.5 for the slab in
    the middle of the beam, less for slabs on its positive flank, more on its negative one.
    """
    lo = elevation_amplitude(probe, depths_m, z - dz / 2, medium_speed_m_s) ** 2
    hi = elevation_amplitude(probe, depths_m, z + dz / 2, medium_speed_m_s) ** 2
    return lo / np.maximum(lo + hi, 1e-300)


# Lateral kernels of surface echoes are cut where the two-way amplitude stays below this
# for good (−60 dB: the tail of the brightest echo, itself ≈ −10 dB, falls below a 60 dB
# display).
SURFACE_KERNEL_FLOOR = 1e-3


def lateral_amplitude(
    probe: ProbeConfig,
    depths_m: NDArray[np.float64],
    spacing_m: float,
    floor: float = SURFACE_KERNEL_FLOOR,
    medium_speed_m_s: float | None = None,
) -> NDArray[np.float64]:
    """Two-way lateral amplitude PSF (rows, taps), peak 1, sampled every ``spacing_m``
    (the drawn column spacing) for rows at ``depths_m``; centred, symmetric, cut where every
    row stays below ``floor`` of its peak; in a medium of speed ``medium_speed_m_s``
    (None: the scanner's).

    The array's own profile where the lateral beam and its side lobes are derived
    (``side_lobe_db: array``); otherwise a Gaussian of the depth's FWHM (stated or
    derived) with, when side lobes are on, copies at ± :data:`SIDE_LOBE_OFFSET_PER_FWHM`
    × FWHM at the stated level or the array's. The copies are drawn with the main lobe's
    shape (a side lobe's real width is about half the main lobe's null-to-null width; the
    level at its peak is what matters for a detector).
    """
    depths = np.asarray(depths_m, float)
    fwhm = lateral_fwhm_m(probe, depths, medium_speed_m_s)
    own = probe.lateral_fwhm_mm is None and probe.side_lobe_db == "array"
    derived = probe.lateral_fwhm_mm is None or probe.side_lobe_db == "array"
    tables = beam_of(probe, medium_speed_m_s) if derived else None
    if own:
        assert tables is not None
        radius = int(np.ceil(tables.lateral_x[-1] / spacing_m))
        x = np.arange(-radius, radius + 1) * spacing_m
        k = tables.lateral_profile(depths, x)
    else:
        sigma = fwhm / FWHM_PER_SIGMA  # amplitude σ (m) per row
        if probe.side_lobe_db is None:
            level = np.zeros(len(depths))
        elif probe.side_lobe_db == "array":
            assert tables is not None
            level = 10.0 ** (np.nan_to_num(tables.at("side_lobe_db", depths), nan=-300.0) / 20.0)
        else:
            level = np.full(len(depths), 10.0 ** (float(probe.side_lobe_db) / 20.0))
        offset = SIDE_LOBE_OFFSET_PER_FWHM * fwhm
        reach = np.max(np.where(level > 0, offset, 0.0) + 4.0 * sigma)
        radius = max(int(np.ceil(reach / spacing_m)), 1)
        x = np.arange(-radius, radius + 1) * spacing_m
        s = sigma[:, None]
        copies = np.exp(-0.5 * ((x - offset[:, None]) / s) ** 2) + np.exp(
            -0.5 * ((x + offset[:, None]) / s) ** 2
        )
        # The copies add in intensity (no cross term with the main lobe's Gaussian tail,
        # which stands for no real aperture's): |h|² = g² + level² · copies².
        # The Gaussian is cut at 3 σ of its intensity, as every Gaussian kernel here.
        main = np.where(np.abs(x) <= 3.0 * s / np.sqrt(2.0), np.exp(-((x / s) ** 2)), 0.0)
        k = np.sqrt(main + (level[:, None] * copies) ** 2)
    # Cut the taps no row needs (all below the floor from there out).
    need = np.flatnonzero(np.max(k, axis=0) >= floor)
    cut = int(max(abs(need[0] - radius), abs(need[-1] - radius))) if len(need) else 0
    return k[:, radius - cut : radius + cut + 1]
