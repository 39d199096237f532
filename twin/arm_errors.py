"""Error sources of the real arm beyond its DH table: what a UR3 does between the angles
its motors are driven to and where its links end up, and the session clock they need.

Each model here is physical and off at zero (see :class:`twin.robot.RobotConfig`):

- **joint compliance** — the gravity and payload torque of each joint twists its
  harmonic drive: the link lags the motor by the catalogue's torque–twist curve;
- **gear transmission error** — a strain-wave gear's output angle wanders periodically
  with the wave-generator angle (N × the joint angle), plus **lost motion** (hysteresis)
  of a sign set by the direction the joint last moved;
- **thermal drift** — warm aluminium links grow: DH ``a`` and ``d`` scale by α ΔT(t);
- **session clock** — how long moves, settling and grabs take, so that time-dependent
  sources (the arm's temperature, the water's) know when a frame was taken.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calib.dh import DHTable

__all__ = [
    "ALUMINIUM_EXPANSION_PER_K",
    "GEAR_RATIO",
    "HARMONIC_DRIVE_STIFFNESS",
    "ROBOT_STREAM_KEY",
    "UR_GEAR_SIZES",
    "JointErrors",
    "harmonic_drive_twist",
    "robot_stream",
    "thermal_rise_k",
    "thermal_table",
    "trapezoid_time_s",
]

Array = NDArray[np.float64]

#: Spawn key of the per-robot stream (fixed properties of one arm, e.g. the phases of its
#: gears' transmission error): the same for every dataset of a scenario's robot.
ROBOT_STREAM_KEY = 400


def robot_stream(seed: int) -> np.random.Generator:
    """The per-robot generator of a scenario seed (independent of the stage streams)."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(ROBOT_STREAM_KEY,)))


# ----------------------------------------------------------------------- joint compliance

#: Strain-wave gear torsional stiffness by size (Harmonic Drive CSF/CSG component-set
#: catalogue, reduction ratio ≥ 80): (T1, T2) in N m and (K1, K2, K3) in N m/rad. The
#: torque–twist curve is piecewise linear: slope 1/K1 up to T1, 1/K2 up to T2, 1/K3 above
#: (the catalogue's own formula). Sizes 14–20 span ≈ 5e3–3e4 N m/rad.
HARMONIC_DRIVE_STIFFNESS: dict[int, tuple[float, float, float, float, float]] = {
    14: (2.0, 6.9, 0.47e4, 0.61e4, 0.71e4),
    17: (3.9, 12.0, 1.0e4, 1.4e4, 1.6e4),
    20: (7.0, 25.0, 1.6e4, 2.5e4, 2.9e4),
}

#: Gear size per joint of a UR3 (base, shoulder, elbow, three wrists). UR does not
#: publish them; the estimate follows the joints' torque ratings (shoulder and base the
#: largest drive, the wrists the smallest that carries the 3 kg payload).
UR_GEAR_SIZES = (20, 20, 17, 14, 14, 14)

#: Reduction ratio of the joints' strain-wave gears (UR joints: ≈ 100–121; one value for
#: all joints): the wave generator turns N times per joint revolution.
GEAR_RATIO = 101


def harmonic_drive_twist(tau: Array, sizes: tuple[int, ...] = UR_GEAR_SIZES) -> Array:
    """Twist (6,) in radians of each joint's gear under torques ``tau`` (6,) in N m, from
    the catalogue's piecewise-linear torque–twist curve (odd in the torque)."""
    tau = np.asarray(tau, dtype=float)
    out = np.empty_like(tau)
    for i, t in enumerate(tau):
        T1, T2, K1, K2, K3 = HARMONIC_DRIVE_STIFFNESS[sizes[i]]
        a = abs(t)
        if a <= T1:
            phi = a / K1
        elif a <= T2:
            phi = T1 / K1 + (a - T1) / K2
        else:
            phi = T1 / K1 + (T2 - T1) / K2 + (a - T2) / K3
        out[i] = np.copysign(phi, t)
    return out


# --------------------------------------------------------------- the joints put together

#: Weights of the transmission error's spectral lines, as fractions of half its
#: peak-to-peak value: 1× and 2× the wave-generator revolution (the dominant lines of a
#: strain-wave gear) and 1× the output revolution (the catalogue's accuracy curves). They
#: sum to 1, so the error never exceeds the catalogue's peak-to-peak value.
_TE_LINES = ((GEAR_RATIO, 0.40), (2 * GEAR_RATIO, 0.35), (1, 0.25))


