"""Pulse propagation along straight rays: surface echoes, transmission, attenuation,
travel time and shadow.

Each ray starts at the transducer face in the medium and is followed through every
surface it meets. At a surface the echo's mean energy is

    A² = (T · r · 10^(−L / 20))² · [(1 − d²) (χ² S² + (1 − χ²) S_s²) + d²]

with ``r = |Z2 − Z1| / (Z2 + Z1)`` the amplitude reflection coefficient, ``T`` the two-way
transmission ``Π (1 − r_j²)`` through the surfaces crossed so far and ``L`` the two-way
attenuation (dB) of the path. ``S`` is the echo of a mirror tilted as the surface is,
through the probe's apertures (the image plane's tilt and the elevation's, from the
transducer: :func:`sim_us.transducer.mirror_response`), 1 facing the probe: a smooth
surface returns nothing the aperture does not catch, −17 dB at 10° for an F# 2.3 array.
A textured surface (a printed part's layer lines and roughness, finer than the beam's
footprint) reflects in the Kirchhoff approximation: of its energy the coherent share χ²
(:func:`coherent_factor`, from the texture's rms height σ) follows the mirror's lobe of
the surface smoothed over the footprint (the ray caster's normal of the un-textured
shape), the rest is returned by the texture's facets, tilted by their rms slope s, over
the lobe widened by them, ``S_s`` (geometrical optics). ``d`` is the material's diffuse
share: what sub-wavelength roughness and the print's fine structure return at every
angle. The coherent part ``χ S`` is the echo of a mirror, smooth in the image; the rest
is incoherent, a sum of random-phase wavelets from the surface's facets, which the
simulator can draw as speckle lying on the surface (``surface_speckle``). The echo is
placed at the *apparent* depth: the travel time at each segment's true speed, displayed
at the speed the scanner assumes.
A ray stops when it leaves the imaged depth or its echoes fall below the display floor,
which is what makes a printed solid throw a complete shadow. Rays do not refract
(as in the peer simulators); at the small incidence angles that carry echoes the
bend is small.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from .materials import Material, amplitude_reflection, attenuation_db_per_m
from .raycast import RayCaster
from .transducer import MIRROR_SLOPES, BandLoss, MirrorTables, slope_index, table_at

__all__ = ["Echoes", "coherent_factor", "rough_surface_shape", "trace"]

Array = NDArray[np.float64]

# Amplitude reflection of the transducer face for the reverberation echo.
_FACE_REFLECTION = 0.5
# A new pass starts this far past the last hit so the same surface is not found again.
_STEP_M = 1e-6
_MAX_PASSES = 24
_NP_PER_DB = np.log(10.0) / 20.0
# A surface's diffuse return grows with the area a ray's tube meets, 1 / |cos θ|, up to
# this incidence (75°: 3.9 ×): nearer grazing the tube's footprint outgrows the resolution
# cell the echo is drawn in, and the depth span it spreads over is the slab's.
_GRAZING_COS = float(np.cos(np.radians(75.0)))


def _medium_loss_db(fc_db: Array, band: BandLoss | None) -> Array:
    """The broadband echo's loss (dB) for the medium's two-way loss at fc (0 without a
    band model: the medium's loss is then in the path gain at fc)."""
    return np.zeros(len(fc_db)) if band is None else band.loss(fc_db)


def coherent_factor(k_sigma_cos: Array) -> Array:
    """Amplitude factor of the coherent (specular) reflection of a rough surface,
    ``χ = exp(−2 (k σ cos θ)²)``, with k the wavenumber of the incident wave, σ the rms
    height of the surface along its mean normal and θ the incidence angle.

    Kirchhoff approximation for a Gaussian height distribution (Ament 1953; Beckmann &
    Spizzichino 1963, ch. 5; Ogilvy 1991, ch. 4): the coherent field is the smooth
    surface's times the height's characteristic function at the phase difference
    2 k cos θ, exp(−(2 k σ cos θ)² / 2). Its square, exp(−g) with g = (2 k σ cos θ)² the
    Rayleigh roughness parameter, is the coherent *intensity* share; the surface counts as
    smooth (Rayleigh criterion) while σ cos θ < λ / 8, i.e. g < π²/4 and χ > 0.29.
    """
    return np.exp(-2.0 * k_sigma_cos**2)


def rough_surface_shape(
    mirror: Array, widened: Array, diffuse: Array, k_sigma_cos: Array, area: Array = 1.0
) -> tuple[Array, Array]:
    """Echo shape factor (rms amplitude re a mirror facing the probe) of a surface, and its
    coherent part.

    ``mirror`` is the echo S of a smooth mirror tilted as the surface is, ``widened`` the
    lobe S_s of facets tilted about it by the texture's slopes, ``diffuse`` the material's
    diffuse share d, ``k_sigma_cos`` the texture's k σ cos θ (0: smooth), ``area`` the
    surface a ray's tube meets per its cross-section, 1 / |cos θ| (θ the incidence). The
    energy

        shape² = (1 − d²) (χ² S² + (1 − χ²) S_s²) + d² · area

    splits into the coherent χ S √(1 − d²) and the incoherent rest (the facets' and the
    diffuse return, random in phase: speckle). A surface facing the probe returns all of a
    mirror's energy when smooth, less when rough only as far as the facets' tilts send it
    past the aperture. The diffuse return is the surface's own scatterers', the same per
    unit of its area at every angle: a surface met obliquely puts more of them in a ray's
    tube (d is defined facing the probe). Returns (shape, coherent).
    """
    chi = np.exp(-2.0 * k_sigma_cos**2)  # coherent_factor (inlined: compiled below)
    keep = 1.0 - diffuse**2
    coherent = np.sqrt(keep) * chi * mirror
    energy = keep * (chi**2 * mirror**2 + (1.0 - chi**2) * widened**2) + diffuse**2 * area
    return np.sqrt(energy), coherent


_rough_shape = numba.njit(cache=True, nogil=True)(rough_surface_shape)


@numba.njit(cache=True, nogil=True, boundscheck=False, inline="always")
def _mirror_lobe(
    lateral_table, elevation_table, nodes, q, tilt_lat, tilt_el, per_tilt, spread
):  # pragma: no cover - compiled
    """The mirror's lateral and elevation lobes (each two-way, of its own aperture) at hit
    ``q``'s depth nodes, for a reflector tilted ``tilt_lat`` / ``tilt_el`` (rad) from
    facing the probe and widened by facets of rms slope ``spread`` (rad; 0 for a plain
    mirror)."""
    i0, i1, wd = nodes
    j0, j1, wj = slope_index(spread)
    return (
        table_at(lateral_table, i0[q], i1[q], wd[q], abs(tilt_lat) * per_tilt, j0, j1, wj),
        table_at(elevation_table, i0[q], i1[q], wd[q], abs(tilt_el) * per_tilt, j0, j1, wj),
    )


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _surface_echoes(
    dirs,
    normals,
    laterals,
    elevations,
    ray,
    nodes,
    facets,
    layer_share,
    layer_m,
    build_axis,
    k_sigma_cos,
    diffuse,
    lateral_table,
    elevation_table,
    per_tilt,
    focal_spot,
    wavelength,
):  # pragma: no cover - compiled
    """Per hit: its tilts from facing the probe (in the image plane and in elevation), the
    echo's shape factor and its coherent part (:func:`rough_surface_shape`), what a second
    bounce keeps (χ S) and the coherent echo per unit of the elevation lobe (χ √(1 − d²)
    S_lateral). ``nodes`` = (i0, i1, wd) the hit's depth nodes in the mirror tables.

    A print's layer staircase sends its share ``layer_share`` of the texture's energy back
    from its treads: small mirrors facing the build direction b (on the side the surface
    faces), each ``h / tan α`` wide (h the layer height, α the surface's angle to the
    build plate); treads narrower than the focal spot (λ F#) fill it in part, returning
    ``w / spot`` of its energy (a row of them, at depths a layer apart, adds in energy).
    Their echo is the mirror's lobe at b's tilt from the beam, widened by the tread's own
    diffraction (≈ λ / 2w, as facets of that rms tilt): a printed sphere seen along its
    build direction echoes from its whole cap, seen from aside only about its top. The
    rest of the texture's energy (the roughness's) keeps the facets' widened lobe.

    Compiled: on numpy this was three dozen (hits,) temporaries per pass, a third of the
    time of a frame of printed parts."""
    n = len(ray)
    tilt_el = np.empty(n)
    shape = np.empty(n)
    coherent = np.empty(n)
    bounce = np.empty(n)
    coherent_lateral = np.empty(n)
    top = MIRROR_SLOPES[-1]
    for q in range(n):
        d, nrm = dirs[q], normals[q]
        lat_ax, el_ax = laterals[ray[q]], elevations[ray[q]]
        cos_in = d[0] * nrm[0] + d[1] * nrm[1] + d[2] * nrm[2]
        facing = max(abs(cos_in), 1e-12)
        t_lat = np.arctan((lat_ax[0] * nrm[0] + lat_ax[1] * nrm[1] + lat_ax[2] * nrm[2]) / facing)
        t_el = np.arctan((el_ax[0] * nrm[0] + el_ax[1] * nrm[1] + el_ax[2] * nrm[2]) / facing)
        tilt_el[q] = t_el
        lat0, el0 = _mirror_lobe(
            lateral_table, elevation_table, nodes, q, t_lat, t_el, per_tilt, 0.0
        )
        lat_w, el_w = _mirror_lobe(
            lateral_table, elevation_table, nodes, q, t_lat, t_el, per_tilt, facets[q]
        )
        spec, widened = lat0 * el0, lat_w * el_w
        share, h = layer_share[q], layer_m[q]
        if share > 0 and h > 0:
            b = build_axis[q]
            cos_a = b[0] * nrm[0] + b[1] * nrm[1] + b[2] * nrm[2]
            sign = -1.0 if cos_a < 0 else 1.0  # the treads face out of the surface
            cos_a = abs(cos_a)
            sin_a = np.sqrt(max(1.0 - cos_a * cos_a, 0.0))
            width = h * cos_a / sin_a if sin_a > 0 else np.inf
            fill = min(1.0, width / focal_spot) if focal_spot > 0 else 1.0
            d_b = sign * (d[0] * b[0] + d[1] * b[1] + d[2] * b[2])
            facing_b = max(abs(d_b), 1e-12)
            lat_b = sign * (lat_ax[0] * b[0] + lat_ax[1] * b[1] + lat_ax[2] * b[2])
            el_b = sign * (el_ax[0] * b[0] + el_ax[1] * b[1] + el_ax[2] * b[2])
            # A tread narrower than the focal spot diffracts: its echo spreads over λ / 2w.
            spread = min(wavelength / (2.0 * width), top) if width > 0 else top
            treads2 = 0.0
            if not d_b > 0:  # treads facing away from the probe return nothing
                lat, el = _mirror_lobe(
                    lateral_table,
                    elevation_table,
                    nodes,
                    q,
                    np.arctan(lat_b / facing_b),
                    np.arctan(el_b / facing_b),
                    per_tilt,
                    spread,
                )
                treads2 = fill * (lat * el) ** 2
            widened = np.sqrt((1.0 - share) * widened**2 + share * treads2)
        # The surface a ray's tube meets: 1 / |cos θ|, up to the grazing limit.
        area = 1.0 / max(facing, _GRAZING_COS)
        shape[q], coherent[q] = _rough_shape(spec, widened, diffuse[q], k_sigma_cos[q], area)
        chi = np.exp(-2.0 * k_sigma_cos[q] ** 2)  # coherent_factor
        bounce[q] = chi * spec
        coherent_lateral[q] = np.sqrt(1.0 - diffuse[q] ** 2) * chi * lat0
    return tilt_el, shape, coherent, bounce, coherent_lateral


@dataclass(frozen=True)
class Echoes:
    """Surface echoes of a batch of rays.

    ``ray`` index of the ray, ``depth`` apparent depth (m), ``amplitude`` echo amplitude
    relative to a perfect reflector at zero depth (its rms, of the coherent and incoherent
    shares together), ``coherent`` the coherent (specular) share of it, the rest
    ``√(amplitude² − coherent²)`` being incoherent: the texture's and the material's diffuse
    return, a sum of random-phase wavelets that the image shows as speckle. ``point`` (when
    asked for) is each echo's hit point (scene frame, m). ``medium_end`` (n_rays,) is the apparent
    depth at which each ray first enters a solid (inf if never): backscatter of the medium
    exists only before it. ``slope`` (when asked for with elevation axes) is the rate of
    change of the echo's apparent depth with an elevational shift of the ray (m/m, signed: deeper
    for a shift along +e), from the surface's tangent plane at the hit.
    """

    ray: NDArray[np.int64]
    depth: Array
    amplitude: Array
    medium_end: Array
    slope: Array | None = None
    coherent: Array | None = None
    point: Array | None = None
    tilt: Array | None = None
    first: NDArray[np.bool_] | None = None
    coherent_lateral: Array | None = None


def trace(
    caster: RayCaster,
    part_materials: list[Material],
    medium: Material,
    origins: Array,
    directions: Array,
    max_depth: float,
    f_mhz: float,
    assumed_speed: float,
    floor_db: float,
    mirror: MirrorTables,
    axes: tuple[Array, Array],
    reverberation: bool = True,
    slopes: bool = False,
    points: bool = False,
    band: BandLoss | None = None,
) -> Echoes:
    """Follow rays through the scene and collect their echoes.

    Parameters
    ----------
    origins, directions : (n, 3) float, scene frame
    max_depth : float, metres (apparent)
    floor_db : float
        Stop a ray once no echo it could still return would reach this far below a
        perfect reflector's (dB, positive): two-way losses and transmission included.
    mirror : MirrorTables
        The probe's echo of a tilted surface element (:func:`sim_us.beam.mirror_of`).
    axes : two (n, 3) float, scene frame
        Each ray's lateral and elevational axes (the image plane's x and the probe's z):
        a surface's tilt is read in the image plane and in elevation.
    slopes : bool
        The echoes carry their depth ``slope`` along the elevational axis.
    points : bool
        Also return each echo's hit point (for the surface speckle).
    band : BandLoss, optional
        The probe's broadband echo's loss against its centre frequency's for the medium's
        attenuation law (:func:`sim_us.transducer.band_loss`): the medium's path loses
        that; None, the centre frequency's. The parts (printed solids, tens of dB/cm)
        attenuate at the centre frequency.
    """
    n = len(origins)
    # Material table: index 0 is the medium, i + 1 is part i.
    mats = [medium, *part_materials]
    speed = np.array([m.speed_m_s for m in mats])
    imped = np.array([m.impedance for m in mats])
    att_np = np.array([attenuation_db_per_m(m, f_mhz) for m in mats]) * np.log(10.0) / 20.0
    laterals, elevations = axes
    # Printed parts: layer height and build direction (index 0, the medium: none).
    layer_height = np.array([0.0, *(p.layer_m for p in caster.parts)])
    build_axis = np.array(
        [
            np.zeros(3),
            *(np.zeros(3) if p.build_axis is None else p.build_axis for p in caster.parts),
        ],
        dtype=float,
    )
    diffuse = np.array([m.diffuse for m in mats])
    log_floor = -floor_db * np.log(10.0) / 20.0

    # State of the rays still travelling, one row per ray, compacted with a single gather
    # per pass: position (3), direction (3), apparent depth, log path gain, material, ray.
    # ``log gain`` is the log of the path's two-way transmission times attenuation.
    # Column 10: the two-way loss at fc (dB) of the path's share in the medium, whose
    # broadband loss ``band`` gives (``log gain`` holds the parts' attenuation).
    medium_db_per_m = 2.0 * attenuation_db_per_m(medium, f_mhz)
    state = np.empty((n, 11))
    state[:, 0:3] = origins
    state[:, 3:6] = directions
    state[:, 6:8] = 0.0
    state[:, 8] = 0  # the medium
    state[:, 9] = np.arange(n)
    state[:, 10] = 0.0
    medium_end = np.full(n, np.inf)
    out_ray, out_depth, out_amp, out_slope, out_coh, out_point = [], [], [], [], [], []
    out_tilt, out_first, out_coh_lat = [], [], []
    first_pass = True
    # The broadband loss of each ray's path in the medium so far (state column 10 is its
    # loss at fc), kept beside the state rather than looked up again at every use.
    medium_loss = _medium_loss_db(state[:, 10], band)

    for _ in range(_MAX_PASSES):
        if len(state) == 0:
            break
        cur = state[:, 8].astype(np.int64)
        c = speed[cur]
        in_medium = cur == 0
        a2 = 2.0 * att_np[cur]  # two-way attenuation, nepers per metre
        budget = state[:, 7] - medium_loss * _NP_PER_DB - log_floor  # nepers left
        max_geo = (max_depth - state[:, 6]) * c / assumed_speed
        with np.errstate(divide="ignore", invalid="ignore"):
            max_att = np.where(a2 > 0, budget / a2, np.inf)
            if band is not None and medium_db_per_m > 0:
                # In the medium: as far as its broadband loss leaves the budget.
                fc_end = band.fc_for(medium_loss + budget / _NP_PER_DB)
                max_att = np.where(in_medium, (fc_end - state[:, 10]) / medium_db_per_m, max_att)
        a2 = np.where(in_medium, 0.0, a2) if band is not None else a2
        hits = caster.first_hits(state[:, 0:3], state[:, 3:6], np.minimum(max_geo, max_att))
        hit = hits.part >= 0
        state, cur, c, a2, medium_loss = state[hit], cur[hit], c[hit], a2[hit], medium_loss[hit]
        t, part, nrm = hits.t[hit], hits.part[hit], hits.normal[hit]
        dirs = state[:, 3:6]
        ray = state[:, 9].astype(np.int64)
        y_app = state[:, 6] + t * assumed_speed / c
        log_gain = state[:, 7] - a2 * t
        if band is not None:
            state[:, 10] += np.where(cur == 0, medium_db_per_m * t, 0.0)
            medium_loss = _medium_loss_db(state[:, 10], band)
        path_gain = log_gain - medium_loss * _NP_PER_DB
        cos_in = np.einsum("ij,ij->i", dirs, nrm)
        entering = cos_in < 0
        new = np.where(entering, part + 1, 0)
        r = amplitude_reflection(imped[cur], imped[new])
        surface = part + 1
        facing = np.maximum(np.abs(cos_in), 1e-12)
        zeros = np.zeros(len(t))
        if hits.texture_rms is not None:
            # k of the incident medium; σ along the smoothed normal.
            k_sigma_cos = 2 * np.pi * f_mhz * 1e6 / c * hits.texture_rms[hit] * facing
        else:
            k_sigma_cos = zeros
        tilt_el, shape, coherent, spec_bounce, coherent_lateral = _surface_echoes(
            np.ascontiguousarray(dirs),
            nrm,
            laterals,
            elevations,
            ray,
            mirror.depth_nodes(y_app),
            zeros if hits.texture_slope is None else hits.texture_slope[hit],
            zeros if hits.layer_share is None else hits.layer_share[hit],
            layer_height[surface],
            build_axis[surface],
            k_sigma_cos,
            diffuse[surface],
            mirror.lateral,
            mirror.elevation,
            1.0 / mirror.tilt_step,
            mirror.focal_spot_m,
            mirror.wavelength_m,
        )
        path = np.exp(path_gain)
        amp = path * r * shape
        out_ray.append(ray)
        out_depth.append(y_app)
        out_amp.append(amp)
        # The coherent (mirror) echo: all of a smooth surface's echo facing the probe,
        # none far off it, where only the incoherent facets' and diffuse returns remain.
        out_coh.append(path * r * coherent)
        out_tilt.append(tilt_el)
        # The coherent echo per unit of the elevation lobe: the caller may integrate that
        # lobe over elevation more finely than one tilt per ray.
        out_coh_lat.append(path * r * coherent_lateral)
        out_first.append(np.full(len(ray), first_pass))
        if points:
            out_point.append(state[:, 0:3] + t[:, None] * dirs)
        if slopes:
            # The surface's tangent plane n·(p − p_hit) = 0: shifting the ray by dz along
            # its elevational axis e moves the hit by dt = −(n·e)/(n·d) dz along the ray,
            # displayed at the speed the scanner assumes (the path before the surface is
            # taken as unchanged). Grazing hits give large slopes; the caller bounds them.
            cos_e = np.einsum("ij,ij->i", elevations[ray], nrm)
            with np.errstate(divide="ignore", invalid="ignore"):
                slope = -cos_e / cos_in * assumed_speed / c
            out_slope.append(np.nan_to_num(slope, nan=0.0))
        if reverberation:
            # Echo bounced back by the probe face and reflected once more: one more round
            # trip, specular part only (strong flat reflectors such as the tank floor).
            keep = 2 * y_app < max_depth
            out_ray.append(ray[keep])
            out_depth.append(2 * y_app[keep])
            out_amp.append((amp * r * _FACE_REFLECTION * spec_bounce * path)[keep])
            out_coh.append(out_amp[-1])  # the specular part only: coherent
            out_tilt.append(2.0 * tilt_el[keep])
            out_coh_lat.append(np.zeros(int(keep.sum())))
            out_first.append(np.zeros(int(keep.sum()), dtype=bool))
            if points:
                out_point.append(out_point[-1][keep])
            if slopes:
                out_slope.append(2 * out_slope[-1][keep])  # twice the path, twice the slope
        first_entry = entering & (cur == 0)
        hit_rays = ray[first_entry]
        medium_end[hit_rays] = np.minimum(medium_end[hit_rays], y_app[first_entry])
        state[:, 0:3] += (t + _STEP_M)[:, None] * dirs
        state[:, 6] = y_app
        state[:, 7] = log_gain + np.log1p(-(r**2))
        state[:, 8] = new
        alive = state[:, 7] - medium_loss * _NP_PER_DB > log_floor
        going = alive & (y_app < max_depth)
        state, medium_loss = state[going], medium_loss[going]
        first_pass = False

    if not out_ray:
        return Echoes(
            np.empty(0, dtype=np.int64),
            np.empty(0),
            np.empty(0),
            medium_end,
            np.empty(0) if slopes else None,
            np.empty(0),
            np.empty((0, 3)) if points else None,
            np.empty(0),
            np.empty(0, dtype=bool),
            np.empty(0),
        )
    return Echoes(
        np.concatenate(out_ray),
        np.concatenate(out_depth),
        np.concatenate(out_amp),
        medium_end,
        np.concatenate(out_slope) if slopes else None,
        np.concatenate(out_coh),
        np.concatenate(out_point) if points else None,
        np.concatenate(out_tilt),
        np.concatenate(out_first),
        np.concatenate(out_coh_lat),
    )
