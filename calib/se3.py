"""Rigid transforms in SE(3), the one vocabulary every stage shares.

Conventions (DESIGN.md §3): a transform is a ``float64`` array of shape (4, 4) named
``T_<dst>_<src>``; it maps src coordinates into dst, so inner names cancel when composing
(``T_base_us = T_base_ee @ T_ee_us``). Batches are (n, 4, 4). A point is ``p_<frame>`` (3,),
a set ``P_<frame>`` (n, 3). Angles are radians; a value in degrees says so in its name.

Rotation conversions delegate to :class:`scipy.spatial.transform.Rotation`; the SE(3)
exponential and logarithm are written out because scipy has no SE(3) and the closed forms
are a few lines (the left Jacobian ``V`` of SO(3)).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from .errors import TransformError

__all__ = [
    "apply",
    "check",
    "euler_from_matrix",
    "exp",
    "hat",
    "identity",
    "invert",
    "kabsch",
    "log",
    "make",
    "matrix_from_euler",
    "matrix_from_pose6",
    "matrix_from_rotvec",
    "nearest_rotation",
    "pose6_from_matrix",
    "rotation_angle",
    "rotvec_from_matrix",
    "translation_distance",
]

Array = NDArray[np.float64]

# Below this rotation angle (rad) the series expansions of exp/log are used: the closed
# forms divide by theta**2 and lose precision there.
_SMALL_ANGLE = 1e-6


def check(T: ArrayLike, name: str, *, batch: bool = False, tol: float = 1e-5) -> Array:
    """``T`` as a float64 array if it is a rigid transform, (4, 4), or with ``batch`` a
    stack of them, (n, 4, 4); else :class:`~calib.errors.TransformError` naming ``name``
    and what is wrong. For the method's entry points and the file and hardware boundaries:
    a wrong matrix is refused where it enters, not found by the error it causes later.

    ``tol`` bounds the last row's and ``RᵀR``'s deviation from exact (files hold a few
    decimals); the rotation must be proper (det +1, not a reflection).

    Examples
    --------
    >>> check(np.eye(4), "T_ee_us").shape
    (4, 4)
    >>> check(np.diag([1.0, 1.0, -1.0, 1.0]), "T_ee_us")
    Traceback (most recent call last):
    ...
    calib.errors.TransformError: T_ee_us: not a rigid transform: a reflection (det −1)
    """
    try:
        A = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise TransformError(f"{name}: not a matrix of numbers") from None
    want = "(n, 4, 4)" if batch else "(4, 4)"
    if A.shape[-2:] != (4, 4) or A.ndim != (3 if batch else 2):
        raise TransformError(f"{name}: shape {A.shape}, a rigid transform is {want}")
    if not np.all(np.isfinite(A)):
        raise TransformError(f"{name}: not a rigid transform: it holds NaN or infinite entries")
    if np.abs(A[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0) > tol:
        raise TransformError(f"{name}: not a rigid transform: its last row is not (0, 0, 0, 1)")
    R = A[..., :3, :3]
    gram = np.swapaxes(R, -1, -2) @ R
    if np.abs(gram - np.eye(3)).max(initial=0.0) > tol:
        raise TransformError(
            f"{name}: not a rigid transform: its 3 × 3 block is not a rotation "
            "(scaled or sheared; RᵀR ≠ I)"
        )
    if np.any(np.linalg.det(R) < 0):
        raise TransformError(f"{name}: not a rigid transform: a reflection (det −1)")
    return A


def identity(n: int | None = None) -> Array:
    """Identity transform (4, 4), or a batch of ``n`` of them (n, 4, 4)."""
    eye = np.eye(4)
    return eye if n is None else np.broadcast_to(eye, (n, 4, 4)).copy()


def make(R: ArrayLike, t: ArrayLike) -> Array:
    """Build transforms from rotations and translations.

    Parameters
    ----------
    R : (..., 3, 3) float
        Rotation matrices.
    t : (..., 3) float, metres
        Translations (the origin of the source frame in the destination frame).

    Returns
    -------
    T : (..., 4, 4) float

    Examples
    --------
    The us frame 3 cm in front of the flange, turned 90° about the flange's z axis:

    >>> T_ee_us = make(matrix_from_rotvec([0.0, 0.0, np.pi / 2]), [0.0, 0.0, 0.03])
    >>> T_ee_us.round(3)
    array([[ 0.  , -1.  ,  0.  ,  0.  ],
           [ 1.  ,  0.  ,  0.  ,  0.  ],
           [ 0.  ,  0.  ,  1.  ,  0.03],
           [ 0.  ,  0.  ,  0.  ,  1.  ]])
    """
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros((*shape, 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def invert(T: ArrayLike) -> Array:
    """Inverse of rigid transforms, ``T_src_dst`` from ``T_dst_src``; (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def apply(T: ArrayLike, P: ArrayLike) -> Array:
    """Map points with transforms: ``P_dst = apply(T_dst_src, P_src)``.

    Parameters
    ----------
    T : (..., 4, 4) float
    P : (..., 3) float, metres
        Broadcast against ``T``'s batch shape: one transform and many points, many
        transforms and one point each, or both batched alike.

    Returns
    -------
    (..., 3) float, metres

    Examples
    --------
    A point 2 cm deep in the image, in the flange frame and back (inner names cancel):

    >>> T_ee_us = make(np.eye(3), [0.0, 0.0, 0.03])
    >>> p_ee = apply(T_ee_us, [0.0, 0.02, 0.0])
    >>> p_ee
    array([0.  , 0.02, 0.03])
    >>> apply(invert(T_ee_us), p_ee)
    array([0.  , 0.02, 0.  ])
    """
    T = np.asarray(T, dtype=float)
    P = np.asarray(P, dtype=float)
    if T.ndim == 2:
        return P @ T[:3, :3].T + T[:3, 3]
    return np.einsum("...ij,...j->...i", T[..., :3, :3], P) + T[..., :3, 3]


def matrix_from_rotvec(rotvec: ArrayLike) -> Array:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3), radians."""
    rotvec = np.asarray(rotvec, dtype=float)
    return Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(*rotvec.shape, 3)


def rotvec_from_matrix(R: ArrayLike) -> Array:
    """Rotation vectors (..., 3), radians, angle in [0, π], from rotation matrices."""
    R = np.asarray(R, dtype=float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*R.shape[:-2], 3)


def matrix_from_euler(angles_rad: ArrayLike, *, seq: str = "xyz") -> Array:
    """Rotation matrices from Euler angles in radians.

    ``seq`` follows scipy: lower case is extrinsic (about the fixed axes), upper case
    intrinsic. The scenario files use extrinsic ``xyz``.
    """
    angles_rad = np.asarray(angles_rad, dtype=float)
    R = Rotation.from_euler(seq, angles_rad.reshape(-1, 3)).as_matrix()
    return R.reshape(*angles_rad.shape, 3)


def euler_from_matrix(R: ArrayLike, *, seq: str = "xyz") -> Array:
    """Euler angles (..., 3) in radians from rotation matrices; inverse of
    :func:`matrix_from_euler` away from gimbal lock."""
    R = np.asarray(R, dtype=float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler(seq).reshape(*R.shape[:-2], 3)


def matrix_from_pose6(pose: ArrayLike) -> Array:
    """Transform from a 6-vector ``[x, y, z, rx, ry, rz]`` (metres, rotation vector):
    the pose format of UR controllers (``actual_TCP_pose``)."""
    pose = np.asarray(pose, dtype=float)
    return make(matrix_from_rotvec(pose[..., 3:]), pose[..., :3])


def pose6_from_matrix(T: ArrayLike) -> Array:
    """Inverse of :func:`matrix_from_pose6`; (..., 6)."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], rotvec_from_matrix(T[..., :3, :3])], axis=-1)


