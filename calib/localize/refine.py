"""The radial-band refinement (paper §III-E-4) and the cap's sub-voxel centre (method
"refined").

Around the current centres, the bright fraction on proximal hemispheres of trial radius,
averaged over all sweeps of the sphere and normalised to its peak, gives a radial profile
(:func:`radial_profile`): the interior extends to its first rising 0.25 crossing, the
shell band lies between its 0.75 crossings (:func:`profile_bands`). Those bands replace
the initial samples for the refinement passes (:func:`_radial_band_passes`).

Method "refined" then fits each accepted centre to the cap's echo
(:func:`_refine_centre`): laterally the echo's moments about the cap's top, axially the
peak of the top's echo (:func:`_axial_peak`) one radius above the centre, and in
elevation the vertex of a least-squares parabola through the cap's peak grey level (dB)
per slice, slices clipped at 255 left out, refitted in a window centred on the vertex
itself (:func:`_elevation_vertex`, :func:`_centred_vertex`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .consensus import _MAX_ELEVATION_SIGMA
from .kernels import cap_weights, column_tops, parabola_vertex
from .search import _M_PER_MM, _best_on_grid, _local_window, fibonacci_hemisphere, half_ball_samples
from .settings import LocalizerConfig
from .volume import LABEL_BRIGHT, SweepVolume

__all__ = ["apparent_radius", "profile_bands", "profile_crossings", "radial_profile"]

Array = NDArray[np.float64]

_REFINE_ROUNDS = 4
_REFINE_TOL = 5e-6  # metres: a twentieth of a pixel
_MAX_DRIFT_VOXELS = 3.0  # voxels of at least 1 mm: the sub-voxel fit's reach from the grid


def radial_profile(
    vols: Sequence[SweepVolume], centres_vox: Sequence[Array], radii: Array, n_dirs: int
) -> Array:
    """Peak-normalised bright fraction on proximal hemispheres of trial radius, averaged
    over sweeps; (len(radii),)."""
    dirs = fibonacci_hemisphere(n_dirs)
    total = np.zeros(len(radii))
    count = np.zeros(len(radii))
    for vol, cv in zip(vols, centres_vox, strict=True):
        centre = vol.position(*np.asarray(cv, dtype=float))
        P = centre[None, None, :] + radii[:, None, None] * dirs[None, :, :]
        k, r, c = vol.index(P)
        lab = vol.label_at(k, r, c)
        valid = (lab > 0).sum(axis=1)
        bright = (lab == LABEL_BRIGHT).sum(axis=1)
        ok = valid > 0
        total[ok] += bright[ok] / valid[ok]
        count[ok] += 1
    profile = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    peak = profile.max()
    return profile / peak if peak > 0 else profile


def profile_crossings(
    radii: Array, profile: Array
) -> tuple[float | None, float | None, float | None]:
    """(first rising 0.25 crossing, rising and falling 0.75 crossings around the peak) of
    a peak-normalised radial profile, linearly interpolated; None where it has none."""
    peak = int(np.argmax(profile))

    def crossing(level: float, rising: bool) -> float | None:
        idx = range(1, peak + 1) if rising else range(peak + 1, len(profile))
        for i in idx:
            a, b = profile[i - 1], profile[i]
            if (a < level <= b) if rising else (a >= level > b):
                return float(radii[i - 1] + (level - a) / (b - a) * (radii[i] - radii[i - 1]))
        return None

    return crossing(0.25, True), crossing(0.75, True), crossing(0.75, False)


def profile_bands(radii: Array, profile: Array, radius: float) -> tuple[float, float, float]:
    """(interior limit, shell inner, shell outer) from a peak-normalised radial profile:
    first rising 0.25 crossing; rising and falling 0.75 crossings around the peak. Falls
    back to (0.8 R, 0.9 R, 1.1 R) pieces when a crossing is missing, and to all three
    when the bands are not a shell outside an interior (a profile that peaks at the
    centre, e.g. from sweeps too sparse to resolve the cap, would otherwise turn the
    shell inside out and lose every sweep)."""
    inner, rise, fall = profile_crossings(radii, profile)
    bands = (
        inner if inner is not None else 0.8 * radius,
        rise if rise is not None else 0.9 * radius,
        fall if fall is not None else 1.1 * radius,
    )
    if not bands[0] <= bands[2] or not bands[1] < bands[2]:
        return 0.8 * radius, 0.9 * radius, 1.1 * radius
    return bands


def _radial_band_passes(
    vols: Sequence[SweepVolume],
    results: list[tuple[NDArray[np.int64], float, float, float]],
    radius: float,
    grid: float,
    cfg: LocalizerConfig,
) -> list[tuple[NDArray[np.int64], float, float, float]]:
    """``cfg.refinement_passes`` passes of the radial-band refinement: the radial profile
    about the centres that scored (``results``: each sweep's (voxel, score, f_shell,
    f_interior)), its bands as the new shell and interior samples, and every sweep
    searched again within ``refine_window_mm`` of its centre with them."""
    radii = np.arange(0.0, 1.6 * radius, min(vols[0].spacing[:2]))
    for _ in range(cfg.refinement_passes):
        ok = [i for i, r in enumerate(results) if r[1] >= cfg.min_score]
        if not ok:
            break
        profile = radial_profile(
            [vols[i] for i in ok], [results[i][0] for i in ok], radii, cfg.profile_directions
        )
        inner, rise, fall = profile_bands(radii, profile, radius)
        shell_p = half_ball_samples(cfg.shell_samples, fall, inner=rise)
        interior_p = half_ball_samples(cfg.interior_samples, inner)
        results = [
            _best_on_grid(
                vol,
                *_local_window(res[0], vol, cfg.refine_window_mm * 1e-3, grid),
                shell_p,
                interior_p,
                cfg.min_coverage,
            )
            for vol, res in zip(vols, results, strict=True)
        ]
    return results


def _refine_centre(vol: SweepVolume, centre: Array, radius: float) -> tuple[Array, float] | None:
    """Sub-voxel centre from the moments of the cap's echo, and the standard error of its
    elevation (0 where not estimated; see :func:`_elevation_vertex`); None when the fit
    drifts more than :data:`_MAX_DRIFT_VOXELS` voxels (at least 1 mm each) from
    ``centre``, the grid's candidate (:func:`_did_not_settle` says why); an error of NaN
    when no echo about the candidate could be read at all (:func:`_nothing_to_refine`).

    The probe-facing cap is mirror-symmetric about the centre's lateral and elevational
    coordinates, so the echo-weighted mean of x over the cap gives it (first over the
    cap's band, then over the rows about its top, which the speckle of a scattering
    medium around the sphere does not outweigh), and z is the vertex of the top's peak
    grey level across the slices (:func:`_elevation_vertex`); the top of the cap (normal
    incidence, the strongest echo, seen in every nearby frame
    through the slice thickness) lies one radius above the centre, so the depth of its
    echo's peak (:func:`_axial_peak`) plus R gives y. A least-squares sphere fit would be
    pulled upwards instead: the elevation beam smears that top echo over neighbouring
    frames and flattens the stacked cap. Weights are grey levels above their brightness
    level (the frame mean, and the depth's noise floor with method "refined"); a few
    rounds re-centre the windows.
    """
    dx, dy, dz = vol.spacing
    seed = np.asarray(centre, dtype=float)
    current = seed
    z_sigma = 0.0
    measured = False  # an elevation read off the cap's echo at least once
    K, H, W = vol.shape
    for _ in range(_REFINE_ROUNDS):
        x_c, y_c, z_c = current
        k0, _, c0 = (int(v) for v in vol.index(current))
        # Cap window: ±R laterally and in elevation, a band of ±R/2 about the cap's depth.
        ks = np.arange(max(k0 - int(radius / dz) - 1, 0), min(k0 + int(radius / dz) + 2, K))
        (first, last), _ = vol.pixel(
            np.array([[x_c, y_c - 1.5 * radius, z_c], [x_c, y_c - 0.5 * radius, z_c]])
        )
        rs = np.arange(max(int(first) - vol.row0, 0), min(int(last) - vol.row0 + 1, H))
        cs = np.arange(max(c0 - int(radius / dx) - 1, 0), min(c0 + int(radius / dx) + 2, W))
        if not (len(ks) and len(rs) and len(cs)):
            break
        # Coordinates are separable on the grid: keep them as three axes.
        zs = vol.z0 + ks * dz
        xs, ys = vol.axes(rs, cs)
        # Echo above its level, inside the shell band |d − R| ≤ R/2.
        w = cap_weights(
            vol._frames,
            vol._levels,
            vol._nearest,
            vol._frame_rows,
            vol._frame_cols,
            ks,
            rs,
            cs,
            (zs - z_c) ** 2,
            (ys - y_c) ** 2,
            (xs - x_c) ** 2,
            (0.5 * radius) ** 2,
            (1.5 * radius) ** 2,
        )
        total = w.sum()
        if total <= 0:
            break
        # Each slice's frame sits off its integer stacking shift by up to half a pixel.
        x_new = float(w.sum(axis=(0, 1)) @ xs / total)
        x_new += float(vol.residual_shift(ks, w.sum(axis=(1, 2)))[0])
        z_mean = float(w.sum(axis=(1, 2)) @ zs / total)
        near_x = np.abs(xs - x_new) <= 0.5 * _M_PER_MM
        # One brightness level for every slice: the vertex of the profile must not move
        # with the level. Each frame's level follows its own rows, and where the sphere's
        # echoes raise the depth's noise floor about the cap, the frames' in-plane drift
        # along the sweep (its axis a little off the image normal) slides the cap across
        # that bump: a level varying linearly with elevation tilts the profile and moved
        # the vertex by up to 0.15 mm at 45 mm.
        ks_all = np.arange(K)
        frame_of = vol._nearest[ks_all]
        near_seed = np.abs(ys - (y_c - radius)) <= 0.75 * _M_PER_MM
        rows = np.clip(
            rs[near_seed][None, :] - vol._frame_rows[frame_of][:, None],
            0,
            vol._frames.shape[1] - 1,
        )
        level = 0.0
        if rows.size:
            level = float(np.median(vol._levels[frame_of[:, None], rows].max(axis=1)))
        # Top of the cap first: the column under (x, z) in the slices nearest the current
        # elevation. The elevation profile is then read at the depth of that top: read one
        # millimetre too deep (a grid seed below the top, where a saturated or diffuse cap
        # scores as well), the slices through the centre show the dark interior and those
        # 2 mm to either side the cap's flanks, the profile has two peaks, and the vertex
        # went off to one of them (a 3 mm sphere, +20 dB, 20 mm deep).
        col = np.abs(xs - x_new) <= max(dx, 0.25 * _M_PER_MM)
        frames = np.abs(zs - z_c) <= 0.75 * dz
        wt = w[frames][:, :, col].sum(axis=(0, 2))
        if wt.sum() <= 0:
            break
        y_top = _axial_peak(
            vol.intensity(ks[frames], rs, cs[col], level=level), 255.0 - level, ys, wt
        )
        y_top += float(vol.residual_shift(ks[frames], w[frames][:, :, col].sum(axis=(1, 2)))[1])
        near_y = np.abs(ys - y_top) <= 0.75 * _M_PER_MM
        # Laterally, too, from the top of the cap: the echo-weighted mean over the whole
        # band follows whatever else is bright in it, and in a scattering medium that is
        # the speckle around the sphere's echo-free interior (gel, the cap's top 5 mm under
        # the face at 0 dB: 8 of 67 accepted centres 0.7-1.07 mm off laterally; from the
        # top, 78 accepted and none past 0.75 mm). In water it moved the median errors by
        # −0.005 mm on average and the worst accepted from 0.62 to 0.58 mm
        # (robustness.yaml), from 0.88 to 0.76 mm (robustness_wide.yaml).
        top_w = w[:, near_y, :]
        if top_w.sum() > 0:
            x_new = float(top_w.sum(axis=(0, 1)) @ xs / top_w.sum())
            x_new += float(vol.residual_shift(ks, top_w.sum(axis=(1, 2)))[0])
            near_x = np.abs(xs - x_new) <= 0.5 * _M_PER_MM
        # Elevation from the top of the cap only (where the echo stands far above noise),
        # over every slice: beyond the elevation focus the beam is wider than a small
        # sphere and its echo of the top follows the beam profile well past ± R.
        top = np.maximum(vol.intensity(ks_all, rs[near_y], cs[near_x], level=level), 0.0)
        # A slice's top at a grey level of 255 is saturated.
        clip = np.full(K, 255.0 - level)
        zs_all = vol.z0 + ks_all * dz
        z_new, z_sigma = _elevation_vertex(
            top, zs_all, z_mean, dz, clip, np.abs(zs_all - z_mean) <= radius
        )
        measured = True
        midpoint = z_sigma == 0
        if midpoint:
            z_sigma = _MIDPOINT_SIGMA_SLICES * dz
        if 0 < z_sigma < np.inf and (not midpoint or z_sigma > _MAX_ELEVATION_SIGMA):
            # The brightness vertex is uncertain where few frames see the top (a sharp
            # specular echo, frames far apart): the cap's depth in each frame measures
            # the elevation too, through the sphere's known radius. A midpoint is joined
            # with it only where it alone would not do (frames far apart): on pymust's
            # smooth sphere, 1 mm frames, the midpoints lay 0.04–0.05 mm off and the
            # joined estimates up to 0.32 mm (the specular cap's depth off its top is the
            # beam's, not the section's); on sim_us's printed sphere with frames 2–2.5 mm
            # apart, the midpoints up to 1.2 mm off and the joined ones 0.33 mm.
            geometric = _elevation_from_depths(vol, rs, cs[col], level, radius, z_new, ys)
            if geometric is not None:
                z_geo, s_geo = geometric
                w_v, w_g = 1.0 / z_sigma**2, 1.0 / s_geo**2
                z_new = (w_v * z_new + w_g * z_geo) / (w_v + w_g)
                z_sigma = float(np.sqrt(1.0 / (w_v + w_g)))
        new = np.array([x_new, y_top + radius, z_new])
        moved = np.linalg.norm(new - current)
        current = new
        if moved < _REFINE_TOL:
            break
    # A refinement that wanders far from the grid's candidate is not trusted, and neither
    # is the candidate: a grid point is right only to the grid's step, and where the fit
    # cannot settle near it the cap is not what the fit reads (the grid point handed back
    # instead lay 1.1 mm off, a 3 mm sphere at +20 dB).
    if np.linalg.norm(current - seed) > _MAX_DRIFT_VOXELS * max(dx, dy, dz, _M_PER_MM):
        return None
    if not measured:
        # Nothing of the cap stands above its level about the candidate: the centre is the
        # grid's, right to its step only. Handed back with an elevation error of 0 it was
        # 0.7-1.1 mm off in every such sweep (gel, +20 dB, a 20 mm target: 10 of 80
        # accepted sweeps, the three over 1 mm among them).
        return current, np.nan
    return current, z_sigma


def _nothing_to_refine() -> str:
    """Why a candidate about which no echo stands above its brightness level (the cap's
    band is dark once the depth's noise floor is taken off) is not accepted."""
    return (
        "nothing of the cap's echo stands above its brightness level about the grid's "
        "candidate: its centre is known to the grid's step only and its elevation is not "
        "measured"
    )


def _did_not_settle() -> str:
    """Why a candidate whose sub-voxel fit drifted away from it is not accepted."""
    return (
        "the cap's echo did not settle on a centre: its sub-voxel fit drifted more than "
        f"{_MAX_DRIFT_VOXELS:g} voxels (at least {_MAX_DRIFT_VOXELS:g} mm) from the grid's "
        "candidate"
    )


def _elevation_from_depths(
    vol: SweepVolume,
    rs: NDArray[np.int64],
    cs: NDArray[np.int64],
    level: float,
    radius: float,
    z_guess: float,
    ys: Array,
) -> tuple[float, float] | None:
    """Elevation of the centre (and its standard error) from the depth of the cap's top
    in each frame: a frame at elevation z cuts the sphere in a circle whose top lies
    ``√(R² − (z − z_c)²)`` above the centre, so the tops across the frames trace an arc of
    the known radius whose apex is the centre's elevation. Least squares over the frames
    within 0.8 R of ``z_guess`` whose column (rows ``rs``, columns ``cs``) holds an echo
    above ``level`` (the depth of each from :func:`_axial_peak`); the centre's depth is
    solved for at each trial elevation. The standard error from the fit's curvature and
    the depths' scatter (at least a quarter pixel: two or three frames leave no estimate
    of it). None with fewer than two frames."""
    K = vol.shape[0]
    dz, dy = vol.spacing[2], vol.spacing[1]
    zs = vol.z0 + np.arange(K) * dz
    near = np.flatnonzero(np.abs(zs - z_guess) <= 0.8 * radius)
    # Each frame's top as _axial_peak reads it (its row sums as the weights), compiled.
    tops, found = column_tops(
        vol.intensity(near, rs, cs, level=level), 255.0 - level, np.ascontiguousarray(ys)
    )
    if found.sum() < 2:
        return None
    d, z = tops[found], zs[near[found]]
    lo, hi = z.max() - 0.999 * radius, z.min() + 0.999 * radius
    if hi <= lo:
        return None
    trial = np.linspace(lo, hi, 401)
    rise = np.sqrt(np.maximum(radius**2 - (z[None, :] - trial[:, None]) ** 2, 0.0))
    y_c = (d[None, :] + rise).mean(axis=1)
    sse = (((y_c[:, None] - rise) - d[None, :]) ** 2).sum(axis=1)
    i = int(np.clip(np.argmin(sse), 1, len(trial) - 2))
    step = trial[1] - trial[0]
    curvature = (sse[i - 1] - 2.0 * sse[i] + sse[i + 1]) / step**2
    if curvature <= 0:
        return None
    z_c = float(trial[i] + 0.5 * (sse[i - 1] - sse[i + 1]) / (curvature * step))
    # The depths' scatter, with two pseudo-observations of a quarter pixel's.
    s2 = (float(sse[i]) + 2.0 * (0.25 * dy) ** 2) / (len(d) - 2 + 2)
    return z_c, float(np.sqrt(2.0 * s2 / curvature))


#: Standard error (in slices) of the half-maximum midpoint, where no parabola fits the
#: profile: two crossings interpolated between slices, the elevation known to about a
#: slice (uniform over one: 1 / √12). On quick.yaml (1 mm slices, −20 to +20 dB, 20 and
#: 40 mm deep, 3 and 5 mm spheres) 228 of 529 centres came from it, 0.035–0.13 mm off
#: in elevation (median per condition), 0.51 mm at most; with slices 2.5 mm apart they
#: were up to 1.2 mm off, and handed back with no error stated.
_MIDPOINT_SIGMA_SLICES = 1.0 / np.sqrt(12.0)


def _axial_peak(grey: Array, clip: float, ys: Array, w: Array) -> float:
    """Depth of the cap's top echo: the vertex of the parabola through the brightest row
    of the column's grey levels (``grey`` (slices, rows, columns), less one level, at
    ``clip`` where saturated; rows at depths ``ys``) and its two neighbours.

    The echo of the top is not symmetric in depth: the rest of the cap within the slice
    thickness lies deeper (e²/2R at elevation e), so the echo rises sharply and trails
    off below. Its peak is the top; a weighted mean over the echo lies in its tail, and
    by how much depends on where the brightness level cuts the tail, i.e. on the gain
    (0.08 mm deeper at −10 dB than at 0 dB, 45 mm deep). Where the peak is saturated, the
    echo's leading edge: the depth where the brightest grey level per row first reaches
    the clip (the top's echo rises there; the saturated run below it is the rest of the
    cap in the slice, and its mean lay 0.5-0.8 mm deep at +20 dB 45 mm down with a sharp
    pulse); the edge lies before the peak by where the clip cuts the pulse's rise
    (≈ 0.1 mm for a 0.11 mm pulse 20 dB over the clip). On the band's edge, the mean of the
    weights ``w`` (rows) over the echo."""
    profile = grey.sum(axis=(0, 2))
    i = int(np.argmax(profile))
    saturated = (grey[:, max(i - 1, 0) : i + 2] >= clip - 0.5).any()
    if saturated:
        top = grey.max(axis=(0, 2))
        k = int(np.argmax(top >= clip - 0.5))
        if k > 0 and top[k] > top[k - 1]:
            frac = (clip - 0.5 - top[k - 1]) / (top[k] - top[k - 1])
            return float(ys[k - 1] + frac * (ys[k] - ys[k - 1]))
        return float(ys[k])
    if 0 < i < len(profile) - 1:
        g_m, g_0, g_p = profile[i - 1 : i + 2]
        curvature = g_m - 2.0 * g_0 + g_p
        if curvature < 0:
            return float(ys[i] + 0.5 * (g_m - g_p) / curvature * (ys[1] - ys[0]))
    return float(w @ ys / w.sum())


def _elevation_vertex(
    w: Array,
    zs: Array,
    z_mean: float,
    dz: float,
    clip: Array | None = None,
    search: NDArray[np.bool_] | None = None,
) -> tuple[float, float]:
    """Sub-slice elevation of the cap and its standard error from its peak grey level per
    slice (0: the half-maximum midpoint, no fit to give one; inf: not measured) (``w`` is
    (slices, ...), ``zs`` the slices' elevations, ``clip`` each slice's ``w`` at a grey
    level of 255, ``search`` the slices where the brightest is looked for).

    The peak grey level per slice is log-compressed (dB), in which a Gaussian beam profile
    is a parabola; its vertex is unbiased where a weighted mean over slices is biased by
    where the centre falls between frames. The parabola is fitted by least squares to the
    contiguous run of slices above half the maximum: three slices where the beam is thin
    (its vertex through them), more where it is wide beyond the elevation focus (there the
    three-slice vertex is a difference of nearly equal noisy peaks). Slices clipped at 255
    (high gain) are left out: the flanks on both sides still fix the vertex of a symmetric
    profile, if their parabola reaches the clip at the clipped slices
    (:func:`_reaches_the_clip`; else the half-maximum midpoint with its error stated).
    Without a clipped slice, the fit is then refined in a window centred on its own
    vertex (:func:`_centred_vertex`). Without a usable fit, the midpoint of the
    half-maximum crossings; where the profile does not fall to half on both sides (or
    nothing echoes), the echo-weighted mean ``z_mean`` with an infinite error: the
    elevation is not measured.
    """
    if w.size == 0:
        return z_mean, np.inf
    peaks = w.reshape(len(w), -1).max(axis=1)
    k = int(np.argmax(np.where(search, peaks, -np.inf) if search is not None else peaks))
    if peaks[k] <= 0:
        return z_mean, np.inf
    half = 0.5 * peaks[k]
    lo = hi = k
    while lo > 0 and peaks[lo - 1] >= half:
        lo -= 1
    while hi < len(peaks) - 1 and peaks[hi + 1] >= half:
        hi += 1
    # One slice beyond the run on each side: the parabola needs the fall on both sides.
    lo, hi = max(lo - 1, 0), min(hi + 1, len(peaks) - 1)
    run = np.arange(lo, hi + 1)
    clipped = peaks[run] >= clip[run] - 0.5 if clip is not None else np.zeros(len(run), dtype=bool)
    use = run[~clipped & (peaks[run] > 0)]
    # Slices on both sides of the peak, or on both sides of a clipped top.
    below_the_clip = False
    if len(use) >= 3 and (use[0] < k < use[-1] or clipped.any()):
        u = (zs[use] - zs[k]) / dz
        fit = _parabola_vertex(u, peaks[use])
        if fit is not None and u[0] <= fit[0] <= u[-1]:
            below_the_clip = not _reaches_the_clip(
                u, peaks[use], (zs[run[clipped]] - zs[k]) / dz, peaks[run[clipped]]
            )
            if not below_the_clip:
                if not clipped.any():
                    fit = _centred_vertex(peaks, (zs - zs[k]) / dz, fit, 0.25 * (hi - lo), clip)
                return float(zs[k] + fit[0] * dz), fit[1] * dz
    top = run[clipped] if clipped.any() else np.array([k])
    mid = _half_maximum_midpoint(peaks, zs, int(top[0]), int(top[-1]))
    if mid is None:
        return z_mean, np.inf
    # A clipped top whose unclipped neighbours' parabola stays below the clip: its
    # midpoint, known to a slice as any midpoint but stated, so that the caller joins it
    # with the cap's depth across the frames, which the clip does not hide.
    return mid, (_MIDPOINT_SIGMA_SLICES * dz if below_the_clip else 0.0)


def _reaches_the_clip(u: Array, y: Array, u_clipped: Array, y_clipped: Array) -> bool:
    """Whether the least-squares parabola through the unclipped slices (``u``, ``y``)
    reaches the clipped slices' levels (``y_clipped`` at ``u_clipped``): a saturated
    slice's peak is at least its clip, so a parabola below it there is not the profile.

    A printed sphere's flanks return a diffuse echo in every slice that cuts them: at
    +20 dB the one slice through the top clipped and its neighbours 1 and 2 mm off lay
    on a plateau of that diffuse echo at half the clip; the parabola through the plateau
    put the vertex 0.4-0.54 mm off (quick.yaml, sphere 2, stated probe, 45 sweeps: worst
    0.56 mm, median 0.16). Refused, the half-maximum midpoint about the clipped slice
    alone: worst 0.27, median 0.15, but at +20 dB on robustness.yaml's images the median
    per point rose by 0.013 mm; joined with the cap's depths across the frames
    (:func:`_elevation_from_depths`): worst 0.20, median 0.076, and on twelve
    robustness.yaml-like scans at +20 dB (30-70 mm, spheres 1-3, 540 sweeps) median
    0.120 / worst 0.34 against 0.121 / 0.34 with the parabola kept."""
    if not len(u_clipped):
        return True
    coef = np.polyfit(u, y, 2)
    return bool(np.all(np.polyval(coef, u_clipped) >= y_clipped - 0.5))


def _centred_vertex(
    peaks: Array, u: Array, start: tuple[float, float], width: float, clip: Array | None
) -> tuple[float, float]:
    """The vertex ``start`` (slices from the brightest, and its standard error) refitted
    with the slices weighted by a Gaussian window centred on the vertex itself (1 σ of
    ``width`` slices, at least one), a few times over.

    The profile in dB is a parabola only near its top (its flanks fall into the speckle
    and level off). A window fixed by which slices clear half the maximum changes as the
    centre moves between two frames, and the shape's departure from a parabola then
    pulls the vertex towards the middle between frames (measured on the twin: ± 0.044 mm
    with the centre's phase between frames 1 mm apart, within 0.057 mm of scatter). A
    window centred on the vertex is symmetric about it whatever the phase: 0.015 mm, and
    0.048 mm of scatter. Where the refit cannot be made (too few slices, a clipped slice
    in the window, a parabola that does not open downwards, a vertex that jumps by more
    than a slice), ``start``."""
    width = max(width, 1.0)
    clipped = peaks >= clip - 0.5 if clip is not None else np.zeros(len(peaks), dtype=bool)
    vertex, sigma = start
    for _ in range(4):
        near = np.abs(u - vertex) <= 3.0 * width
        if clipped[near].any():
            return start
        near &= peaks > 0  # below the brightness level: no echo to fit
        window = np.exp(-0.5 * ((u[near] - vertex) / width) ** 2)
        fit = _parabola_vertex(u[near], peaks[near], window)
        if fit is None or abs(fit[0] - start[0]) > 1.0:
            return start
        moved = abs(fit[0] - vertex)
        vertex, sigma = fit
        if moved < 1e-3:
            break
    return vertex, sigma


def _parabola_vertex(
    u: Array, y: Array, weights: Array | None = None
) -> tuple[float, float] | None:
    """Vertex of the (window-weighted) least-squares parabola through (u, y) and its
    standard error (the points' scatter about it, alike for every point, through the
    fit by the delta method; 0 where fewer than 5 points, in effect, leave no honest
    estimate of it); None unless it opens downwards."""
    if len(u) < 3:
        return None
    wt = np.ones(len(u)) if weights is None else np.asarray(weights, dtype=float)
    # Contiguous float64 arrays: one compiled signature whatever the caller's views.
    status, vertex, sigma = parabola_vertex(
        np.ascontiguousarray(u, dtype=float),
        np.ascontiguousarray(y, dtype=float),
        np.ascontiguousarray(wt),
    )
    if status == 0:
        return float(vertex), float(sigma)
    if status == 1:
        return None
    # Degenerate abscissae: the pseudo-inverse's least-squares parabola.
    V = np.vander(u, 3)
    Minv = np.linalg.pinv(V.T @ (wt[:, None] * V))
    coef = Minv @ (V.T @ (wt * y))
    a, b = coef[0], coef[1]
    if a >= 0:
        return None
    vertex = -b / (2 * a)
    n_effective = wt.sum() ** 2 / np.sum(wt**2)  # Kish's; n for equal weights
    if n_effective - 3 < 2:
        return float(vertex), 0.0
    # The residuals' degrees of freedom under the window: n − 3 for equal weights.
    s2 = float(np.sum(wt * (V @ coef - y) ** 2)) / (wt.sum() * (1 - 3 / n_effective))
    cov = s2 * (Minv @ (V.T @ ((wt**2)[:, None] * V)) @ Minv)[:2, :2]
    g = np.array([b / (2 * a * a), -1 / (2 * a)])  # ∂vertex / ∂(a, b)
    return float(vertex), float(np.sqrt(max(g @ cov @ g, 0.0)))


def _half_maximum_midpoint(peaks: Array, zs: Array, first: int, last: int) -> float | None:
    """Midpoint of the elevations where ``peaks`` crosses half its maximum below slice
    ``first`` and above slice ``last`` (linearly interpolated); None when the profile
    does not fall to half on both sides."""
    half = 0.5 * peaks[first : last + 1].max()

    def crossing(inner: int, step: int) -> float | None:
        i = inner
        while 0 <= i + step < len(peaks):
            a, b = peaks[i], peaks[i + step]
            if b < half <= a:
                return float(zs[i] + (a - half) / (a - b) * (zs[i + step] - zs[i]))
            i += step
        return None

    lo, hi = crossing(first, -1), crossing(last, +1)
    return None if lo is None or hi is None else 0.5 * (lo + hi)


#: The cap's leading edge in :func:`apparent_radius`: this far below the column's peak
#: grey level, a tenth of the grey range (6 dB, half the amplitude, on a 60 dB display).
_EDGE_DROP_GREY = 25.5
#: A column whose peak reaches this grey level is clipped: its peak, and so its edge, is
#: unknown.
_CLIPPED_GREY = 254.5
#: The fitted section's radius, in units of the given radius, that counts as a reading.
_FIT_RANGE = (0.4, 2.5)


def apparent_radius(vol: SweepVolume, centre: Array, radius: float) -> float | None:
    """The sphere's radius as the sweep's image draws it (metres), or None where too little
    of the cap echoes: in the slice nearest the centre's elevation, the cap's leading edge
    per column (where the column's echo first comes within ``_EDGE_DROP_GREY`` of its own
    peak: no level but the echo's; columns clipped at 255, whose peak is unknown, left
    out) within ±0.8 ``radius`` of the centre, a circle fitted to it (robust least
    squares), and the sphere's radius from that section's and the slice's offset from the
    centre. A check on what the pipeline was told, not a measurement it uses.

    The edge is the echo's half-amplitude point (the FWHM's convention), not half its
    grey level: grey is logarithmic, and half of it is ≈ 30 dB down, in the PSF's skirts,
    which a steep flank spreads sideways into the next columns. Over eight conditions
    drawn across gain (−20 to +20 dB), depth (10–45 mm), radius (3–8 mm) and seed, in
    water's defocused beam, the half-grey edge read the radius −0.23 to +0.80 mm off (two
    of eight past 0.4 mm: a correct radius called wrong); the half-amplitude edge −0.07 to
    +0.13 mm, and −0.06 to +0.17 mm over eight more conditions drawn afterwards."""
    dx, dz = vol.spacing[0], vol.spacing[2]
    K, H, W = vol.shape
    k, _, c0 = (round(float(v)) for v in vol.index(centre))
    if not 0 <= k < K:
        return None
    (first, last), _ = vol.pixel(
        np.array(
            [
                [centre[0], centre[1] - 1.6 * radius, centre[2]],
                [centre[0], centre[1] - 0.2 * radius, centre[2]],
            ]
        )
    )
    rs = np.arange(max(int(first) - vol.row0, 0), min(int(last) - vol.row0 + 1, H))
    cs = np.arange(max(c0 - int(0.8 * radius / dx), 0), min(c0 + int(0.8 * radius / dx) + 1, W))
    if len(rs) < 3 or len(cs) < 5:
        return None
    xs, ys = vol.axes(rs, cs)
    grey = np.maximum(vol.intensity(np.array([k]), rs, cs, level=0.0)[0], 0.0)
    edge_x, edge_y = [], []
    for j, x in enumerate(xs):
        col = grey[:, j]
        peak = col.max()
        if peak <= _EDGE_DROP_GREY or peak >= _CLIPPED_GREY:
            continue
        edge = peak - _EDGE_DROP_GREY
        i = int(np.argmax(col >= edge))
        if i == 0:
            continue  # the echo starts above the window: no edge seen
        f = (edge - col[i - 1]) / (col[i] - col[i - 1])
        edge_x.append(x)
        edge_y.append(ys[i - 1] + f * (ys[i] - ys[i - 1]))
    if len(edge_x) < 5:
        return None
    X, Y = np.array(edge_x), np.array(edge_y)
    fit = least_squares(
        lambda p: np.hypot(X - p[0], Y - p[1]) - p[2],
        [centre[0], centre[1], radius],
        loss="soft_l1",
        f_scale=0.05e-3,
    )
    # A circle far from the given size is no reading of it: where only the cap's top
    # echoes (gel, the specular arc), the flank columns' edges are speckle and the fit
    # runs off to a near-straight line (a 5 mm sphere in gel "drawn" 21 m in radius).
    # A radius given wrong by a factor (the diameter for the radius) still shows.
    if not fit.success or not _FIT_RANGE[0] * radius <= fit.x[2] <= _FIT_RANGE[1] * radius:
        return None
    offset = vol.z0 + k * dz - centre[2]  # the slice's elevation off the centre
    return float(np.hypot(fit.x[2], offset))
