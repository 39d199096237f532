"""``T_ee_us`` from any mix of targets in one fit (issue "N-wire and wire targets", item 1):
N-wire patterns, single wires, cone tips and spheres' centres at their CAD positions,
each observation contributing the residual its kind defines (:mod:`calib.targets`).

Over every observation ``i`` of frame ``k`` the fit asks

    B_i · (T_base_phantom⁻¹ · T_base_ee[k] · T_ee_us · s(u_i) − p_i) = 0

for ``T_ee_us``, optionally the pixel scale ``s`` (a spacing the scanner reports wrong,
or a speed of sound off, is that unknown) and, on a robot, the phantom's pose (as the
three-marker fit estimates its layout's). What the targets cannot tell (a lone wire's
pose along and about itself) is left where it started: the phantom's pose is moved
only along the directions the residuals see.

1. **Start.** Points only (N-wire, cone tips, spheres): a closed form linear in the
   affine image-to-probe map (and in the phantom's pose when it is unknown), no guess
   needed. With wires: from a given start (the coarse mount and the phantom's taught
   pose).
2. **Refinement.** Robust least squares of the residuals (soft-L1, then Cauchy at three
   times their own median-absolute-deviation scale, re-measured until it holds): no
   threshold.
3. **Bounds.** A delete-group jackknife over blocks of consecutive frames, each twice as
   long as the residuals stay correlated, against the first-order covariance, the larger
   in every direction, Student-t widened; declared errors every frame shares (a
   phantom's build tolerance, the echoes' depth bias) propagated through the fit to
   first order; the 95 % bounds of rotation, translation and the mean error over the
   image.
4. **Information.** The information the data hold about the mount, the phantom's pose
   and the scale profiled out: its eigenvalues (as
   :mod:`calib.acquisition.observability` states a plan's).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

# scipy.special's distribution functions, which scipy.stats wraps (chi2.isf is chdtri):
# importing scipy.stats costs every process ≈ 0.5 s.
from scipy.special import chdtri, ndtri, stdtrit

from .. import se3
from ..errors import CalibrationError
from ..files.plus_config import image_to_probe_mm
from ..image import pixel_axes
from ..targets import Target, TargetObservations, WireTarget, observation_rows, row_mask
from .uncertainty import _dominating, image_grid
from .verdict import (
    DEFAULT_IMAGE_MM,
    MAX_DROPPED_SHARE,
    UNDETERMINED_DEG,
    UNDETERMINED_MM,
    Requirements,
    Status,
)

__all__ = [
    "MIN_FRAMES",
    "OUTLIER_FLOOR_MM",
    "TargetCalibration",
    "TargetModel",
    "TargetVerdict",
    "calibrate_targets",
    "closed_form",
    "correlation_frames",
    "fit_phantom_pose",
    "judge_targets",
    "nominal_xy",
    "wire_starts",
]

Array = NDArray[np.float64]
_MM = 1e3
#: Fewer frames with an observation than this cannot be split into jackknife blocks and
#: leave a fit: refuse (PLUS's own tests calibrate from well over a hundred).
MIN_FRAMES = 10
#: Jackknife blocks of consecutive frames: each at least twice the residuals' correlation
#: length (:func:`correlation_frames`), so that blocks, not frames, are independent; at
#: most ten (the sphere method's nine views), at least four (fewer leave the t quantile,
#: and the bound, unusable: it is then wide, and the verdict says so).
MAX_BLOCKS = 10
MIN_BLOCKS = 4
#: A point is an outlier when its squared error exceeds the χ² 0.1 % quantile of the
#: fit's own per-axis scale (as many degrees of freedom as its target's constraints): a
#: detection or tracking glitch, not noise.
_OUTLIER_P = 1e-3
#: The Cauchy loss's scale in the data's own σ: points within a few σ count fully (the
#: noise), those far beyond fade (glitches).
_GLITCH_SIGMAS = 3.0
#: ... and beyond this many millimetres: a wire point off by less is no glitch, whatever
#: the scatter (the sphere method's centres: 2 mm; a wire point is read more finely).
OUTLIER_FLOOR_MM = 1.0
#: A direction of the phantom's pose the residuals see less than this (relative to the
#: best seen one) is not estimated: a lone wire's pose along and about itself.
_GAUGE_RTOL = 1e-9


@dataclass(frozen=True)
class TargetCalibration:
    """The result of :func:`calibrate_targets`.

    ``T_ee_us`` (4, 4) metres; ``spacing_m`` the pixel spacing (columns, rows) the fit
    holds with (estimated when ``scale_estimated``); ``T_base_phantom`` (given, or
    estimated when ``phantom_estimated``); ``errors_mm`` each observation's error (the
    norm of its residual: 3-D for points, across the wire for wires); ``covariance``
    (8, 8) of (rotation vector of ``T_ee_us`` in the ee frame, rad; its translation, m;
    the two scale factors) — zero rows for what was not estimated; ``bound95`` rotation
    (deg), translation (mm) and mean error over the image (mm); ``converged`` and the
    solver's ``message``; ``blocks`` the jackknife's groups; ``outliers`` the points
    beyond the χ² quantile of the fit's own scale and a millimetre; ``scale`` the fitted
    spacing over the nominal one (1, 1 when held); ``sigma_mm`` the residuals' robust
    scale per axis; ``information_eigenvalues`` (6,) of the information about the mount
    (rotation rad, translation mm), the phantom's pose and the scale profiled out,
    descending; ``phantom_dof`` how many directions of the phantom's pose the data
    determined (6 unless a lone wire's symmetry leaves some); ``points_base`` each
    observation's image point through the answer and its pose (base frame, metres)."""

    T_ee_us: Array
    spacing_m: tuple[float, float]
    T_base_phantom: Array
    errors_mm: Array
    covariance: Array
    bound95: dict[str, float]
    converged: bool
    message: str
    blocks: int
    outliers: int
    width_px: int
    height_px: int
    scale_estimated: bool
    phantom_estimated: bool
    scale: tuple[float, float]
    sigma_mm: float
    information_eigenvalues: Array
    seconds: float = 0.0
    phantom_dof: int = 6
    points_base: Array | None = None  # (n, 3) the observations through the answer, m

    def image_to_probe_mm(self) -> Array:
        """PLUS's ``ImageToProbe``: pixel (column, row, 0, 1) → probe (ee) millimetres,
        the fitted pixel spacing included."""
        return image_to_probe_mm(self.T_ee_us, self.width_px, self.spacing_m)


def nominal_xy(pixel: Array, width_px: int, spacing_m: tuple[float, float]) -> Array:
    """Pixels (n, 2: column, row) as image-frame coordinates (n, 2, metres) at the
    nominal spacing."""
    x, y = pixel_axes(pixel[:, 1], pixel[:, 0], width_px, spacing_m)
    return np.column_stack([x, y])


def closed_form(
    xy: Array, T_k: Array, p: Array, T_base_phantom: Array | None
) -> tuple[Array, tuple[float, float], Array]:
    """Step 1 of the module doc for point observations: (T_ee_us, scale factors,
    T_base_phantom) from image points ``xy`` (n, 2, m) at poses ``T_k`` (n, 4, 4) tied to
    phantom points ``p`` (n, 3)."""
    n = len(xy)
    q = np.column_stack([xy, np.ones(n)])  # (n, 3): x, y, 1
    Rt = np.transpose(T_k[:, :3, :3], (0, 2, 1))  # R_kᵀ
    if T_base_phantom is not None:
        p_base = se3.apply(T_base_phantom, p)
        P_ee = np.einsum("nij,nj->ni", Rt, p_base - T_k[:, :3, 3])
        M = np.linalg.lstsq(q, P_ee, rcond=None)[0].T  # P_ee = M q
        T_P = T_base_phantom
    else:
        # R_kᵀ R_P p + R_kᵀ t_P − M q = R_kᵀ t_k, linear in (R_P, t_P, M): 21 unknowns.
        A = np.zeros((3 * n, 21))
        for a in range(3):
            rows = slice(a, 3 * n, 3)
            # coefficient of R_P[b, c] in row a: R_k[b, a] p_c
            A[rows, :9] = (T_k[:, :3, a][:, :, None] * p[:, None, :]).reshape(n, 9)
            A[rows, 9:12] = T_k[:, :3, a]
            A[rows, 12 + 3 * a : 15 + 3 * a] = -q
        b = np.einsum("nij,nj->ni", Rt, T_k[:, :3, 3]).ravel()
        sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
        if rank < 21:
            raise CalibrationError(
                "the frames' probe orientations are too alike to estimate the phantom's "
                "pose with the calibration: tilt and turn the probe between frames"
            )
        T_P = se3.make(se3.nearest_rotation(sol[:9].reshape(3, 3)), sol[9:12])
        M = sol[12:].reshape(3, 3)
    kx, ky = float(np.linalg.norm(M[:, 0])), float(np.linalg.norm(M[:, 1]))
    r1, r2 = M[:, 0] / kx, M[:, 1] / ky
    R = se3.nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    return se3.make(R, M[:, 2]), (kx, ky), T_P


class TargetModel:
    """The residuals (mm) as a function of the parameter vector: increments of
    ``T_ee_us`` (rotation vector about its initial rotation, translation), of the
    phantom's pose along ``phantom_basis`` when it is estimated, and the two scale
    factors when estimated. A point's residual is measured along the base frame's axes
    (any orthonormal rows measure a point alike), a wire's across the wire."""

    def __init__(
        self,
        xy: Array,
        T_k: Array,
        p: Array,
        rows: Array,
        mask: NDArray[np.bool_],
        T_X0: Array,
        T_P0: Array,
        estimate_phantom: bool,
        estimate_scale: bool,
        scale0,
        phantom_basis: Array | None = None,
    ):
        self.xy, self.T_k, self.p = xy, T_k, p
        self.rows, self.mask = rows, mask
        self.points_only = bool(mask.all())
        self.T_X0, self.T_P0 = T_X0, T_P0
        self.estimate_phantom, self.estimate_scale = estimate_phantom, estimate_scale
        self.scale0 = np.asarray(scale0, dtype=float)
        self.basis = np.eye(6) if phantom_basis is None else phantom_basis
        self.n_phantom = self.basis.shape[1] if estimate_phantom else 0
        self.n = 6 + self.n_phantom + 2 * estimate_scale

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        T_X = se3.make(se3.matrix_from_rotvec(x[:3]) @ self.T_X0[:3, :3], self.T_X0[:3, 3] + x[3:6])
        i = 6
        T_P = self.T_P0
        if self.estimate_phantom:
            d = self.basis @ x[i : i + self.n_phantom]
            T_P = se3.make(
                se3.matrix_from_rotvec(d[:3]) @ self.T_P0[:3, :3], self.T_P0[:3, 3] + d[3:]
            )
            i += self.n_phantom
        scale = self.scale0 * (x[i : i + 2] if self.estimate_scale else 1.0)
        return T_X, T_P, scale

    def x0(self) -> Array:
        x = np.zeros(self.n)
        if self.estimate_scale:
            x[-2:] = 1.0
        return x

    def points(self, x: Array, rows=slice(None)) -> tuple[Array, Array]:
        """The observations' image points and their targets' points, base frame (m)."""
        T_X, T_P, scale = self.unpack(x)
        xy = self.xy[rows] * scale
        P_us = np.column_stack([xy, np.zeros(len(xy))])
        T = self.T_k[rows] @ T_X
        image = np.einsum("nij,nj->ni", T[:, :3, :3], P_us) + T[:, :3, 3]
        return image, se3.apply(T_P, self.p[rows])

    def residual_vectors(self, x: Array, rows=slice(None)) -> Array:
        """(n, 3) mm: base-frame differences for points, the rows across a wire (phantom
        frame) for wires, zero where a wire has no third constraint."""
        image, target = self.points(x, rows)
        d = (image - target) * _MM
        if self.points_only:
            return d
        _, T_P, _ = self.unpack(x)
        B = self.rows[rows]
        mask = self.mask[rows]
        across = np.einsum("nij,jk,nk->ni", B, T_P[:3, :3].T, d)
        return np.where(mask.all(axis=1)[:, None], d, across * mask)

    def residuals(self, x: Array, rows=slice(None)) -> Array:
        r = self.residual_vectors(x, rows)
        return r.ravel() if self.points_only else r[self.mask[rows]]

    def shift_columns(self, x: Array, delta: Array) -> Array:
        """The residuals' change (mm) when each observation's target point moves by
        ``delta`` (n, 3, phantom frame, metres): a declared error's column."""
        _, T_P, _ = self.unpack(x)
        moved = -(delta @ T_P[:3, :3].T) * _MM  # base frame
        if self.points_only:
            return moved.ravel()
        across = np.einsum("nij,jk,nk->ni", self.rows, T_P[:3, :3].T, moved)
        full = np.where(self.mask.all(axis=1)[:, None], moved, across)
        return full[self.mask]


def _fit(model: TargetModel, x0: Array, f_scale: float, rows=slice(None), loss="soft_l1", **kw):
    return least_squares(
        lambda x: model.residuals(x, rows), x0, loss=loss, f_scale=f_scale, x_scale="jac", **kw
    )


def _robust_sigma(r: Array) -> float:
    """Per-axis scale of residuals (mm): 1.4826 × their median absolute value."""
    return max(1.4826 * float(np.median(np.abs(r))), 1e-6)


def correlation_frames(frame: NDArray[np.int_], target: NDArray[np.int_], r: Array) -> int:
    """How many consecutive frames share an error: the first lag (in frames used) at which
    the autocorrelation of the residual vectors (n, 3), per target, averaged, falls below
    1/e. Neighbouring frames of a freehand sweep share the tracker's and the phantom's
    pose-dependent errors; on PLUS's fCal recording this is about 20 frames."""
    used = np.unique(frame)
    n = len(used)
    order = {f: i for i, f in enumerate(used)}
    acf = np.zeros(max(n // 3, 1))
    for j in np.unique(target):
        rows = np.flatnonzero(target == j)
        series = np.full((n, 3), np.nan)
        series[[order[f] for f in frame[rows]]] = r[rows]
        series -= np.nanmean(series, axis=0)
        power = np.nanmean(np.sum(series * series, axis=1))
        for lag in range(1, len(acf)):
            products = np.sum(series[:-lag] * series[lag:], axis=1)
            acf[lag] += np.nanmean(products) / power if np.isfinite(products).any() else 0.0
    acf /= len(np.unique(target))
    below = np.flatnonzero(acf[1:] < np.exp(-1.0))
    return int(below[0] + 1) if len(below) else len(acf)


def _blocks(frame: NDArray[np.int_], length: int) -> NDArray[np.int_]:
    """The jackknife's group of each point: blocks of consecutive used frames, each at
    least ``length`` frames, between MIN_BLOCKS and MAX_BLOCKS of them."""
    used = np.unique(frame)
    g = int(np.clip(len(used) // max(length, 1), MIN_BLOCKS, MAX_BLOCKS))
    g = min(g, len(used))
    block_of = dict(zip(used, np.arange(len(used)) * g // len(used), strict=True))
    return np.array([block_of[f] for f in frame])


def _jacobian(f, x: Array, h: float = 1e-7) -> Array:
    r0 = f(x)
    J = np.empty((len(r0), len(x)))
    for j in range(len(x)):
        dx = np.zeros(len(x))
        dx[j] = h
        J[:, j] = (f(x + dx) - r0) / h
    return J


def _phantom_basis(model: TargetModel) -> Array | None:
    """The directions of the phantom's pose the targets' constraints see (6, k), or None
    when they see all six: how a small move of the phantom (rotation vector about the
    base origin, translation; metres) moves each constraint where its observation meets
    it — a point's position, the foot of the observation on a wire — along the
    constraint's rows. A lone wire's rotation about itself and slide along itself move
    no constraint: exactly null, whatever the residuals at the start."""
    _, T_P, _ = model.unpack(model.x0())
    R, t = T_P[:3, :3], T_P[:3, 3]
    image, _ = model.points(model.x0())
    local = (image - t) @ R  # the observations in the phantom frame
    q = model.p.copy()
    wire = ~model.mask.all(axis=1)
    if wire.any():
        d = np.cross(model.rows[wire, 0], model.rows[wire, 1])  # along each wire
        along = np.einsum("ni,ni->n", local[wire] - q[wire], d)
        q[wire] = q[wire] + along[:, None] * d
    q_base = q @ R.T  # about the base origin, as unpack turns the pose
    b_base = np.einsum("nij,kj->nik", model.rows, R)  # each row in the base frame
    J = np.concatenate([np.cross(q_base[:, None, :], b_base), b_base], axis=2)[model.mask]
    _, s, Vt = np.linalg.svd(J, full_matrices=False)
    seen = s > _GAUGE_RTOL * s[0]
    return None if seen.all() else Vt[seen].T.copy()


def wire_starts(
    obs: TargetObservations,
    target: WireTarget,
    T_k: Array,
    T_X0: Array,
    width_px: int,
    spacing: tuple[float, float],
) -> list[Array]:
    """Where a single wire's fit may start: the dots through the coarse mount, and the
    wire's CAD line laid through their centre along (a) the mean normal of the image
    planes (the probe is taught across the wire, so the wire runs along the image's
    elevation axis) and (b) the dots' principal axis (the sweeps slide along the wire).
    With a coarse mount degrees off, (b) can follow the mount's error instead; with
    sweeps turned far about the axial axis, (a) can: both are tried. The phantom's pose
    about and along the wire is not needed. ``T_k`` every frame's flange pose, ``T_X0``
    the mount the dots are mapped through. Returns the phantom poses to start from."""
    xy = nominal_xy(obs.pixel, width_px, spacing)
    P_us = np.column_stack([xy, np.zeros(len(xy))])
    T = T_k[obs.frame] @ T_X0
    pts = np.einsum("nij,nj->ni", T[:, :3, :3], P_us) + T[:, :3, 3]
    centre = pts.mean(axis=0)
    normal = T[:, :3, 2].mean(axis=0)
    axes = (normal / np.linalg.norm(normal), np.linalg.svd(pts - centre, full_matrices=False)[2][0])
    d = target.direction
    mid = (np.asarray(target.front) + np.asarray(target.back)) / 2
    starts = []
    for axis in axes:
        axis = axis if axis @ d >= 0 else -axis
        v, c = np.cross(d, axis), float(d @ axis)
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R = np.eye(3) + K + K @ K / (1.0 + c)  # the least rotation taking d onto the axis
        starts.append(se3.make(R, centre - R @ mid))
    return starts


def fit_phantom_pose(
    obs: TargetObservations,
    targets: Sequence[Target],
    T_base_ee: Array,
    *,
    T_ee_us: Array,
    spacing_m: tuple[float, float],
    width_px: int,
    start: Array,
) -> tuple[Array, Array]:
    """The phantom's pose that a given calibration (``T_ee_us`` and the pixel spacing,
    held) puts the observations on, robustly (soft-L1 at the residuals' own scale), along
    the directions the targets' constraints see; and each observation's error there (mm).
    What :func:`calibrate_targets` does with the calibration free: a calibration checked
    on a dataset whose phantom no tracker measured."""
    xy = nominal_xy(obs.pixel, width_px, spacing_m)
    T_k = np.asarray(T_base_ee, dtype=float)[obs.frame]
    rows, mask = observation_rows(obs, targets), row_mask(obs, targets)
    model = TargetModel(
        xy, T_k, obs.phantom_point, rows, mask, T_ee_us, start, True, False, (1.0, 1.0)
    )
    model = _seen_directions_only(model)
    k = model.n_phantom

    def residuals(z: Array) -> Array:
        x = np.zeros(model.n)
        x[6 : 6 + k] = z
        return model.residuals(x)

    z = np.zeros(k)
    for loss in ("linear", "soft_l1"):
        scale = _robust_sigma(residuals(z))
        z = least_squares(residuals, z, loss=loss, f_scale=scale, x_scale="jac").x
    x = np.zeros(model.n)
    x[6 : 6 + k] = z
    _, T_P, _ = model.unpack(x)
    return T_P, np.linalg.norm(model.residual_vectors(x), axis=1)


def _seen_directions_only(model: TargetModel) -> TargetModel:
    """``model`` with the phantom's pose moved only along the directions its targets'
    constraints see (:func:`_phantom_basis`); itself when they see all six."""
    basis = _phantom_basis(model)
    if basis is None:
        return model
    return TargetModel(
        model.xy, model.T_k, model.p, model.rows, model.mask, model.T_X0, model.T_P0,
        True, model.estimate_scale, model.scale0, basis,
    )  # fmt: skip


#: A declared error shared by every frame: given the model and the solution, the
#: residuals' response (columns, mm) to each of its components at 1 σ, or None.
Declared = Callable[[TargetModel, Array], Array | None]


def calibrate_targets(
    obs: TargetObservations,
    targets: Sequence[Target],
    T_base_ee: Array,
    *,
    width_px: int,
    height_px: int,
    spacing_m: tuple[float, float],
    T_base_phantom: Array | None = None,
    start: tuple[Array, Array] | None = None,
    estimate_scale: bool = True,
    declared: Declared | None = None,
    axial_bias_m: float = 0.0,
    n_draws: int = 4000,
    groups: NDArray[np.int_] | None = None,
    mount_sigma_m: float = 0.0,
    mount_sigma_rad: float = 0.0,
) -> TargetCalibration:
    """``T_ee_us`` (and the pixel scale, and the phantom's pose when ``T_base_phantom``
    is None) from observations of ``targets`` in frames taken at poses ``T_base_ee``
    (one per frame); see the module doc. ``start`` (T_ee_us, T_base_phantom): where the
    fit starts; needed when the targets include wires or a lone point (its phantom's
    turn is unseen and the closed form cannot have it); otherwise the closed form. One
    :class:`~calib.errors.CalibrationError` when the frames cannot determine it.

    The bounds add declared errors every frame shares, which no residual shows:
    ``declared`` (e.g. a phantom's build tolerance) and a bias of the echoes' depth
    (``axial_bias_m``, 1 σ; at least the rms distance between the points' centres and
    their echoes' peaks, which a comet tail lengthens), propagated to first order
    through the fit; and the rig's own error of the mount's position that no view shows
    (``mount_sigma_m``, ``mount_sigma_rad``: 1 σ per axis, declared; it goes into
    ``T_ee_us`` whole; :class:`calib.calibration.uncertainty.UncertaintyInputs`).

    ``groups`` (n,): the jackknife's groups when the data have them — a robot's views
    (:func:`calib.calibration.uncertainty.pose_orientation_groups`: the sweeps of one
    orientation share what that orientation does to the target's echo); without, blocks
    of consecutive frames (a freehand recording)."""
    t0 = time.perf_counter()
    if obs.frames_used < MIN_FRAMES:
        why = obs.refused.most_common(1)
        raise CalibrationError(
            f"{obs.frames_used} frames show the targets; the calibration needs at "
            f"least {MIN_FRAMES}" + (f" (most frames: {why[0][0]}, {why[0][1]}×)" if why else "")
        )
    xy = nominal_xy(obs.pixel, width_px, spacing_m)
    T_k = np.asarray(T_base_ee, dtype=float)[obs.frame]
    p = obs.phantom_point
    rows, mask = observation_rows(obs, targets), row_mask(obs, targets)
    if mask.all() and start is None:
        T_X0, scale0, T_P0 = closed_form(xy, T_k, p, T_base_phantom)
    elif start is None:
        raise CalibrationError(
            "a fit with wires needs a start (the coarse mount and the phantom's pose)"
        )
    else:
        T_X0, T_P0 = start
        scale0 = (1.0, 1.0)
        if T_base_phantom is not None:
            T_P0 = T_base_phantom
    if not estimate_scale:
        scale0 = (1.0, 1.0)
    estimate_phantom = T_base_phantom is None
    model = TargetModel(
        xy, T_k, p, rows, mask, T_X0, T_P0, estimate_phantom, estimate_scale, scale0
    )
    if estimate_phantom:
        model = _seen_directions_only(model)
    sigma = _robust_sigma(model.residuals(model.x0()))
    fit = _fit(model, model.x0(), sigma)
    # Then at the data's own scale at that solution, with a loss whose influence fades
    # (Cauchy): a glitch millimetres off no longer pulls the answer.
    for _ in range(3):  # the scale re-measured at each solution, until it holds
        sigma = _robust_sigma(fit.fun)
        fit = _fit(model, fit.x, _GLITCH_SIGMAS * sigma, loss="cauchy")
        if abs(_robust_sigma(fit.fun) / sigma - 1) < 0.02:
            break
    sigma = _robust_sigma(fit.fun)
    T_X, T_P, scale = model.unpack(fit.x)
    r = model.residual_vectors(fit.x)
    errors = np.linalg.norm(r, axis=1)
    dof = mask.sum(axis=1)
    limits = np.maximum(sigma * np.sqrt(chdtri(dof, _OUTLIER_P)), OUTLIER_FLOOR_MM)
    outliers = int(np.sum(errors > limits))

    # First-order covariance of the parameters (robust scale) and the block jackknife.
    # fit.jac is the Jacobian the robust loss weighted (inliers ≈ 1, outliers less).
    cov1 = np.linalg.pinv(fit.jac.T @ fit.jac) * sigma**2
    if groups is None:
        blocks = _blocks(obs.frame, 2 * correlation_frames(obs.frame, obs.target, r))
    else:
        blocks = np.unique(np.asarray(groups), return_inverse=True)[1]
    g = int(blocks.max()) + 1
    estimates = []
    for b in range(g):
        keep = blocks != b
        part = _fit(model, fit.x, _GLITCH_SIGMAS * sigma, keep, loss="cauchy", max_nfev=50)
        estimates.append(part.x)
    E = np.array(estimates)
    d = E - E.mean(axis=0)
    cov_jack = (g - 1) / g * d.T @ d
    cov = _dominating(cov1, cov_jack)
    widen = (float(stdtrit(g - 1, 0.975)) / float(ndtri(0.975))) ** 2
    cov = cov * widen
    # The information about the mount (θ = rotation rad, translation mm) with the
    # nuisances (phantom pose, scale) profiled out: its conditioning, as
    # calib.acquisition.observability states a sphere plan's.
    J_raw = _jacobian(lambda x: model.residuals(x), fit.x)
    J_raw[:, 3:6] *= 1e-3
    H = J_raw.T @ J_raw
    Hm, Hn, Hmn = H[:6, :6], H[6:, 6:], H[:6, 6:]
    info = Hm - Hmn @ np.linalg.pinv(Hn) @ Hmn.T if len(Hn) else Hm
    eig = np.sort(np.linalg.eigvalsh(0.5 * (info + info.T)))[::-1]
    # The echoes' depth is uncertain at least by how far their centres lie from their
    # peaks (a comet tail or a pulse's ring-down pulls a centre down): measured here.
    if len(obs.skew):
        axial_bias_m = max(axial_bias_m, float(np.sqrt(np.mean(obs.skew**2))) * spacing_m[1])
    columns = []
    shared = declared(model, fit.x) if declared is not None else None
    if shared is not None:
        columns.append(shared)
    if axial_bias_m > 0:
        r0 = model.residuals(fit.x)
        model.xy = xy + np.array([0.0, axial_bias_m])
        columns.append((model.residuals(fit.x) - r0)[:, None])
        model.xy = xy
    if columns:
        D = np.column_stack(columns)
        J = J_raw.copy()
        J[:, 3:6] *= 1e3
        w = 1.0 / (1.0 + (fit.fun / (_GLITCH_SIGMAS * sigma)) ** 2)  # the Cauchy weights
        A = np.linalg.pinv(J.T @ (w[:, None] * J)) @ (J.T * w) @ D
        cov = cov + A @ A.T

    if mount_sigma_m > 0 or mount_sigma_rad > 0:
        # (rotation vector, translation): a turn about the image's origin and a move of it.
        cov = cov.copy()
        cov[0:3, 0:3] += mount_sigma_rad**2 * np.eye(3)
        cov[3:6, 3:6] += mount_sigma_m**2 * np.eye(3)
    # Draws: rotation, translation, and mean distance over the image.
    keep_idx = list(range(6)) + ([model.n - 2, model.n - 1] if estimate_scale else [])
    C = cov[np.ix_(keep_idx, keep_idx)]
    rng = np.random.default_rng(0x5EED_0A1E)
    ev, V = np.linalg.eigh((C + C.T) / 2)
    draws = rng.standard_normal((n_draws, len(keep_idx))) @ (V * np.sqrt(np.clip(ev, 0, None))).T
    spacing_fit = (float(spacing_m[0] * scale[0]), float(spacing_m[1] * scale[1]))
    grid = image_grid(spacing_fit[0] * (width_px - 1), spacing_fit[1] * (height_px - 1))
    grid_xy = grid[:, :2] / np.array(spacing_fit)  # in units of the fitted spacing
    est = se3.apply(T_X, grid)
    rot = np.degrees(np.linalg.norm(draws[:, :3], axis=1))
    trans = np.linalg.norm(draws[:, 3:6], axis=1) * _MM
    image = np.empty(n_draws)
    for i, dx in enumerate(draws):
        R = se3.matrix_from_rotvec(dx[:3]) @ T_X[:3, :3]
        s = np.array(spacing_fit) * (1.0 + (dx[6:8] / np.array(scale) if estimate_scale else 0.0))
        P = np.column_stack([grid_xy * s, np.zeros(len(grid_xy))]) @ R.T + T_X[:3, 3] + dx[3:6]
        image[i] = np.linalg.norm(P - est, axis=1).mean() * _MM
    q = lambda v: float(np.percentile(v, 95))  # noqa: E731
    # The covariance reported: rotation vector and translation of T_ee_us, scale factors.
    full = np.zeros((8, 8))
    full[np.ix_(range(len(keep_idx)), range(len(keep_idx)))] = C
    return TargetCalibration(
        T_X,
        spacing_fit,
        T_P,
        errors,
        full,
        {"rotation_deg": q(rot), "translation_mm": q(trans), "image_mm": q(image)},
        bool(fit.status > 0),
        str(fit.message),
        g,
        outliers,
        int(width_px),
        int(height_px),
        estimate_scale,
        estimate_phantom,
        (float(scale[0]), float(scale[1])),
        sigma,
        eig,
        time.perf_counter() - t0,
        model.n_phantom if estimate_phantom else 0,
        model.points(fit.x)[0],
    )


@dataclass(frozen=True)
class TargetVerdict:
    """``accepted``, ``suspect`` or ``rejected``, with one line per reason."""

    status: Status
    reasons: tuple[str, ...]

    def line(self) -> str:
        return self.status + (": " + "; ".join(self.reasons) if self.reasons else "")

    def as_dict(self) -> dict[str, Any]:
        return {"status": self.status, "reasons": list(self.reasons)}


def judge_targets(
    cal: TargetCalibration, requirements: Requirements | None = None
) -> TargetVerdict:
    """The verdict of a calibration from targets (N-wire, wire, cone tip), on the
    questions :mod:`calib.calibration.verdict` asks of a sphere calibration that apply:
    did the fit converge; do the data determine ``T_ee_us`` (bound within 10° / 10 mm);
    do the points agree as their own scatter predicts (outliers at most a tenth); is the
    bound what the user asked (or within a millimetre over the image when nothing was
    asked)."""
    requirements = requirements or Requirements()
    rejected: list[str] = []
    suspect: list[str] = []
    b = cal.bound95
    if not cal.converged:
        rejected.append(f"the fit did not converge ({cal.message}): the answer is where it stopped")
    if b["rotation_deg"] > UNDETERMINED_DEG or b["translation_mm"] > UNDETERMINED_MM:
        rejected.append(
            f"the data do not determine T_ee_us (95 % bound {b['rotation_deg']:.1f}° / "
            f"{b['translation_mm']:.1f} mm): tilt and turn the probe more between frames"
        )
    share = cal.outliers / len(cal.errors_mm)
    if share > MAX_DROPPED_SHARE:
        suspect.append(
            f"{cal.outliers} of {len(cal.errors_mm)} wire points disagree with the rest "
            f"beyond their own scatter ({cal.sigma_mm:.2f} mm per axis): "
            "wrong dots, tracking glitches or wires off the phantom's definition; check the "
            "frames, the tracker and the phantom"
        )
    if requirements.any:
        over = []
        if requirements.image_mm is not None and b["image_mm"] > requirements.image_mm:
            over.append(f"{b['image_mm']:.2f} mm over the image > {requirements.image_mm:g}")
        if requirements.rotation_deg is not None and b["rotation_deg"] > requirements.rotation_deg:
            over.append(f"{b['rotation_deg']:.2f}° > {requirements.rotation_deg:g}")
        if over:
            rejected.append("95 % bound above the requirement: " + ", ".join(over))
    elif b["image_mm"] > DEFAULT_IMAGE_MM:
        suspect.append(
            f"95 % bound {b['image_mm']:.2f} mm over the image (above {DEFAULT_IMAGE_MM:g} "
            "mm): record more frames, at more orientations"
        )
    if rejected:
        return TargetVerdict("rejected", tuple(rejected + suspect))
    if suspect:
        return TargetVerdict("suspect", tuple(suspect))
    return TargetVerdict("accepted", ())
