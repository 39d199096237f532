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

import numpy as np
from numpy.typing import NDArray

from .materials import Material, amplitude_reflection, attenuation_db_per_m
from .raycast import RayCaster
from .transducer import MIRROR_SLOPES, MirrorTables

__all__ = ["Echoes", "coherent_factor", "rough_surface_shape", "trace"]

Array = NDArray[np.float64]

# Amplitude reflection of the transducer face for the reverberation echo.
_FACE_REFLECTION = 0.5
# A new pass starts this far past the last hit so the same surface is not found again.
_STEP_M = 1e-6
_MAX_PASSES = 24


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
    return np.exp(-2.0 * np.asarray(k_sigma_cos) ** 2)


def rough_surface_shape(
    mirror: Array, widened: Array, diffuse: Array, k_sigma_cos: Array
) -> tuple[Array, Array]:
    """Echo shape factor (rms amplitude re a mirror facing the probe) of a surface, and its
    coherent part.

    ``mirror`` is the echo S of a smooth mirror tilted as the surface is, ``widened`` the
    lobe S_s of facets tilted about it by the texture's slopes, ``diffuse`` the material's
    diffuse share d, ``k_sigma_cos`` the texture's k σ cos θ (0: smooth). The energy

        shape² = (1 − d²) (χ² S² + (1 − χ²) S_s²) + d²

    splits into the coherent χ S √(1 − d²) and the incoherent rest (the facets' and the
    diffuse return, random in phase: speckle). A surface facing the probe returns all of a
    mirror's energy when smooth, less when rough only as far as the facets' tilts send it
    past the aperture. Returns (shape, coherent).
    """
    chi = coherent_factor(k_sigma_cos)
    keep = 1.0 - diffuse**2
    coherent = np.sqrt(keep) * chi * mirror
    energy = keep * (chi**2 * mirror**2 + (1.0 - chi**2) * widened**2) + diffuse**2
    return np.sqrt(energy), coherent


