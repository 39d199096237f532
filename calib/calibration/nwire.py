"""Calibration from N-wire phantoms (issue "N-wire and wire targets", item 3): the field's
standard phantom through the same questions the sphere method answers — what ``T_ee_us``
is, how sure we are of it, and whether to use it.

Each frame in which :func:`calib.localize.nwire.detect_nwires` finds every pattern gives one
point per pattern whose position is known in two frames: in the image (the diagonal
wire's dot, pixels) and in the phantom (where the image plane cuts the diagonal,
:func:`calib.localize.nwire.middle_wire_point`, from the ratio of the dots' distances along
their line). With the probe's pose ``T_base_ee`` per frame (a tracker's
``ProbeToReference``, or a robot's flange pose) the calibration solves, over every such
point ``i`` of frame ``k``,

    T_base_ee[k] · T_ee_us · s(u_i)  =  T_base_phantom · p_i

for ``T_ee_us`` (PLUS's ``ImageToProbe`` without the pixel spacing), the pixel scale
``s`` (optional: a spacing the scanner reports wrong, or a speed of sound off, is the same
unknown) and, on a robot, the phantom's pose ``T_base_phantom`` (as the three-marker fit
estimates the layout's; a tracker measures it, PLUS's ``Phantom`` → ``Reference``).

1. **Closed form.** The equation is linear in the entries of the affine map
   ``M = [k_x r_1, k_y r_2, t]`` from nominal image coordinates to the probe frame (and, on
   a robot, in those of ``T_base_phantom``): linear least squares, then the nearest
   rotations. No initial guess is needed.
2. **Refinement.** Robust least squares of the 3-D distances (soft-L1, then Cauchy at three
   times that scale), at the scale of the residuals' own median absolute deviation: no
   threshold.
3. **Error.** The 3-D reprojection error of each point (the distance above, mm) — what
   PLUS reports — and its summary as PLUS states it (mean and SD below the 95th
   percentile, its ``ErrorConfidenceLevel``).
4. **Bounds and verdict.** A delete-group jackknife over blocks of consecutive frames,
   each twice as long as the residuals stay correlated (neighbouring frames share the
   tracker's and the phantom's pose-dependent errors: on PLUS's fCal recording the two
   halves' answers differ by 1.2 mm over the image, which blocks of ten frames would
   call impossible) against the first-order covariance, the larger in every direction,
   Student-t widened; the 95 % bounds of rotation, translation and the mean error over
   the image; and a verdict as :mod:`calib.calibration.verdict` gives the sphere method's.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.special import ndtri, stdtrit
from scipy.stats import chi2

from .. import se3
from ..errors import CalibrationError
from ..files.dataset import AcquisitionInfo
from ..files.plus_config import NWirePattern, image_to_probe_mm
from ..image import pixel_axes
from ..localize.nwire import NWireDetection, detect_nwires, middle_wire_point
from ..pipeline import axial_scale
from ..records import Dataset
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
    "NWireCalibration",
    "NWireObservations",
    "NWireVerdict",
    "calibrate_either_side",
    "calibrate_nwire",
    "correlation_frames",
    "dataset_frames",
    "dataset_spacing_m",
    "image_points_in_base",
    "judge_nwire",
    "observations_of",
    "observe_nwires",
    "plus_error_mm",
    "reprojection_errors_mm",
]

Array = NDArray[np.float64]
_MM = 1e3
#: Fewer frames with every pattern found than this cannot be split into jackknife blocks
#: and leave a fit: refuse (PLUS's own tests calibrate from well over a hundred).
MIN_FRAMES = 10
#: Jackknife blocks of consecutive frames: each at least twice the residuals' correlation
#: length (:func:`correlation_frames`), so that blocks, not frames, are independent; at
#: most ten (the sphere method's nine views), at least four (fewer leave the t quantile,
#: and the bound, unusable: it is then wide, and the verdict says so).
MAX_BLOCKS = 10
MIN_BLOCKS = 4
#: A point is an outlier when its 3-D error squared exceeds the χ²(3) 0.1 % quantile of
#: the fit's own per-axis scale: a segmentation or tracking glitch, not noise.
_OUTLIER_P = 1e-3
#: The Cauchy loss's scale in the data's own σ: points within a few σ count fully (the
#: noise), those far beyond fade (glitches).
_GLITCH_SIGMAS = 3.0
#: ... and beyond this many millimetres: a wire point off by less is no glitch, whatever
#: the scatter (the sphere method's centres: 2 mm; a wire point is read more finely).
OUTLIER_FLOOR_MM = 1.0
#: PLUS's ErrorConfidenceLevel: its 3-D error is stated below this percentile.
PLUS_CONFIDENCE = 95.0


@dataclass(frozen=True)
class NWireObservations:
    """The diagonal-wire points of the frames where every pattern was found.

    ``frame`` (n,) index into the frames; ``pattern`` (n,) into the phantom's patterns;
    ``pixel`` (n, 2) the diagonal dot (column, row); ``phantom_point`` (n, 3) where the
    plane cuts the diagonal (phantom frame, metres); ``detections`` every frame's result
    (reasons for those not used); ``outer`` the outer dots the point was read with (for
    the phantom's tolerance in the bounds)."""

    frame: NDArray[np.int_]
    pattern: NDArray[np.int_]
    pixel: Array
    phantom_point: Array
    detections: tuple[NWireDetection, ...]
    outer: Array | None = None  # (n, 2, 2): the outer dots (first, last) as read, pixels
    skew: Array | None = None  # (n,): the diagonal dot's centre below its peak, rows

    @property
    def frames_used(self) -> int:
        return len(np.unique(self.frame))

    def subset(self, keep: NDArray[np.bool_]) -> NWireObservations:
        """The points where ``keep`` holds (frame indices unchanged)."""
        return NWireObservations(
            self.frame[keep],
            self.pattern[keep],
            self.pixel[keep],
            self.phantom_point[keep],
            self.detections,
            None if self.outer is None else self.outer[keep],
            None if self.skew is None else self.skew[keep],
        )

    def refusals(self) -> Counter[str]:
        """Why frames were not used: reason → count."""
        return Counter(d.reason for d in self.detections if not d.ok)


def observe_nwires(
    frames: NDArray[np.uint8],
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
) -> NWireObservations:
    """Detect the N patterns in every frame and turn each found pattern into its
    diagonal-wire point (image and phantom)."""
    detections = tuple(detect_nwires(f, patterns, spacing_mm) for f in frames)
    return observations_of(detections, patterns, spacing_mm)


def observations_of(
    detections: Sequence[NWireDetection],
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
    *,
    mirrored: bool = False,
) -> NWireObservations:
    """The diagonal-wire points of detections; ``mirrored``: each line's outer dots
    taken the other way round (the image's marked side showing the pattern's last wire
    first: a probe turned half a turn about its axis)."""
    sx, sy = spacing_mm
    mm = np.array([sx, sy])
    rows_f, rows_p, pix, pts, outer, skew = [], [], [], [], [], []
    for k, det in enumerate(detections):
        if not det.ok:
            continue
        for j, pattern in enumerate(patterns):
            a, m, b = (np.array(det.points[w.name]) for w in pattern.wires)
            if mirrored:
                a, b = b, a
            rows_f.append(k)
            rows_p.append(j)
            pix.append(m)
            outer.append((a, b))
            skew.append(det.skew.get(pattern.wires[1].name, 0.0))
            pts.append(middle_wire_point(pattern, a * mm, m * mm, b * mm))
    return NWireObservations(
        np.array(rows_f, dtype=int),
        np.array(rows_p, dtype=int),
        np.array(pix, dtype=float).reshape(-1, 2),
        np.array(pts, dtype=float).reshape(-1, 3),
        tuple(detections),
        np.array(outer, dtype=float).reshape(-1, 2, 2),
        np.array(skew, dtype=float),
    )


@dataclass(frozen=True)
class NWireCalibration:
    """The result of :func:`calibrate_nwire`.

    ``T_ee_us`` (4, 4) metres; ``spacing_m`` the pixel spacing (columns, rows) the fit
    holds with (estimated when ``scale_estimated``); ``T_base_phantom`` (given, or
    estimated when ``phantom_estimated``); ``errors_mm`` each point's 3-D reprojection
    error; ``covariance`` (8, 8) of (rotation vector of ``T_ee_us`` in the ee frame, rad;
    its translation, m; the two scale factors) — zero rows for what was not estimated;
    ``bound95`` rotation (deg), translation (mm) and mean error over the image (mm);
    ``converged`` and the solver's ``message``; ``blocks`` the jackknife's groups;
    ``outliers`` the points beyond the χ² quantile of the fit's own scale and a
    millimetre; ``scale`` the fitted spacing over the nominal one (1, 1 when held);
    ``sigma_mm`` the residuals' robust scale per axis; ``information_eigenvalues`` (6,)
    of the information about the mount (rotation rad, translation mm), the phantom's pose
    and the scale profiled out, descending."""

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

    def image_to_probe_mm(self) -> Array:
        """PLUS's ``ImageToProbe``: pixel (column, row, 0, 1) → probe (ee) millimetres,
        the fitted pixel spacing included."""
        return image_to_probe_mm(self.T_ee_us, self.width_px, self.spacing_m)


def plus_error_mm(errors_mm: Array) -> tuple[float, float]:
    """The 3-D reprojection error as PLUS states it: mean and SD of the errors at or
    below their 95th percentile (vtkProbeCalibrationAlgo's ``ErrorConfidenceLevel``)."""
    e = np.asarray(errors_mm, dtype=float)
    kept = e[e <= np.percentile(e, PLUS_CONFIDENCE)]
    return float(kept.mean()), float(kept.std())


def _nominal_xy(pixel: Array, width_px: int, spacing_m: tuple[float, float]) -> Array:
    x, y = pixel_axes(pixel[:, 1], pixel[:, 0], width_px, spacing_m)
    return np.column_stack([x, y])


def _closed_form(
    xy: Array, T_k: Array, p: Array, T_base_phantom: Array | None
) -> tuple[Array, tuple[float, float], Array]:
    """Step 1 of the module doc: (T_ee_us, scale factors, T_base_phantom)."""
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


class _Model:
    """The residuals of step 2 as a function of the parameter vector: increments of
    ``T_ee_us`` (rotation vector about its initial rotation, translation), of the
    phantom's pose when it is estimated, and the two scale factors when estimated."""

    def __init__(self, xy, T_k, p, T_X0, T_P0, estimate_phantom, estimate_scale, scale0):
        self.xy, self.T_k, self.p = xy, T_k, p
        self.T_X0, self.T_P0 = T_X0, T_P0
        self.estimate_phantom, self.estimate_scale = estimate_phantom, estimate_scale
        self.scale0 = np.asarray(scale0, dtype=float)
        self.n = 6 + 6 * estimate_phantom + 2 * estimate_scale

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        T_X = se3.make(se3.matrix_from_rotvec(x[:3]) @ self.T_X0[:3, :3], self.T_X0[:3, 3] + x[3:6])
        i = 6
        T_P = self.T_P0
        if self.estimate_phantom:
            T_P = se3.make(
                se3.matrix_from_rotvec(x[i : i + 3]) @ self.T_P0[:3, :3],
                self.T_P0[:3, 3] + x[i + 3 : i + 6],
            )
            i += 6
        scale = self.scale0 * (x[i : i + 2] if self.estimate_scale else 1.0)
        return T_X, T_P, scale

    def x0(self) -> Array:
        x = np.zeros(self.n)
        if self.estimate_scale:
            x[-2:] = 1.0
        return x

    def points(self, x: Array, rows=slice(None)) -> tuple[Array, Array]:
        T_X, T_P, scale = self.unpack(x)
        xy = self.xy[rows] * scale
        P_us = np.column_stack([xy, np.zeros(len(xy))])
        T = self.T_k[rows] @ T_X
        image = np.einsum("nij,nj->ni", T[:, :3, :3], P_us) + T[:, :3, 3]
        return image, se3.apply(T_P, self.p[rows])

    def residuals(self, x: Array, rows=slice(None)) -> Array:
        image, wire = self.points(x, rows)
        return ((image - wire) * _MM).ravel()


def _fit(model: _Model, x0: Array, f_scale: float, rows=slice(None), loss="soft_l1", **kw):
    return least_squares(
        lambda x: model.residuals(x, rows), x0, loss=loss, f_scale=f_scale, x_scale="jac", **kw
    )


def _robust_sigma(r: Array) -> float:
    """Per-axis scale of residuals (mm): 1.4826 × their median absolute value."""
    return max(1.4826 * float(np.median(np.abs(r))), 1e-6)


def correlation_frames(frame: NDArray[np.int_], pattern: NDArray[np.int_], r: Array) -> int:
    """How many consecutive frames share an error: the first lag (in frames used) at which
    the autocorrelation of the residual vectors, per pattern, averaged, falls below
    1/e. Neighbouring frames of a freehand sweep share the tracker's and the phantom's
    pose-dependent errors; on PLUS's fCal recording this is about 20 frames."""
    used = np.unique(frame)
    n = len(used)
    order = {f: i for i, f in enumerate(used)}
    acf = np.zeros(max(n // 3, 1))
    for j in np.unique(pattern):
        rows = np.flatnonzero(pattern == j)
        series = np.full((n, 3), np.nan)
        series[[order[f] for f in frame[rows]]] = r[rows]
        series -= np.nanmean(series, axis=0)
        power = np.nanmean(np.sum(series * series, axis=1))
        for lag in range(1, len(acf)):
            products = np.sum(series[:-lag] * series[lag:], axis=1)
            acf[lag] += np.nanmean(products) / power if np.isfinite(products).any() else 0.0
    acf /= len(np.unique(pattern))
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


def _declared_columns(model, x, obs, patterns, spacing_m, tolerance, axial_bias):
    """The residuals' response (mm) to each declared error at its 1 σ, as columns: every
    coordinate of every wire end (the build tolerance: the diagonal point is read through
    the pattern's geometry) and a common shift of the echoes' depth. None without either."""
    columns = []
    if tolerance > 0 and patterns is not None and obs.outer is not None:
        _, T_P, _ = model.unpack(x)
        mm = np.array(spacing_m) * _MM
        for j, pattern in enumerate(patterns):
            rows = np.flatnonzero(obs.pattern == j)
            a, b = obs.outer[rows, 0] * mm, obs.outer[rows, 1] * mm
            m = obs.pixel[rows] * mm
            base = middle_wire_point(pattern, a, m, b)
            for w in range(3):
                for end in ("front", "back"):
                    for axis in range(3):
                        wires = list(pattern.wires)
                        point = getattr(wires[w], end).copy()
                        point[axis] += tolerance
                        wires[w] = replace(wires[w], **{end: point})
                        moved = NWirePattern(tuple(wires))  # type: ignore[arg-type]
                        p = middle_wire_point(moved, a, m, b)
                        col = np.zeros((len(obs.frame), 3))
                        col[rows] = -(p - base) @ T_P[:3, :3].T * _MM
                        columns.append(col.ravel())
    if axial_bias > 0:
        r0 = model.residuals(x)
        xy = model.xy
        model.xy = xy + np.array([0.0, axial_bias])
        columns.append(model.residuals(x) - r0)
        model.xy = xy
    return np.column_stack(columns) if columns else None


def calibrate_nwire(
    obs: NWireObservations,
    T_base_ee: Array,
    *,
    width_px: int,
    height_px: int,
    spacing_m: tuple[float, float],
    T_base_phantom: Array | None = None,
    estimate_scale: bool = True,
    n_draws: int = 4000,
    patterns: Sequence[NWirePattern] | None = None,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
) -> NWireCalibration:
    """``T_ee_us`` (and the pixel scale, and the phantom's pose when ``T_base_phantom``
    is None) from the N-wire observations of frames taken at poses ``T_base_ee`` (one per
    frame); see the module doc. One :class:`~calib.errors.CalibrationError` when the
    frames cannot determine it (too few frames with every pattern, orientations too
    alike).

    The bounds add two declared errors every frame shares, which no residual shows:
    the phantom's build tolerance (``wire_tolerance_m``, 1 σ per axis of each wire's
    ends, with the ``patterns`` the points were read with) and a bias of the echoes'
    depth (``axial_bias_m``, 1 σ: the echo comes from the wire's front surface, drawn by
    a pulse; at least the rms distance between the dots' centres and their echoes'
    peaks, which a comet tail lengthens), each propagated to first order through the
    fit."""
    t0 = time.perf_counter()
    if obs.frames_used < MIN_FRAMES:
        why = obs.refusals().most_common(1)
        raise CalibrationError(
            f"{obs.frames_used} frames show every wire pattern; the calibration needs at "
            f"least {MIN_FRAMES}" + (f" (most frames: {why[0][0]}, {why[0][1]}×)" if why else "")
        )
    xy = _nominal_xy(obs.pixel, width_px, spacing_m)
    T_k = np.asarray(T_base_ee, dtype=float)[obs.frame]
    p = obs.phantom_point
    T_X0, scale0, T_P0 = _closed_form(xy, T_k, p, T_base_phantom)
    if not estimate_scale:
        scale0 = (1.0, 1.0)
    model = _Model(xy, T_k, p, T_X0, T_P0, T_base_phantom is None, estimate_scale, scale0)
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
    r = fit.fun.reshape(-1, 3)
    errors = np.linalg.norm(r, axis=1)
    limit = max(sigma * float(np.sqrt(chi2.isf(_OUTLIER_P, 3))), OUTLIER_FLOOR_MM)
    outliers = int(np.sum(errors > limit))

    # First-order covariance of the parameters (robust scale) and the block jackknife.
    # fit.jac is the Jacobian the robust loss weighted (inliers ≈ 1, outliers less).
    cov1 = np.linalg.pinv(fit.jac.T @ fit.jac) * sigma**2
    blocks = _blocks(obs.frame, 2 * correlation_frames(obs.frame, obs.pattern, r))
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
    if obs.skew is not None and len(obs.skew):
        axial_bias_m = max(axial_bias_m, float(np.sqrt(np.mean(obs.skew**2))) * spacing_m[1])
    declared = _declared_columns(
        model, fit.x, obs, patterns, spacing_m, wire_tolerance_m, axial_bias_m
    )
    if declared is not None:
        J = J_raw.copy()
        J[:, 3:6] *= 1e3
        w = 1.0 / (1.0 + (fit.fun / (_GLITCH_SIGMAS * sigma)) ** 2)  # the Cauchy weights
        A = np.linalg.pinv(J.T @ (w[:, None] * J)) @ (J.T * w) @ declared
        cov = cov + A @ A.T

    # Draws: rotation, translation, and mean distance over the image.
    keep_idx = list(range(6)) + ([model.n - 2, model.n - 1] if estimate_scale else [])
    C = cov[np.ix_(keep_idx, keep_idx)]
    rng = np.random.default_rng(0x5EED_0A1E)
    w, V = np.linalg.eigh((C + C.T) / 2)
    draws = rng.standard_normal((n_draws, len(keep_idx))) @ (V * np.sqrt(np.clip(w, 0, None))).T
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
    return NWireCalibration(
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
        T_base_phantom is None,
        (float(scale[0]), float(scale[1])),
        sigma,
        eig,
        time.perf_counter() - t0,
    )


def dataset_frames(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of the dataset's sequences, in order, and its pose ``T_base_ee``."""
    images = np.concatenate([s.images for s in dataset.sweeps])
    poses = np.concatenate([s.T_base_ee for s in dataset.sweeps])
    return images, poses


def dataset_spacing_m(dataset: Dataset, info: AcquisitionInfo) -> tuple[float, float]:
    """The images' pixel spacing (columns, rows; m), the axial one corrected for the
    medium's speed of sound when the dataset asks for it."""
    sx, sy = dataset.sweeps[0].spacing
    return float(sx), float(sy) * axial_scale(info)


def calibrate_either_side(
    obs: NWireObservations,
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
    T_base_ee: Array,
    **kwargs: Any,
) -> tuple[NWireCalibration, NWireObservations, bool]:
    """:func:`calibrate_nwire` with the image's marked side unknown: the wires read from
    either side (:func:`observations_of`), each fitted, the one whose points agree best
    (the smaller robust scatter) kept. A probe mounted the other way round swaps which
    outer wire each line shows first; the wrong reading puts every diagonal point at the
    other end of its diagonal, and the poses cannot agree with it. Returns (calibration,
    the observations it rests on, whether they are mirrored)."""
    best: tuple[NWireCalibration, NWireObservations, bool] | None = None
    for mirrored in (False, True):
        o = observations_of(obs.detections, patterns, spacing_mm, mirrored=mirrored)
        try:
            cal = calibrate_nwire(o, T_base_ee, patterns=patterns, **kwargs)
        except CalibrationError:
            if mirrored and best is None:
                raise
            continue
        if best is None or cal.sigma_mm < best[0].sigma_mm:
            best = (cal, o, mirrored)
    assert best is not None
    return best


def reprojection_errors_mm(
    obs: NWireObservations,
    T_base_ee: Array,
    image_to_probe_mm: Array,
    T_base_phantom: Array,
) -> Array:
    """Each point's 3-D reprojection error (mm) under a calibration given as PLUS's
    ``ImageToProbe`` (pixel → probe mm, its pixel spacing included): uscal's own, or any
    other tool's."""
    image = image_points_in_base(obs, T_base_ee, image_to_probe_mm)
    wire = se3.apply(T_base_phantom, obs.phantom_point)
    return np.linalg.norm(image - wire, axis=1) * _MM


def image_points_in_base(
    obs: NWireObservations, T_base_ee: Array, image_to_probe_mm: Array
) -> Array:
    """The diagonal dots (n, 3) mapped to the base frame (metres) through a calibration
    given as PLUS's ``ImageToProbe`` and each frame's pose."""
    A = np.asarray(image_to_probe_mm, dtype=float)
    uv = np.column_stack([obs.pixel, np.zeros(len(obs.pixel)), np.ones(len(obs.pixel))])
    P_ee = (uv @ A.T)[:, :3] * 1e-3
    T_k = np.asarray(T_base_ee, dtype=float)[obs.frame]
    return np.einsum("nij,nj->ni", T_k[:, :3, :3], P_ee) + T_k[:, :3, 3]


@dataclass(frozen=True)
class NWireVerdict:
    """``accepted``, ``suspect`` or ``rejected``, with one line per reason."""

    status: Status
    reasons: tuple[str, ...]

    def line(self) -> str:
        return self.status + (": " + "; ".join(self.reasons) if self.reasons else "")

    def as_dict(self) -> dict[str, Any]:
        return {"status": self.status, "reasons": list(self.reasons)}


def judge_nwire(cal: NWireCalibration, requirements: Requirements | None = None) -> NWireVerdict:
    """The verdict of an N-wire calibration, on the questions :mod:`calib.calibration.verdict` asks
    of a sphere calibration that apply to it: did the fit converge; do the data
    determine ``T_ee_us`` (bound within 10° / 10 mm); do the points agree as their own
    scatter predicts (outliers at most a tenth); is the bound what the user asked (or
    within a millimetre over the image when nothing was asked)."""
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
        return NWireVerdict("rejected", tuple(rejected + suspect))
    if suspect:
        return NWireVerdict("suspect", tuple(suspect))
    return NWireVerdict("accepted", ())
