"""Pulse propagation along straight rays: surface echoes, transmission, attenuation,
travel time and shadow.

Each ray starts at the transducer face in the medium and is followed through every
surface it meets. At a surface the echo amplitude is

    A = T · r · [(1 − d) · exp(−(θ/θs)²) + d] · 10^(−L / 20)

with ``r = |Z2 − Z1| / (Z2 + Z1)`` the amplitude reflection coefficient, θ the incidence
angle, θs the surface's specular width, d its diffuse (roughness) share, ``T`` the
two-way transmission ``Π (1 − r_j²)`` through the surfaces crossed so far and ``L`` the
two-way attenuation (dB) of the path. The echo is placed at the *apparent* depth: the
travel time at each segment's true speed, displayed at the speed the scanner assumes.
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

__all__ = ["Echoes", "trace"]

Array = NDArray[np.float64]

# Amplitude reflection of the transducer face for the reverberation echo.
_FACE_REFLECTION = 0.5
# A new pass starts this far past the last hit so the same surface is not found again.
_STEP_M = 1e-6
_MAX_PASSES = 24


@dataclass(frozen=True)
class Echoes:
    """Surface echoes of a batch of rays.

    ``ray`` index of the ray, ``depth`` apparent depth (m), ``amplitude`` echo amplitude
    relative to a perfect reflector at zero depth. ``medium_end`` (n_rays,) is the apparent
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
    reverberation: bool = True,
    elevations: Array | None = None,
) -> Echoes:
    """Follow rays through the scene and collect their echoes.

    Parameters
    ----------
    origins, directions : (n, 3) float, scene frame
    max_depth : float, metres (apparent)
    floor_db : float
        Stop a ray once no echo it could still return would reach this far below a
        perfect reflector's (dB, positive): two-way losses and transmission included.
    elevations : (n, 3) float, scene frame, optional
        Each ray's elevational axis: the echoes then carry their depth ``slope``.
    """
    n = len(origins)
    # Material table: index 0 is the medium, i + 1 is part i.
    mats = [medium, *part_materials]
    speed = np.array([m.speed_m_s for m in mats])
    imped = np.array([m.impedance for m in mats])
    att_np = np.array([attenuation_db_per_m(m, f_mhz) for m in mats]) * np.log(10.0) / 20.0
    spec_w = np.radians([m.specular_width_deg for m in mats])
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
    out_ray, out_depth, out_amp, out_slope = [], [], [], []

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
        theta = np.arccos(np.minimum(np.abs(cos_in), 1.0))
        surface = part + 1
        spec = np.exp(-((theta / spec_w[surface]) ** 2))
        shape = (1.0 - diffuse[surface]) * spec + diffuse[surface]
        path = np.exp(log_gain)
        amp = path * r * shape
        out_ray.append(ray)
        out_depth.append(y_app)
        out_amp.append(amp)
        if elevations is not None:
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
            out_amp.append((amp * r * _FACE_REFLECTION * spec * path)[keep])
            if elevations is not None:
                out_slope.append(2 * out_slope[-1][keep])  # twice the path, twice the slope
        first_entry = entering & (cur == 0)
        hit_rays = ray[first_entry]
        medium_end[hit_rays] = np.minimum(medium_end[hit_rays], y_app[first_entry])
        state[:, 0:3] += (t + _STEP_M)[:, None] * dirs
        state[:, 6] = y_app
        state[:, 7] = log_gain + np.log1p(-(r**2))
        state[:, 8] = new
        state = state[(state[:, 7] > log_floor) & (y_app < max_depth)]

    if not out_ray:
        empty = np.empty(0) if elevations is not None else None
        return Echoes(np.empty(0, dtype=np.int64), np.empty(0), np.empty(0), medium_end, empty)
    return Echoes(
        np.concatenate(out_ray),
        np.concatenate(out_depth),
        np.concatenate(out_amp),
        medium_end,
        np.concatenate(out_slope) if elevations is not None else None,
    )
