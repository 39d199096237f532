"""Wires: targets thinner than the beam, drawn from the physics of a small cylinder
rather than ray-cast.

A calibration wire (nylon monofilament or steel, 0.1–0.5 mm) is thinner than the beam's
lateral and elevation widths, so a ray model of it is wrong twice over: a ray that hits
it throws a hard shadow where the real beam diffracts around it (the wire under another
stays visible on every scanner), and a ray that grazes it draws a mirror the full
beam's width. Each wire is therefore a line target the beam crosses:

- **Where.** In each elevation sub-plane of the slice the wire crosses at one point
  (``x``, ``y``); its echo comes from the specular point of the cylinder's surface facing
  the probe, ``a·√(1 − d_y²)`` above its axis (``a`` the radius, ``d`` the axis).
- **How strong.** The amplitude reflection coefficient of the wire's material in the
  medium, times three factors: across the wire (in the image plane) a convex mirror of
  radius of curvature ``a / (1 − d_x²)`` returns coherently only from its first Fresnel
  zone, ``√(λ a')`` wide, of the focal spot ``λ F#`` a flat mirror must fill (capped at
  one); along the wire it is a straight mirror strip, tilted in elevation by the angle of
  its axis to the beam, so its echo follows the probe's elevation mirror lobe
  (:class:`sim_us.transducer.MirrorTables`, as a tilted plane's), with the material's
  diffuse share returned at any tilt; and the two-way loss of
  the broadband echo in the medium. Each sub-plane adds its share of the elevation beam
  (the simulator's sub-plane weights), so a wire crossing the slice obliquely draws the
  smear the slice thickness gives it.
- **Comet tail.** Sound entering the wire rings between its walls: echoes every
  ``2a·c₀/c_wire`` of apparent depth, the m-th of amplitude ``(1 − R²) R^(2m−1)`` (R the
  wall's reflection coefficient) less the wire's own attenuation, until they fall below
  the display's range: a long tail under a steel wire (R ≈ 0.94), two or three faint
  echoes under nylon (R ≈ 0.3).
- **Drawn** at the depth its time of flight gives at the scanner's assumed speed of
  sound (the medium's own speed is what the sound travels at).
- **Hidden** where the scanline has already entered a solid part (the ray-cast scene's
  medium end): a wire inside or behind a solid is not seen.

No shadow: the wire removes a sliver of the beam a few wavelengths wide, which diffraction
fills within a millimetre or two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .materials import MATERIALS, Material, amplitude_reflection

__all__ = ["Wire", "WireEchoes", "wire_echoes"]

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Wire:
    """A straight wire between two points (scene frame, metres), of a diameter (m) and a
    material (a name of :data:`~sim_us.materials.MATERIALS` or a :class:`Material`)."""

    name: str
    front: Array
    back: Array
    diameter_m: float
    material: str | Material = "nylon"

    def material_of(self) -> Material:
        return self.material if isinstance(self.material, Material) else MATERIALS[self.material]


@dataclass(frozen=True)
class WireEchoes:
    """Point echoes to splat: frame, sub-plane, fractional column and row, and amplitude²
    relative to a flat mirror facing the probe (before the sub-plane's beam weight)."""

    frame: NDArray[np.int64]
    plane: NDArray[np.int64]
    col: Array
    row: Array
    energy: Array


def wire_echoes(
    wires: tuple[Wire, ...],
    T_scene_us: Array,
    z_planes: Array,
    *,
    medium: Material,
    width_px: int,
    true_spacing: tuple[float, float],
    offset: tuple[float, float],
    assumed_speed_m_s: float,
    f_mhz: float,
    wavelength_m: float,
    focal_spot_m: float,
    elevation_lobe,
    loss_db,
    dynamic_range_db: float,
) -> WireEchoes:
    """The echoes (see the module doc) of ``wires`` in frames at ``T_scene_us`` (n, 4, 4),
    in the sub-planes at elevations ``z_planes`` (K,). ``elevation_lobe(depth, tilt)`` is
    the probe's elevation mirror lobe (amplitude), ``loss_db(depth)`` the medium's two-way
    loss; ``offset`` the image origin's (lateral, axial) offset in the face frame."""
    out: list[tuple] = []
    sx, sy = true_spacing
    T_us_scene = np.linalg.inv(np.asarray(T_scene_us, dtype=float))
    floor = 10.0 ** (-dynamic_range_db / 20.0)
    for wire in wires:
        mat = wire.material_of()
        R = float(amplitude_reflection(medium.impedance, mat.impedance))
        a = wire.diameter_m / 2.0
        A = T_us_scene[:, :3, :3] @ wire.front + T_us_scene[:, :3, 3]  # (n, 3)
        B = T_us_scene[:, :3, :3] @ wire.back + T_us_scene[:, :3, 3]
        d = B - A
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        dz = B[:, 2] - A[:, 2]
        ok = np.abs(dz) > 1e-9
        u = np.where(
            ok[:, None], (z_planes[None, :] - A[:, 2:3]) / np.where(ok, dz, 1.0)[:, None], -1
        )
        inside = (u >= 0.0) & (u <= 1.0)  # (n, K)
        f, k = np.nonzero(inside)
        if not len(f):
            continue
        P = A[f] + u[f, k][:, None] * (B[f] - A[f])  # crossing points, us frame
        dd = d[f]
        depth = P[:, 1] - a * np.sqrt(np.clip(1.0 - dd[:, 1] ** 2, 0.0, 1.0))
        # Across: the convex mirror's first Fresnel zone against the focal spot.
        a_eff = a / np.clip(1.0 - dd[:, 0] ** 2, 0.05, 1.0)
        across = np.minimum(np.sqrt(wavelength_m * a_eff) / focal_spot_m, 1.0)
        # Along: a straight strip tilted in elevation by its axis' angle to the beam.
        tilt = np.arctan2(dd[:, 1], np.abs(dd[:, 2]) + 1e-12)
        # The wire's diffuse share (its surface's fine roughness) returns at any tilt.
        along = np.sqrt(elevation_lobe(depth, tilt) ** 2 + mat.diffuse**2)
        amp = R * across * along * 10.0 ** (-loss_db(depth) / 20.0)
        col = (P[:, 0] - offset[0]) / sx + (width_px - 1) / 2.0
        # Drawn where the echo's time of flight puts it at the scanner's assumed speed.
        row = (depth * assumed_speed_m_s / medium.speed_m_s - offset[1]) / sy
        out.append((f, k, col, row, amp**2))
        # The comet tail: reverberation between the wire's walls.
        step = 2.0 * a * assumed_speed_m_s / mat.speed_m_s / sy  # rows per round trip
        trip_db = mat.attenuation_db_cm_mhz * f_mhz**mat.attenuation_power * 4.0 * a * 100.0
        loss = 10.0 ** (-trip_db / 20.0)  # the wire's own attenuation per round trip
        ring = (1.0 - R**2) * R
        m = 1
        while ring > floor and m < 200:
            out.append((f, k, col, row + m * step, (amp / R * ring * loss**m) ** 2))
            ring *= R**2
            m += 1
    if not out:
        e = np.zeros(0)
        return WireEchoes(e.astype(np.int64), e.astype(np.int64), e, e, e)
    return WireEchoes(*(np.concatenate(v) for v in zip(*out, strict=True)))