def hat(w: ArrayLike) -> Array:
    """Skew-symmetric matrices (..., 3, 3) with ``hat(w) @ v == cross(w, v)``."""
    w = np.asarray(w, dtype=float)
    W = np.zeros((*w.shape[:-1], 3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def _left_jacobian_coeffs(theta: Array) -> tuple[Array, Array]:
    """Coefficients b, c of the SO(3) left Jacobian ``V = I + b·W + c·W²`` (W = hat(ω))."""
    small = theta < _SMALL_ANGLE
    th = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    c = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (th - np.sin(th)) / th**3)
    return b, c


def exp(xi: ArrayLike) -> Array:
    """Exponential map se(3) → SE(3).

    Parameters
    ----------
    xi : (..., 6) float
        Twist ``[ρ, ω]``: ``ρ`` (metres) and rotation vector ``ω`` (radians).
        ``T = exp(xi)`` has rotation ``exp(hat ω)`` and translation ``V(ω) ρ``.

    Returns
    -------
    (..., 4, 4) float

    Examples
    --------
    A small perturbation of a calibration (0.1 mm along x, 0.5° about z) and its size;
    :func:`log` inverts it:

    >>> xi = np.array([1e-4, 0.0, 0.0, 0.0, 0.0, np.radians(0.5)])
    >>> T = exp(xi)
    >>> round(float(np.degrees(rotation_angle(identity(), T))), 6)
    0.5
    >>> bool(np.allclose(log(T), xi))
    True
    """
    xi = np.asarray(xi, dtype=float)
    rho, omega = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(omega, axis=-1)
    W = hat(omega)
    b, c = _left_jacobian_coeffs(theta)
    V = np.eye(3) + b[..., None, None] * W + c[..., None, None] * (W @ W)
    return make(matrix_from_rotvec(omega), np.einsum("...ij,...j->...i", V, rho))


def log(T: ArrayLike) -> Array:
    """Logarithm SE(3) → se(3), the inverse of :func:`exp` for rotation angles below π.

    Returns
    -------
    xi : (..., 6) float
        ``[ρ, ω]`` as in :func:`exp`.
    """
    T = np.asarray(T, dtype=float)
    omega = rotvec_from_matrix(T[..., :3, :3])
    theta = np.linalg.norm(omega, axis=-1)
    W = hat(omega)
    small = theta < _SMALL_ANGLE
    th = np.where(small, 1.0, theta)
    # V^-1 = I - W/2 + d W², d = (1 - θ sinθ / (2 (1 - cosθ))) / θ²
    d = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / th**2,
    )
    V_inv = np.eye(3) - 0.5 * W + d[..., None, None] * (W @ W)
    rho = np.einsum("...ij,...j->...i", V_inv, T[..., :3, 3])
    return np.concatenate([rho, omega], axis=-1)