@dataclass(frozen=True, eq=False)
class JointErrors:
    """What lies between a joint's motor and its link: compliance, transmission error and
    lost motion. ``q_link - q_motor`` = TE(q_motor) + ± lost motion / 2 − twist(τ(q_link)).

    Attributes
    ----------
    compliance_scale : float
        Multiplies the catalogue twist (0 = rigid joints).
    te_pp_rad : float
        Peak-to-peak transmission error, radians (0 = off).
    lost_motion_rad : float
        Lost motion (hysteresis width), radians (0 = off).
    te_phases : (6, 3) float
        Phase of each spectral line of each joint (drawn once per robot).
    """

    compliance_scale: float
    te_pp_rad: float
    lost_motion_rad: float
    te_phases: Array

    @classmethod
    def create(
        cls,
        compliance_scale: float,
        te_pp_arcmin: float,
        lost_motion_arcmin: float,
        robot_rng: np.random.Generator,
    ) -> JointErrors | None:
        """The joints' model, or ``None`` when every term is off (then nothing is drawn)."""
        if compliance_scale == 0 and te_pp_arcmin == 0 and lost_motion_arcmin == 0:
            return None
        phases = (
            robot_rng.uniform(0.0, 2 * np.pi, (6, len(_TE_LINES)))
            if te_pp_arcmin > 0
            else np.zeros((6, len(_TE_LINES)))
        )
        arcmin = np.pi / (180 * 60)
        return cls(compliance_scale, te_pp_arcmin * arcmin, lost_motion_arcmin * arcmin, phases)

    def transmission_error(self, q_motor: Array) -> Array:
        """Δq (6,) radians of the gears at motor-side angles ``q_motor`` (6,):
        Σ_k A_k sin(n_k q + φ_k) with n_k ∈ {N, 2N, 1} (wave-generator and output lines)."""
        if self.te_pp_rad == 0:
            return np.zeros(6)
        out = np.zeros(6)
        for k, (n, w) in enumerate(_TE_LINES):
            out += w * 0.5 * self.te_pp_rad * np.sin(n * q_motor + self.te_phases[:, k])
        return out

    def offset(
        self,
        q_motor: Array,
        q_link: Array,
        approach: Array,
        torque: Callable[[Array], Array],
    ) -> Array:
        """``q_link − q_motor`` (6,), radians. ``approach`` (6,) is the sign of each joint's
        last motion (lost motion lags it); ``torque(q)`` the joints' holding torque (6,)
        in N m at link angles ``q``."""
        e = self.transmission_error(q_motor) + 0.5 * self.lost_motion_rad * approach
        if self.compliance_scale > 0:
            # The motor holds the link against gravity with τ = qfrc_bias; the gear's spring
            # gives way by its twist, so the link sags: q_link = q_motor − τ / K(τ).
            e = e - self.compliance_scale * harmonic_drive_twist(torque(q_link))
        return e

    def settle(
        self,
        q_target: Array,
        guided: bool,
        approach: Array,
        torque: Callable[[Array], Array],
    ) -> tuple[Array, Array]:
        """Link and motor angles (each (6,)) after a move to ``q_target``.

        Commanded (``guided`` false): the motors reach ``q_target`` and the links land off
        by the offset. Hand-guided: the operator puts the *links* at ``q_target`` and the
        motors sit off by the offset. A fixed point (the offset depends on both weakly:
        its derivative is ≲ 0.05, so four passes converge far below a nanoradian).
        """
        q_motor = q_target.copy()
        q_link = q_target.copy()
        for _ in range(4):
            e = self.offset(q_motor, q_link, approach, torque)
            if guided:
                q_motor = q_target - e
            else:
                q_link = q_target + e
        return q_link, q_motor


# ------------------------------------------------------------------------- thermal drift

#: Linear expansion coefficient of the arm's aluminium tubes and castings (1/K).
ALUMINIUM_EXPANSION_PER_K = 23e-6


def thermal_rise_k(t_s: float, rise_k: float, time_constant_s: float) -> float:
    """Temperature rise ΔT(t) = ΔT∞ (1 − e^(−t/τ)) of the arm ``t_s`` seconds after the
    session started cold (first-order warm-up of the joints' motors and drives)."""
    if rise_k == 0:
        return 0.0
    return rise_k * (1.0 - np.exp(-t_s / time_constant_s))


def thermal_table(table: DHTable, delta_t_k: float) -> DHTable:
    """The DH table of the arm warmed by ``delta_t_k``: every length (d, a) grows by
    α ΔT; angles stay."""
    p = table.as_array()
    p[:, 1:3] *= 1.0 + ALUMINIUM_EXPANSION_PER_K * delta_t_k
    return DHTable.from_array(p, name=f"{table.name}@{delta_t_k:.2f}K")


# ---------------------------------------------------------------------------- the clock


def trapezoid_time_s(distance: float, speed: float, acceleration: float) -> float:
    """Duration of a point-to-point motion over ``distance`` with a trapezoidal velocity
    profile (the UR controller's: accelerate, cruise, decelerate; a triangle when the
    move is too short to reach ``speed``)."""
    if distance <= 0:
        return 0.0
    if distance < speed**2 / acceleration:
        return 2.0 * float(np.sqrt(distance / acceleration))
    return distance / speed + speed / acceleration