def _with_treads(
    widened: Array,
    share: Array,
    part: NDArray[np.int64],
    normal: Array,
    ray: NDArray[np.int64],
    depth: Array,
    layers: tuple[Array, Array],
    axes: tuple[Array, Array],
    directions: Array,
    mirror: MirrorTables,
) -> Array:
    """The texture's incoherent lobe with a print's layer treads in it: of the energy the
    texture scatters, the layer staircase's share ``share`` comes back from its treads,
    small mirrors facing the build direction b (on the side the surface faces), each
    ``h / tan α`` wide (h the layer height, α the surface's angle to the build plate);
    treads narrower than the focal spot (λ F#) fill it in part, returning ``w / spot`` of
    its energy (a row of them, at depths a layer apart, adds in energy). The echo of the
    treads is the mirror's lobe at b's tilt from the beam, widened by the tread's own
    diffraction (≈ λ / 2w, as facets of that rms tilt): a printed sphere seen along its
    build direction echoes from its whole cap, seen from aside only about its top. The
    rest (the roughness's share) keeps the facets' widened lobe."""
    height, axis = layers
    surface = part + 1
    h = height[surface]
    b = axis[surface]
    printed = (share > 0) & (h > 0)
    if not printed.any():
        return widened
    cos_a = np.einsum("ij,ij->i", b, normal)
    b = np.where(cos_a[:, None] < 0, -b, b)  # the treads face out of the surface
    cos_a = np.abs(cos_a)
    sin_a = np.sqrt(np.maximum(1.0 - cos_a**2, 0.0))
    width = np.divide(h * cos_a, sin_a, out=np.full(len(sin_a), np.inf), where=sin_a > 0)
    fill = np.minimum(1.0, width / mirror.focal_spot_m) if mirror.focal_spot_m > 0 else 1.0
    laterals, elevations = axes
    facing = np.maximum(np.abs(np.einsum("ij,ij->i", directions, b)), 1e-12)
    tilt_lat = np.arctan(np.einsum("ij,ij->i", laterals[ray], b) / facing)
    tilt_el = np.arctan(np.einsum("ij,ij->i", elevations[ray], b) / facing)
    away = np.einsum("ij,ij->i", directions, b) > 0  # treads facing away from the probe
    # A tread narrower than the focal spot diffracts: its echo spreads over ≈ λ / 2w.
    top = MIRROR_SLOPES[-1]
    spread = np.minimum(
        np.divide(mirror.wavelength_m, 2.0 * width, out=np.full(len(width), top), where=width > 0),
        top,
    )
    _, _, lat, el = mirror.lobes(depth, tilt_lat, tilt_el, spread)
    treads2 = np.where(away, 0.0, fill * (lat * el) ** 2)
    energy = (1.0 - share) * widened**2 + share * treads2
    return np.where(printed, np.sqrt(energy), widened)


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
    """
    n = len(origins)
    # Material table: index 0 is the medium, i + 1 is part i.
    mats = [medium, *part_materials]
    speed = np.array([m.speed_m_s for m in mats])
    imped = np.array([m.impedance for m in mats])
    att_np = np.array([attenuation_db_per_m(m, f_mhz) for m in mats]) * np.log(10.0) / 20.0
    laterals, elevations = axes
    # Printed parts: layer height and build direction (index 0, the medium: none).
    layers = (
        np.array([0.0, *(p.layer_m for p in caster.parts)]),
        np.array(
            [
                np.zeros(3),
                *(np.zeros(3) if p.build_axis is None else p.build_axis for p in caster.parts),
            ]
        ),
    )
    diffuse = np.array([m.diffuse for m in mats])
    log_floor = -floor_db * np.log(10.0) / 20.0

    # State of the rays still travelling, one row per ray, compacted with a single gather
    # per pass: position (3), direction (3), apparent depth, log path gain, material, ray.
    # ``log gain`` is the log of the path's two-way transmission times attenuation.
    state = np.empty((n, 10))
    state[:, 0:3] = origins
    state[:, 3:6] = directions
    state[:, 6:8] = 0.0
    state[:, 8] = 0  # the medium
    state[:, 9] = np.arange(n)
    medium_end = np.full(n, np.inf)
    out_ray, out_depth, out_amp, out_slope, out_coh, out_point = [], [], [], [], [], []
    out_tilt, out_first, out_coh_lat = [], [], []
    first_pass = True

    for _ in range(_MAX_PASSES):
        if len(state) == 0:
            break
        cur = state[:, 8].astype(np.int64)
        c = speed[cur]
        a2 = 2.0 * att_np[cur]  # two-way attenuation, nepers per metre
        max_geo = (max_depth - state[:, 6]) * c / assumed_speed
        with np.errstate(divide="ignore"):
            max_att = np.where(a2 > 0, (state[:, 7] - log_floor) / a2, np.inf)
        hits = caster.first_hits(state[:, 0:3], state[:, 3:6], np.minimum(max_geo, max_att))
        hit = hits.part >= 0
        state, cur, c, a2 = state[hit], cur[hit], c[hit], a2[hit]
        t, part, nrm = hits.t[hit], hits.part[hit], hits.normal[hit]
        dirs = state[:, 3:6]
        ray = state[:, 9].astype(np.int64)
        y_app = state[:, 6] + t * assumed_speed / c
        log_gain = state[:, 7] - a2 * t
        cos_in = np.einsum("ij,ij->i", dirs, nrm)
        entering = cos_in < 0
        new = np.where(entering, part + 1, 0)
        r = amplitude_reflection(imped[cur], imped[new])
        surface = part + 1
        # The surface's tilt from facing the probe, in the image plane and in elevation.
        facing = np.maximum(np.abs(cos_in), 1e-12)
        tilt_lat = np.arctan(np.einsum("ij,ij->i", laterals[ray], nrm) / facing)
        tilt_el = np.arctan(np.einsum("ij,ij->i", elevations[ray], nrm) / facing)
        facets = hits.texture_slope[hit] if hits.texture_slope is not None else np.zeros(len(t))
        lat0, el0, lat_w, el_w = mirror.lobes(y_app, tilt_lat, tilt_el, facets)
        spec, widened = lat0 * el0, lat_w * el_w
        if hits.layer_share is not None:
            widened = _with_treads(
                widened,
                hits.layer_share[hit],
                part,
                nrm,
                ray,
                y_app,
                layers,
                (laterals, elevations),
                dirs,
                mirror,
            )
        if hits.texture_rms is not None:
            # k of the incident medium; σ along the smoothed normal.
            k_sigma_cos = 2 * np.pi * f_mhz * 1e6 / c * hits.texture_rms[hit] * facing
        else:
            k_sigma_cos = np.zeros(len(t))
        shape, coherent = rough_surface_shape(spec, widened, diffuse[surface], k_sigma_cos)
        # What a second bounce (the reverberation echo) keeps: the mirror's share.
        spec_bounce = coherent_factor(k_sigma_cos) * spec
        path = np.exp(log_gain)
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
        out_coh_lat.append(
            path * r * np.sqrt(1.0 - diffuse[surface] ** 2) * coherent_factor(k_sigma_cos) * lat0
        )
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
        state = state[(state[:, 7] > log_floor) & (y_app < max_depth)]
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
