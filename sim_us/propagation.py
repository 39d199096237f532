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
    exists only before it.
    """

    ray: NDArray[np.int64]
    depth: Array
    amplitude: Array
    medium_end: Array


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
) -> Echoes:
    """Follow rays through the scene and collect their echoes.

    Parameters
    ----------
    origins, directions : (n, 3) float, scene frame
    max_depth : float, metres (apparent)
    floor_db : float
        Stop a ray once its two-way loss exceeds this (dB, positive).
    """
    n = len(origins)
    # Material table: index 0 is the medium, i + 1 is part i.
    mats = [medium, *part_materials]
    speed = np.array([m.speed_m_s for m in mats])
    imped = np.array([m.impedance for m in mats])
    att = np.array([attenuation_db_per_m(m, f_mhz) for m in mats])
    spec_w = np.radians([m.specular_width_deg for m in mats])
    diffuse = np.array([m.diffuse for m in mats])

    active = np.arange(n)
    pos = np.asarray(origins, dtype=float).copy()
    dirs = np.asarray(directions, dtype=float)
    y_app = np.zeros(n)
    loss = np.zeros(n)
    trans = np.ones(n)
    cur = np.zeros(n, dtype=np.int64)
    medium_end = np.full(n, np.inf)
    out_ray, out_depth, out_amp = [], [], []

    for _ in range(_MAX_PASSES):
        if active.size == 0:
            break
        a = active
        c = speed[cur[a]]
        max_geo = (max_depth - y_app[a]) * c / assumed_speed
        with np.errstate(divide="ignore"):
            max_att = np.where(att[cur[a]] > 0, (floor_db - loss[a]) / (2 * att[cur[a]]), np.inf)
        hits = caster.first_hits(pos[a], dirs[a], np.minimum(max_geo, max_att))
        hit = hits.part >= 0
        a, t, part, nrm = a[hit], hits.t[hit], hits.part[hit], hits.normal[hit]
        c = c[hit]
        d = dirs[a]
        y_hit = y_app[a] + t * assumed_speed / c
        loss_hit = loss[a] + 2.0 * att[cur[a]] * t
        cos_in = np.einsum("ij,ij->i", d, nrm)
        entering = cos_in < 0
        new = np.where(entering, part + 1, 0)
        r = amplitude_reflection(imped[cur[a]], imped[new])
        theta = np.arccos(np.clip(np.abs(cos_in), 0.0, 1.0))
        surface = part + 1
        spec = np.exp(-((theta / spec_w[surface]) ** 2))
        shape = (1.0 - diffuse[surface]) * spec + diffuse[surface]
        amp = trans[a] * r * shape * 10.0 ** (-loss_hit / 20.0)
        out_ray.append(a)
        out_depth.append(y_hit)
        out_amp.append(amp)
        if reverberation:
            # Echo bounced back by the probe face and reflected once more: one more round
            # trip, specular part only (strong flat reflectors such as the tank floor).
            rev_amp = amp * r * _FACE_REFLECTION * spec * 10.0 ** (-loss_hit / 20.0)
            keep = 2 * y_hit < max_depth
            out_ray.append(a[keep])
            out_depth.append(2 * y_hit[keep])
            out_amp.append(rev_amp[keep])
        first_entry = entering & (cur[a] == 0)
        medium_end[a[first_entry]] = np.minimum(medium_end[a[first_entry]], y_hit[first_entry])
        trans[a] *= 1.0 - r**2
        cur[a] = new
        pos[a] += (t + _STEP_M)[:, None] * d
        y_app[a] = y_hit
        loss[a] = loss_hit
        active = a[(loss_hit < floor_db) & (y_hit < max_depth)]

    if not out_ray:
        return Echoes(np.empty(0, dtype=np.int64), np.empty(0), np.empty(0), medium_end)
    return Echoes(
        np.concatenate(out_ray), np.concatenate(out_depth), np.concatenate(out_amp), medium_end
    )
