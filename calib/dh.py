"""Denavit–Hartenberg kinematics of a six-joint arm (standard DH).

One table drives everything that needs the arm's geometry: the controller's nominal
forward kinematics, the twin's true arm (nominal + per-joint deltas), the MuJoCo model
built from it, and the touch-based DH refinement of the paper ("Reference Target
Localization and Kinematics Refinement").

Link transform of joint i (standard DH)::

    A_i(q_i) = Rz(theta_i + q_i) · Tz(d_i) · Tx(a_i) · Rx(alpha_i)

and ``T_base_ee(q) = A_1 ... A_6``; ``ee`` is the tool flange (UR "tool0").
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "NOMINAL_TABLES",
    "DHDeltas",
    "DHTable",
    "forward_kinematics",
    "frame_transforms",
    "link_transform",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DHTable:
    """Standard DH parameters of a six-joint arm.

    Attributes
    ----------
    theta : (6,) float, radians
        Joint-angle offsets (zero for the published UR tables).
    d : (6,) float, metres
    a : (6,) float, metres
    alpha : (6,) float, radians
    name : str
    """

    theta: tuple[float, ...]
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    name: str = "custom"

    def as_array(self) -> Array:
        """(6, 4) array with columns (theta, d, a, alpha)."""
        return np.column_stack([self.theta, self.d, self.a, self.alpha]).astype(float)

    @classmethod
    def from_array(cls, table: ArrayLike, *, name: str = "custom") -> DHTable:
        """Inverse of :meth:`as_array`."""
        table = np.asarray(table, dtype=float)
        if table.shape != (6, 4):
            raise ValueError(f"DH table must have shape (6, 4), got {table.shape}")
        return cls(*(tuple(map(float, table[:, k])) for k in range(4)), name=name)

    def with_deltas(self, deltas: DHDeltas) -> DHTable:
        """This table plus per-joint corrections (the twin's true arm, or a refined one)."""
        return DHTable.from_array(self.as_array() + deltas.as_array(), name=f"{self.name}+Δ")


@dataclass(frozen=True)
class DHDeltas:
    """Per-joint DH corrections (Δθ, Δd, Δa, Δα), each (6,), in radians and metres."""

    theta: tuple[float, ...] = (0.0,) * 6
    d: tuple[float, ...] = (0.0,) * 6
    a: tuple[float, ...] = (0.0,) * 6
    alpha: tuple[float, ...] = (0.0,) * 6

    def as_array(self) -> Array:
        """(6, 4) array with columns (Δθ, Δd, Δa, Δα)."""
        return np.column_stack([self.theta, self.d, self.a, self.alpha]).astype(float)

    @classmethod
    def from_array(cls, deltas: ArrayLike) -> DHDeltas:
        deltas = np.asarray(deltas, dtype=float)
        if deltas.shape != (6, 4):
            raise ValueError(f"DH deltas must have shape (6, 4), got {deltas.shape}")
        return cls(*(tuple(map(float, deltas[:, k])) for k in range(4)))

    def rms(self) -> tuple[float, float, float, float]:
        """RMS over joints of (Δθ rad, Δd m, Δa m, Δα rad), as the paper reports them."""
        return tuple(float(v) for v in np.sqrt(np.mean(self.as_array() ** 2, axis=0)))


_HALF_PI = np.pi / 2

#: Published nominal tables (Universal Robots' DH parameters), metres and radians.
NOMINAL_TABLES: dict[str, DHTable] = {
    "ur3": DHTable(
        theta=(0.0,) * 6,
        d=(0.1519, 0.0, 0.0, 0.11235, 0.08535, 0.0819),
        a=(0.0, -0.24365, -0.21325, 0.0, 0.0, 0.0),
        alpha=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
        name="ur3",
    ),
    "ur3e": DHTable(
        theta=(0.0,) * 6,
        d=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
        a=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
        alpha=(_HALF_PI, 0.0, 0.0, _HALF_PI, -_HALF_PI, 0.0),
        name="ur3e",
    ),
}


def link_transform(theta: ArrayLike, d: ArrayLike, a: ArrayLike, alpha: ArrayLike) -> Array:
    """Standard DH link transforms ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``, broadcast; (..., 4, 4).

    ``theta`` here already includes the joint angle.
    """
    theta, d, a, alpha = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (theta, d, a, alpha))
    )
    return _links(theta, d, a, np.cos(alpha), np.sin(alpha))


def _links(theta: Array, d: Array, a: Array, ca: Array, sa: Array) -> Array:
    """:func:`link_transform` from the joint angles and the table's d, a, cos α and sin α
    (broadcast against ``theta``)."""
    ct, st = np.cos(theta), np.sin(theta)
    A = np.zeros((*np.shape(theta), 4, 4))
    A[..., 0, 0], A[..., 0, 1], A[..., 0, 2], A[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    A[..., 1, 0], A[..., 1, 1], A[..., 1, 2], A[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    A[..., 2, 1], A[..., 2, 2], A[..., 2, 3] = sa, ca, d
    A[..., 3, 3] = 1.0
    return A


@functools.lru_cache(maxsize=64)
def _link_constants(table: DHTable) -> tuple[Array, Array, Array, Array, Array]:
    """A table's joint offsets, d, a, cos α and sin α (read-only (6,) arrays)."""
    p = table.as_array()
    out = (p[:, 0], p[:, 1], p[:, 2], np.cos(p[:, 3]), np.sin(p[:, 3]))
    for v in out:
        v.flags.writeable = False
    return out


def frame_transforms(table: DHTable, q: ArrayLike) -> Array:
    """Poses of all DH frames in the base frame.

    Parameters
    ----------
    table : DHTable
    q : (..., 6) float, radians
        Joint angles.

    Returns
    -------
    (..., 7, 4, 4) float
        ``[T_base_0 (identity), T_base_1, ..., T_base_6 = T_base_ee]``.
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != 6:
        raise ValueError(f"joint vector must end in 6 angles, got shape {q.shape}")
    # link_transform's products with the table's constants, computed once per table:
    # the twin and the calibration evaluate the same few tables at many joint vectors.
    offset, d, a, ca, sa = _link_constants(table)
    A = _links(q + offset, d, a, ca, sa)  # (..., 6, 4, 4)
    out = np.empty((*q.shape[:-1], 7, 4, 4))
    out[..., 0, :, :] = np.eye(4)
    for i in range(6):
        out[..., i + 1, :, :] = out[..., i, :, :] @ A[..., i, :, :]
    return out


def forward_kinematics(table: DHTable, q: ArrayLike) -> Array:
    """Flange pose ``T_base_ee`` (..., 4, 4) for joint angles ``q`` (..., 6), radians."""
    return frame_transforms(table, q)[..., 6, :, :]
