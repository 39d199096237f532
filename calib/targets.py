"""Calibration targets as one concept (paper §III-B, "Geometric Analysis of Calibration
Targets"; issue "N-wire and wire targets", item 1).

Whatever the phantom, an observation is one image point ``u`` (pixels) seen with the
probe at ``T_base_ee``; mapped through ``T_ee_us`` and the phantom's pose it lands at
``x = inv(T_base_phantom) T_base_ee T_ee_us s(u)`` in the phantom frame, and what the
target is says which of its components must vanish:

================  =========================================================  ===========
kind              the observation's point lies ...                           constraints
================  =========================================================  ===========
``sphere``        at the sphere's centre (its CAD position)                  3
``cone_tip``      at the cone's apex                                         3
``nwire``         at the point where the image plane cuts the pattern's      3
                  diagonal, read from its three dots' ratio (each frame its
                  own point)
``wire``          on the wire's line: only its two components across the     2
                  wire are known
================  =========================================================  ===========

A target here is the set of rows of its constraint: :func:`constraint_rows` (m, 3), the
directions in the phantom frame along which an observation's residual is measured
(every direction for a point, the two across a wire). The residual of observation ``i``
is ``B_i (x_i − p_i)``, with ``p_i`` the target's point the observation is tied to (a
point target's position, a wire's front end, the N-wire diagonal's point). The
information a plan gives about ``T_ee_us`` follows from the same rows
(:func:`calib.acquisition.observability.information` with a wire's direction), and
:func:`calib.calibration.targets.calibrate_targets` fits any mix of them at once.

Detection is per kind: the threshold-free sphere localizer (:mod:`calib.localize`), the
wire and N-wire dots (:mod:`calib.localize.nwire`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .files.plus_config import NWirePattern

__all__ = [
    "KINDS",
    "NWireTarget",
    "PointTarget",
    "Target",
    "TargetObservations",
    "WireTarget",
    "constraint_rows",
    "observation_rows",
    "row_mask",
]

Array = NDArray[np.float64]

#: Every kind of target and the number of constraints one observation gives.
KINDS: dict[str, int] = {"sphere": 3, "cone_tip": 3, "nwire": 3, "wire": 2}


@dataclass(frozen=True)
class PointTarget:
    """A point of the phantom the image can be put on: a sphere's centre (the
    localizer's centre) or a cone's tip. ``position`` phantom frame, metres."""

    name: str
    position: Array
    kind: Literal["sphere", "cone_tip"] = "cone_tip"


@dataclass(frozen=True)
class WireTarget:
    """A straight wire between ``front`` and ``back`` (phantom frame, metres): the image
    plane cuts it at one point, known only across the wire."""

    name: str
    front: Array
    back: Array
    kind: Literal["wire"] = "wire"

    @property
    def direction(self) -> Array:
        d = np.asarray(self.back, dtype=float) - np.asarray(self.front, dtype=float)
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class NWireTarget:
    """One N pattern of three wires: a frame's three dots give the point where the image
    plane cuts the diagonal (:func:`calib.localize.nwire.middle_wire_point`)."""

    name: str
    pattern: NWirePattern
    kind: Literal["nwire"] = "nwire"


Target = PointTarget | WireTarget | NWireTarget


def constraint_rows(target: Target) -> Array:
    """The target's constraint as rows (m, 3) in the phantom frame: the directions along
    which an observation's point must meet the target's (orthonormal)."""
    if isinstance(target, WireTarget):
        d = target.direction
        helper = np.eye(3)[int(np.argmin(np.abs(d)))]
        n1 = np.cross(d, helper)
        n1 /= np.linalg.norm(n1)
        return np.vstack([n1, np.cross(d, n1)])
    return np.eye(3)


@dataclass(frozen=True)
class TargetObservations:
    """Image points of any mix of targets.

    ``frame`` (n,) index into the frames (and their poses); ``target`` (n,) index into the
    targets; ``pixel`` (n, 2) the point in the image (column, row); ``phantom_point``
    (n, 3) the target's point it is tied to (phantom frame, metres); ``skew`` (n,) how far
    the point's centre lies below its echo's peak (rows; 0 when not measured);
    ``refused`` why frames gave no observation (reason → count)."""

    frame: NDArray[np.int_]
    target: NDArray[np.int_]
    pixel: Array
    phantom_point: Array
    skew: Array
    refused: Counter[str]

    @property
    def frames_used(self) -> int:
        return len(np.unique(self.frame))

    def __len__(self) -> int:
        return len(self.frame)

    def subset(self, keep: NDArray[np.bool_]) -> TargetObservations:
        """The observations where ``keep`` holds (frame indices unchanged)."""
        return TargetObservations(
            self.frame[keep],
            self.target[keep],
            self.pixel[keep],
            self.phantom_point[keep],
            self.skew[keep],
            self.refused,
        )

    @staticmethod
    def of(
        frame: ArrayLike,
        target: ArrayLike,
        pixel: ArrayLike,
        phantom_point: ArrayLike,
        skew: ArrayLike | None = None,
        refused: Counter[str] | None = None,
    ) -> TargetObservations:
        f = np.asarray(frame, dtype=int).ravel()
        return TargetObservations(
            f,
            np.asarray(target, dtype=int).ravel(),
            np.asarray(pixel, dtype=float).reshape(-1, 2),
            np.asarray(phantom_point, dtype=float).reshape(-1, 3),
            np.zeros(len(f)) if skew is None else np.asarray(skew, dtype=float).ravel(),
            refused or Counter(),
        )


def observation_rows(obs: TargetObservations, targets: Sequence[Target]) -> Array:
    """Each observation's constraint rows (n, 3, 3), phantom frame; a wire's third row is
    zero (:func:`row_mask` says which rows count)."""
    rows = np.zeros((len(targets), 3, 3))
    for j, t in enumerate(targets):
        B = constraint_rows(t)
        rows[j, : len(B)] = B
    return rows[obs.target]


def row_mask(obs: TargetObservations, targets: Sequence[Target]) -> NDArray[np.bool_]:
    """(n, 3): which of each observation's three residual rows are constraints."""
    m = np.array([KINDS[t.kind] for t in targets], dtype=int)[obs.target]
    return np.arange(3)[None, :] < m[:, None]