def rotation_angle(T_a: ArrayLike, T_b: ArrayLike) -> Array | float:
    """Angle (radians, in [0, π]) of the relative rotation between two transforms."""
    T_a = np.asarray(T_a, dtype=float)
    T_b = np.asarray(T_b, dtype=float)
    R_rel = np.swapaxes(T_a[..., :3, :3], -1, -2) @ T_b[..., :3, :3]
    # atan2(sin θ, cos θ) from the relative rotation's antisymmetric part and trace:
    # accurate at every angle (arccos of the trace alone is not near 0 and π) and ≈ 30×
    # faster than through scipy's Rotation (the twin times every move with it).
    axis = np.stack(
        [
            R_rel[..., 2, 1] - R_rel[..., 1, 2],
            R_rel[..., 0, 2] - R_rel[..., 2, 0],
            R_rel[..., 1, 0] - R_rel[..., 0, 1],
        ],
        axis=-1,
    )
    trace = R_rel[..., 0, 0] + R_rel[..., 1, 1] + R_rel[..., 2, 2]
    angle = np.arctan2(0.5 * np.linalg.norm(axis, axis=-1), 0.5 * (trace - 1.0))
    return float(angle) if angle.ndim == 0 else angle


def translation_distance(T_a: ArrayLike, T_b: ArrayLike) -> Array | float:
    """Euclidean distance (metres) between the origins of two transforms."""
    T_a = np.asarray(T_a, dtype=float)
    T_b = np.asarray(T_b, dtype=float)
    dist = np.linalg.norm(T_a[..., :3, 3] - T_b[..., :3, 3], axis=-1)
    return float(dist) if dist.ndim == 0 else dist


def nearest_rotation(A: ArrayLike) -> Array:
    """The rotation nearest a 3 × 3 matrix in the Frobenius norm (its polar factor, by
    SVD, reflection excluded): what a linear estimate of a rotation stands for."""
    U, _, Vt = np.linalg.svd(np.asarray(A, dtype=float))
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def kabsch(P: ArrayLike, Q: ArrayLike) -> Array:
    """Rigid transform (4, 4) best mapping points P (n, 3) onto Q (n, 3) in least squares
    (Kabsch: SVD of the cross-covariance, reflection excluded)."""
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    p0, q0 = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - p0).T @ (Q - q0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make(R, q0 - R @ p0)
