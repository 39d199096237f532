"""How well a pose plan constrains ``T_ee_us`` (paper, "Geometric Analysis of Calibration
Targets").

Observation k reconstructs the target at ``x_k(θ) = R_k (R_X p_k + t_X) + t_k`` (paper
Eq. 1). With θ = (ω, t): a rotation vector applied to ``R_X`` in the flange frame (rad)
and a translation of ``t_X`` (mm), the 3 × 6 Jacobian is

    G_k = ∂x_k/∂θ = [ −R_k [R_X p_k]_×  |  R_k ]        (x in mm, so ω is scaled by 1000)

A displacement shared by all observations is absorbed by the unknown target position, so
the mean Jacobian is removed: G̃_k = G_k − mean(G). The information matrices of a point
(sphere) and of a line (wire of direction û) constraint are (paper Eq. target
information)

    H̃_point = Σ G̃_kᵀ G̃_k,        H̃_line = Σ G̃_kᵀ P⊥ G̃_k,   P⊥ = I − ûûᵀ.

Since H̃_point − H̃_line = Σ G̃_kᵀ ûûᵀ G̃_k ⪰ 0, a wire never carries more information than
a sphere over the same poses. For isotropic localization noise σ (mm) the least-squares
estimate has covariance σ² H̃⁻¹ (to first order).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import se3
from ..targets import Target, constraint_rows

__all__ = [
    "Observability",
    "information",
    "information_of_target",
    "jacobians",
    "observability",
    "planned_observations",
]

Array = NDArray[np.float64]
_MM = 1e3


def jacobians(T_base_ee: ArrayLike, T_ee_us: ArrayLike, p_us: ArrayLike) -> Array:
    """G_k (n, 3, 6) of reconstructed target points with respect to θ = (ω rad, t mm),
    points in mm (see the module docstring)."""
    T = np.asarray(T_base_ee, dtype=float)
    X = np.asarray(T_ee_us, dtype=float)
    P = np.asarray(p_us, dtype=float)
    q = np.einsum("ij,nj->ni", X[:3, :3], P)  # R_X p_k, metres
    R = T[:, :3, :3]
    skew = np.zeros((len(q), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -q[:, 2], q[:, 1], -q[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = q[:, 2], -q[:, 1], q[:, 0]
    G = np.empty((len(q), 3, 6))
    G[:, :, :3] = -(R @ skew) * _MM
    G[:, :, 3:] = R
    return G


def information(G: Array, *, line_direction: ArrayLike | None = None) -> Array:
    """H̃ (6, 6) of Jacobians ``G`` (n, 3, 6): point constraint, or line constraint along
    ``line_direction`` (base frame)."""
    Gt = G - G.mean(axis=0)
    if line_direction is None:
        return np.einsum("nij,nik->jk", Gt, Gt)
    u = np.asarray(line_direction, dtype=float)
    u = u / np.linalg.norm(u)
    P = np.eye(3) - np.outer(u, u)
    return np.einsum("nij,il,nlk->jk", Gt, P, Gt)


def information_of_target(G: Array, target: Target, R_base_phantom: ArrayLike) -> Array:
    """H̃ (6, 6) of Jacobians ``G`` (n, 3, 6) of observations of any kind of target
    (:mod:`calib.targets`): its constraint rows, turned into the base frame, project
    each observation's displacement (a point: all of it; a wire: across it).
    :func:`information` is the point's and the line's case."""
    B = constraint_rows(target) @ np.asarray(R_base_phantom, dtype=float).T  # base frame
    Gt = G - G.mean(axis=0)
    return np.einsum("nij,ki,kl,nlm->jm", Gt, B, B, Gt)


@dataclass(frozen=True)
class Observability:
    """Conditioning of one information matrix.

    Attributes
    ----------
    eigenvalues : (6,) float, descending (mm² per unit of θ²)
    condition_number : float
        λ_max / λ_min (inf when singular).
    min_singular_value : float
        √λ_min: the weakest direction's gain (mm per unit of θ).
    noise_amplification : float
        λ_min / √λ_max (the noise amplification index O5 of Nahvi & Hollerbach; larger is
        better).
    covariance : (6, 6) float
        Predicted covariance of θ = (ω rad, t mm) for the localization noise given.
    std_rotation_deg, std_translation_mm : (3,) float
        Predicted 1 σ of the rotation (about the flange axes) and translation.
    weakest : (6,) float
        Unit direction of θ with the least information.
    """

    eigenvalues: Array
    condition_number: float
    min_singular_value: float
    noise_amplification: float
    covariance: Array
    std_rotation_deg: Array
    std_translation_mm: Array
    weakest: Array


def observability(H: Array, *, noise_mm: float = 0.1) -> Observability:
    """Conditioning figures of an information matrix ``H`` and the covariance predicted
    for isotropic localization noise ``noise_mm`` (1 σ per axis)."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    order = np.argsort(w)[::-1]
    w, V = w[order], V[:, order]
    lam_min = max(float(w[-1]), 0.0)
    cov = noise_mm**2 * np.linalg.pinv(H, rcond=1e-12, hermitian=True)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return Observability(
        eigenvalues=w,
        condition_number=float(w[0] / lam_min) if lam_min > 0 else float("inf"),
        min_singular_value=float(np.sqrt(lam_min)),
        noise_amplification=float(lam_min / np.sqrt(w[0])) if w[0] > 0 else 0.0,
        covariance=cov,
        std_rotation_deg=np.degrees(std[:3]),
        std_translation_mm=std[3:],
        weakest=V[:, -1],
    )


def planned_observations(
    T_base_ee: Sequence[ArrayLike], T_ee_us: ArrayLike, target_base: ArrayLike
) -> Array:
    """Where a target at ``target_base`` appears (``p_us``, (n, 3) metres) at planned flange
    poses, if ``T_ee_us`` were exact (the predicted observations of a plan)."""
    T = np.asarray(T_base_ee, dtype=float) @ np.asarray(T_ee_us, dtype=float)
    return se3.apply(se3.invert(T), np.asarray(target_base, dtype=float))
