"""95 % error bounds of an estimated ``T_ee_us`` from the data it rests on.

The first-order covariance of :func:`calib.calibration.markers.calibrate` (Jacobian and residual
variance) treats every localized centre as independent noise. Two kinds of error break
that: errors that depend on the pose and so are shared by the sweeps of one view (a
localization bias that depends on how the sphere is seen, the kinematic model's
residual, which is a smooth function of the arm's configuration), and errors common to
every sweep that the residuals cannot show (the printed sphere layout off its CAD, a
speed-of-sound scale). The first-order covariance here is at least the sandwich
estimator's (each residual's own size: the localization noise is anisotropic and differs
between views), and the covariance adds:

- **grouped jackknife** (statistical, from the data): the sweeps are grouped by the
  flange orientation they were taken at (the paper's protocol: 9 orientations × 5
  in-plane positions), each group is left out in turn and the calibration re-solved;
  the spread of the leave-one-group-out estimates, ``(g − 1)/g · Σ (θ_i − θ̄)(θ_i − θ̄)ᵀ``
  (Efron & Stein's delete-group jackknife), measures the error of correlated,
  view-dependent sources that sweep-level residuals average away. It is never taken
  below the first-order covariance (the larger of the two in every direction), and its
  95 % quantile uses Student's t with g − 1 degrees of freedom (g groups estimate it).
- **declared systematic terms**, propagated to first order through the solve
  (``dθ = −(JᵀJ)⁻¹ Jᵀ ∂r/∂e · de``): the print tolerance of the CAD sphere layout
  (multi-marker with the CAD layout taken as exact; 1 σ per axis per centre, the
  phantom's print specification — a fit that estimated the layout has it as its prior,
  so it is in the covariance instead), the printed spheres' radius tolerance (each
  sphere's centres move along their beams alike: the localizer fits the CAD radius), a
  bias of the localized centres along the beam common to every sweep (the cap's echo is
  a pulse: up to half the axial resolution), the kinematic model's error after a DH
  refinement, the uncertainty of the axial scale (speed of sound), and the rig's own
  error of the mount that no view shows (declared: a holder's bending, the arm's
  compliance, the localizer's bias on the printed phantom). The kinematic model's error
  is the refinement's own covariance carried to each sweep's pose
  (:func:`calib.kinematics.kinematic_modes`), less what a rigid change of base and
  flange frames absorbs; one draw of it moves every sweep, and
  the part that differs between views is what the jackknife measures too, so it is not
  added on top: the statistical covariance is at least the first order plus it. (Where
  only a residual size is known, 1 σ per axis of each view's point, independent between
  views, it is that floor alike.) The touch fit's residual itself is not that error: it
  carries the stylus's seating on each vertex, which the probe's views do not share.

The bounds are the 95th percentiles, over draws from that covariance, of the three
error measures the twin scores: rotation angle of ``T_est⁻¹ T``, translation distance,
and the mean distance over image points.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri, stdtrit

from .. import se3
from ..image import pixel_to_us
from .alternation import AlternationResult
from .markers import CalibrationResult, Observation

__all__ = [
    "Bound95",
    "UncertaintyInputs",
    "alternation_bound",
    "bound95",
    "image_grid",
    "modes_at",
    "moved_by_modes",
    "orientation_groups",
    "pose_orientation_groups",
]

Array = NDArray[np.float64]
_MM = 1e3

#: The draws' own generator (a fixed seed: the same calibration gives the same bound;
#: no scenario stream is touched).
_DRAWS_SEED = 0x5EED_B095


@dataclass(frozen=True)
class UncertaintyInputs:
    """What the pipeline declares about errors its residuals cannot show.

    Attributes
    ----------
    print_tolerance_m : float
        1 σ per axis of each printed sphere centre about its CAD position (the phantom's
        print specification); used with two or more markers.
    radius_tolerance_m : float
        1 σ of each printed sphere's radius about the CAD radius. The localizer fits the
        cap with the CAD radius, so a sphere printed Δr larger puts every centre of it Δr
        too close to the probe along that view's beam: an error shared by the sphere's
        sweeps, which their scatter cannot show.
    axial_bias_m : float
        1 σ of a bias of every localized centre along its beam, common to all sweeps:
        the cap's echo is a pulse, not the surface, and where in it the centre lands
        depends on the pulse's shape (its envelope, ring-down, log compression); up to
        half the axial resolution either way.
    kinematic_sigma_m : float
        1 σ per axis of the flange position error left by the kinematic model at each
        view, independent between views, when nothing better is known of it (the RMS
        residual of touches, per axis, is an upper estimate: it carries the stylus's
        seating noise, which the probe's views do not share); 0 when the controller's
        own model is trusted. Not used when ``kinematic_modes`` is given.
    kinematic_modes : mapping or None
        The kinematic model's own estimation error at each sweep's reference flange
        pose, ``(target, pose_id)`` → (k, 4, 4) derivatives of ``T_base_ee`` along k
        independent 1 σ directions (:func:`calib.kinematics.kinematic_modes` of a DH
        refinement's covariance). Shared by every sweep through the model's
        parameters, so a systematic term; what a rigid change of the base and flange
        frames would absorb is taken out first (the mount is measured through the
        model: that part is the model's gauge, not an error of the mount).
    axial_scale_sigma : float
        1 σ of the relative axial (depth) scale of the localized centres (speed of sound:
        the thermometer's uncertainty when corrected, the whole known difference when not).
    mount_sigma_m : float
        1 σ per axis of an error of the mount's position that the rig itself makes and no
        view shows (a holder bent by the probe's weight, the arm's compliance under the
        sweeps' load where the touches carried another, the localizer's bias on the
        phantom as printed): one draw moves ``T_ee_us`` as a whole, in the flange frame.
        Declared (a twin's error budget of the rig, a datasheet), not estimated.
    mount_sigma_rad : float
        The same for the mount's orientation: 1 σ per axis of a rotation about the
        image's origin (radians).
    """

    print_tolerance_m: float = 0.0
    radius_tolerance_m: float = 0.0
    axial_bias_m: float = 0.0
    kinematic_sigma_m: float = 0.0
    axial_scale_sigma: float = 0.0
    kinematic_modes: Mapping[tuple[str, int], Array] | None = None
    mount_sigma_m: float = 0.0
    mount_sigma_rad: float = 0.0


@dataclass(frozen=True)
class Bound95:
    """95 % error bounds of a ``T_ee_us`` estimate and what they were made of.

    ``covariance`` (6, 6) is of (rotation vector in the ee frame, rad; translation, m) of
    ``T_ee_us``, as :class:`calib.calibration.markers.CalibrationResult`'s; ``terms`` the 1 σ of
    rotation and translation (rss over the axes, degrees and mm) of each part.
    """

    rotation_deg: float
    translation_mm: float
    image_mm: float
    covariance: Array
    groups: int
    terms: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: float = 0.0

    def as_dict(self) -> dict[str, float]:
        """``metrics.json``'s ``bound95``."""
        return {
            "rotation_deg": self.rotation_deg,
            "translation_mm": self.translation_mm,
            "image_mm": self.image_mm,
        }

    def details(self) -> dict[str, Any]:
        """``metrics.json``'s ``uncertainty``: how the bound was made."""
        return {
            "method": "jackknife over views (orientation groups) + declared systematic terms",
            "views": self.groups,
            "one_sigma_rss": self.terms,
            "covariance_rotvec_rad_translation_m": self.covariance.tolist(),
            "seconds": self.seconds,
        }


def orientation_groups(obs: Sequence[Observation], *, tol_deg: float = 5.0) -> NDArray[np.int_]:
    """Group index (n,) of each observation: observations whose flange orientations are
    within ``tol_deg`` of a group's first one share it (the protocol's views; the
    in-plane positions of one view, and the same view of other spheres, fall together)."""
    return pose_orientation_groups(np.array([o.T_base_ee for o in obs]), tol_deg=tol_deg)


def pose_orientation_groups(T_base_ee: Array, *, tol_deg: float = 5.0) -> NDArray[np.int_]:
    """:func:`orientation_groups` of flange poses (n, 4, 4)."""
    R = np.asarray(T_base_ee, dtype=float)[:, :3, :3]
    cos_tol = np.cos(np.radians(tol_deg))
    out = np.full(len(R), -1)
    g = 0
    for i in range(len(R)):
        if out[i] >= 0:
            continue
        # cos of the relative angle: (tr(R_iᵀ R_j) − 1) / 2
        cos = (np.einsum("ab,nab->n", R[i], R) - 1.0) / 2.0
        out[(out < 0) & (cos > cos_tol)] = g
        g += 1
    return out


def _residual_model(obs, targets, cad, T_X, T_Y, layout=None, weight=0.0):
    """Residuals (mm) of the calibration's loss at ``exp(ξ_X) T_X`` (and phantom pose
    ``exp(ξ_Y) T_Y``) with perturbations: ``e_cad`` (s, 3) metres on the CAD centres,
    ``e_pt`` (n, 3) metres on the reconstructed points, ``e_scale`` on the axial scale.
    With an estimated ``layout`` (name → centre, phantom frame) and its prior's
    ``weight`` (σ_loc / σ_tol), the parameters go on with an increment of each sphere's
    printed position and the residuals with the prior's rows, as in the fit."""
    T_b = np.array([o.T_base_ee for o in obs])
    P = np.array([o.p_us for o in obs])
    groups = [np.array([i for i, o in enumerate(obs) if o.target == s]) for s in targets]
    groups = [g for g in groups if len(g)]
    multi = cad is not None
    C_cad = np.array([cad[obs[g[0]].target] for g in groups]) if multi else None
    floating = multi and layout is not None and weight > 0
    if floating:
        delta0 = np.array([layout[obs[g[0]].target] for g in groups]) - C_cad

    def residuals(x, e_cad=None, e_pt=None, e_scale=0.0):
        """(n_res,) for x (n_p,), or (k, n_res) for a batch x (k, n_p)."""
        xb = np.atleast_2d(x)
        TX = se3.exp(xb[:, :6]) @ T_X  # (k, 4, 4)
        T = T_b[None] @ TX[:, None]  # (k, n, 4, 4)
        Pk = P if e_scale == 0.0 else P * np.array([1.0, 1.0 + e_scale, 1.0])
        X = (T[..., :3, :3] @ Pk[..., None])[..., 0] + T[..., :3, 3]  # (k, n, 3)
        if e_pt is not None:
            X = X + e_pt
        k = len(xb)
        res, means = [], []
        for g in groups:
            m = X[:, g].mean(axis=1)
            means.append(m)
            res.append((X[:, g] - m[:, None]).reshape(k, -1))
        if multi:
            C = C_cad if e_cad is None else C_cad + e_cad
            if floating:
                delta = delta0 + xb[:, 12:].reshape(k, -1, 3)  # (k, s, 3)
                C = C + delta
            Y = se3.exp(xb[:, 6:12]) @ T_Y
            if floating:
                C = np.einsum("kij,ksj->ksi", Y[:, :3, :3], C) + Y[:, None, :3, 3]
            else:
                C = np.einsum("kij,sj->ksi", Y[:, :3, :3], C) + Y[:, None, :3, 3]
            for s, (g, m) in enumerate(zip(groups, means, strict=True)):
                res.append(np.sqrt(len(g)) * (m - C[:, s]))
            if floating:
                res.append(weight * delta.reshape(k, -1))
        out = np.concatenate(res, axis=1) * _MM
        return out if np.ndim(x) == 2 else out[0]

    return residuals, len(groups), multi, 3 * len(groups) * floating


def _jacobian(f, x0, h=1e-7):
    """Residuals and their forward-difference Jacobian, in one batched evaluation."""
    X = np.vstack([x0, x0 + h * np.eye(len(x0))])
    R = f(X)
    return R[0], (R[1:] - R[0]).T / h


def _resolve(obs, targets, cad, T_X, T_Y, layout=None, weight=0.0, iterations=3) -> Array:
    """Re-solve the calibration on a subset of the observations from the full estimate:
    Gauss-Newton steps (the loss is nearly quadratic this close to its minimum; each
    step costs a finite-difference Jacobian, ≈ 1 ms). Returns the left increment ξ of
    ``T_ee_us`` (6,)."""
    f, _, multi, n_layout = _residual_model(obs, targets, cad, T_X, T_Y, layout, weight)
    return _gauss_newton(f, np.zeros(6 + 6 * multi + n_layout), iterations)[:6]


def _gauss_newton(f, x: Array, iterations: int) -> Array:
    """Gauss-Newton steps on residuals ``f`` from ``x`` (finite-difference Jacobians),
    until the step of ``T_ee_us``'s increment is negligible."""
    for _ in range(iterations):
        r, J = _jacobian(f, x)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        x = x + step
        if np.linalg.norm(step[:3]) < 1e-9 and np.linalg.norm(step[3:6]) < 1e-8:
            break
    return x


def _layout_columns(f, x: Array, r: Array, n_s: int, h: float = 1e-6) -> Array:
    """∂r/∂(CAD centres) of a residual model at ``x`` (residuals ``r`` there),
    (n_res, 3 n_s)."""
    D = np.empty((len(r), 3 * n_s))
    for j in range(3 * n_s):
        e = np.zeros(3 * n_s)
        e[j] = h
        D[:, j] = (f(x, e_cad=e.reshape(n_s, 3)) - r) / h
    return D


def _layout_mismatch(obs, targets, J: Array, D_cad: Array, r: Array) -> float:
    """1 σ per axis (metres) of the per-sphere offsets that the fitted centroids' mismatch
    with the CAD layout shows (method of moments on the residuals): a misprinted layout
    and any localization bias of one sphere (its centre off in every view alike) pull
    the spheres apart from their CAD positions alike.

    With ``P = I − J (JᵀJ)⁻¹ Jᵀ`` (the residuals the fit leaves of a perturbation),
    per-point noise (variance ``σ_n²`` per axis, from the sweeps' scatter) and per-sphere
    offsets (``σ_b²``) leave ``E‖r_cad‖² = σ_n² ‖P D_pt‖²_cad + σ_b² ‖P D_cad‖²_cad`` in the
    layout rows of the residuals."""
    n_res = len(r)
    D_pt = np.zeros((n_res, 3 * len(obs)))  # ∂r/∂(point offsets), mm per m
    row = 0
    cad_row = n_res - 3 * len(targets)
    for s, t in enumerate(targets):
        g = np.array([i for i, o in enumerate(obs) if o.target == t])
        n_g = len(g)
        cols = (3 * g[:, None] + np.arange(3)).ravel()
        # Residuals of a sphere's points about their centroid: the centring matrix.
        D_pt[row : row + 3 * n_g, cols] = np.kron(np.eye(n_g) - 1.0 / n_g, np.eye(3))
        D_pt[cad_row + 3 * s : cad_row + 3 * s + 3, cols] = np.tile(np.eye(3), n_g) / np.sqrt(n_g)
        row += 3 * n_g
    D_pt *= _MM
    Q, _ = np.linalg.qr(J)

    def leave(X: Array) -> Array:
        return X - Q @ (Q.T @ X)

    P_pt, P_cad = leave(D_pt), leave(D_cad)
    first, last = slice(0, cad_row), slice(cad_row, n_res)
    sigma_n2 = float(r[first] @ r[first]) / max(float(np.sum(P_pt[first] ** 2)), 1e-30)
    excess = float(r[last] @ r[last]) - sigma_n2 * float(np.sum(P_pt[last] ** 2))
    return float(np.sqrt(max(excess, 0.0) / max(float(np.sum(P_cad[last] ** 2)), 1e-30)))


def modes_at(obs: Sequence[Observation], modes: Mapping[tuple[str, int], Array]) -> Array:
    """(n, k, 4, 4): the kinematic modes (:attr:`UncertaintyInputs.kinematic_modes`) at
    each observation's pose."""
    return np.array([modes[(o.target, int(o.pose_id))] for o in obs])


def moved_by_modes(M: Array, z: Array) -> Array:
    """(n, k, 3) metres: points ``z`` (n, 3, flange frame) moved by each mode of ``M``
    (:func:`modes_at`), to first order."""
    return np.einsum("nkij,nj->nki", M[..., :3, :3], z) + M[..., :3, 3]


def _gauge_free_displacements(
    obs: Sequence[Observation],
    modes: Mapping[tuple[str, int], Array],
    T_X: Array,
    image_points_us: Array,
) -> Array:
    """(n, k, 3) metres: each observation's reconstructed point moved by each of the
    kinematic modes (:attr:`UncertaintyInputs.kinematic_modes`), less what one rigid
    change of the base frame and one of the flange frame explain of that mode over all
    the observations' poses at the image's points (least squares, to first order)."""
    M = modes_at(obs, modes)  # (n, k, 4, 4)
    T = np.array([o.T_base_ee for o in obs])  # (n, 4, 4)
    n, k = M.shape[:2]
    # Tool points: a few of the image's points (corners and middle) and each
    # observation's own, in the flange frame.
    P = np.asarray(image_points_us, dtype=float)
    pick = np.unique(np.r_[0, len(P) - 1, np.argmin(P[:, 0]), np.argmax(P[:, 0]), len(P) // 2])
    tool = se3.apply(T_X, P[pick])  # (m, 3)
    own = se3.apply(T_X, np.array([o.p_us for o in obs]))  # (n, 3)

    def design(z: Array) -> Array:
        """(n, 3, 12): ∂ of the point T z (z in the flange frame, (n, 3)) by the base
        twist (ω_B, v_B) and the flange twist (ω_G, v_G)."""
        y = np.einsum("nij,nj->ni", T[:, :3, :3], z) + T[:, :3, 3]
        R = T[:, :3, :3]
        A = np.empty((len(z), 3, 12))
        A[:, :, 0:3] = -se3.hat(y)
        A[:, :, 3:6] = np.eye(3)
        A[:, :, 6:9] = -R @ se3.hat(z)
        A[:, :, 9:12] = R
        return A

    A_fit = np.concatenate([design(np.broadcast_to(p, (n, 3))) for p in tool], axis=1)
    b_fit = np.concatenate([moved_by_modes(M, np.broadcast_to(p, (n, 3))) for p in tool], axis=2)
    # b_fit: (n, k, 3m) with each point's 3 rows in turn, matching A_fit's (n, 3m, 12).
    b_fit = b_fit.reshape(n, k, len(tool), 3).transpose(0, 2, 3, 1).reshape(n * 3 * len(tool), k)
    xi = np.linalg.lstsq(A_fit.reshape(-1, 12), b_fit, rcond=None)[0]  # (12, k)
    return moved_by_modes(M, own) - np.einsum("nij,jk->nki", design(own), xi)


def _dominating(A: Array, B: Array) -> Array:
    """A covariance at least as large as ``A`` and ``B`` in every direction: ``A`` with
    the eigenvalues of ``B`` whitened by ``A`` raised to at least 1."""
    w, V = np.linalg.eigh(A)
    if w.min() <= 0:
        return A + B
    S = V * np.sqrt(w)  # A = S Sᵀ
    S_inv = np.linalg.inv(S)
    m, U = np.linalg.eigh(S_inv @ B @ S_inv.T)
    return S @ (U * np.maximum(m, 1.0)) @ U.T @ S.T


def _to_rotvec_translation(T_X: Array) -> Array:
    """(6, 6) map from the left increment ``ξ = (ρ, ω)`` of ``T_X`` to (rotation vector in
    the ee frame, change of ``T_X``'s translation): to first order ``ω`` and
    ``ρ + ω × t = ρ − [t]× ω``."""
    t = T_X[:3, 3]
    t_hat = se3.hat(t)
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)
    A[3:, :3] = np.eye(3)
    A[3:, 3:] = -t_hat
    return A


def _rss(cov_xi: Array, A: Array) -> dict[str, float]:
    """1 σ of the rotation (degrees) and of the translation of ``T_ee_us`` (mm), rss over
    the axes, of a covariance of ``ξ``."""
    d = np.sqrt(np.clip(np.diag(A @ cov_xi @ A.T), 0.0, None))
    return {
        "rotation_deg": float(np.degrees(np.linalg.norm(d[:3]))),
        "translation_mm": float(np.linalg.norm(d[3:]) * _MM),
    }


def bound95(
    obs: Sequence[Observation],
    result: CalibrationResult,
    image_points_us: Array,
    *,
    cad_centres: Mapping[str, Array] | None = None,
    inputs: UncertaintyInputs = UncertaintyInputs(),
    n_draws: int = 4000,
) -> Bound95:
    """95 % bounds of the errors of ``result.T_ee_us`` (see the module docstring).

    Parameters
    ----------
    obs : the observations ``result`` was fitted to (its ``retained`` mask applies)
    result : the calibration
    image_points_us : (m, 3) metres, us frame: the points the image error is averaged over
    cad_centres : the multi-marker fit's CAD centres (None: single-marker)
    inputs : the declared systematic terms
    n_draws : draws from the final covariance
    """
    t0 = time.perf_counter()
    obs = [o for o, k in zip(obs, result.retained, strict=True) if k]
    targets = list(dict.fromkeys(o.target for o in obs))
    multi = len(targets) >= 2 and cad_centres is not None and result.T_base_phantom is not None
    cad = {t: np.asarray(cad_centres[t], dtype=float) for t in targets} if multi else None
    T_X = result.T_ee_us
    T_Y = result.T_base_phantom if multi else np.eye(4)
    layout = result.layout if multi else None
    weight = result.layout_weight if layout is not None else 0.0
    f, n_s, multi, n_layout = _residual_model(obs, targets, cad, T_X, T_Y, layout, weight)
    n_p = 6 + 6 * multi + n_layout
    x0 = np.zeros(n_p)
    r0, J = _jacobian(f, x0)
    JtJ_inv = np.linalg.pinv(J.T @ J)
    # Unknown sphere centres are eliminated inside the residuals (centroids): count them.
    # (An estimated layout's increments and its prior's rows cancel in the count.)
    dof = max(len(r0) - n_p - 3 * n_s + n_layout, 1)
    cov_fo = (JtJ_inv * float(r0 @ r0) / dof)[:6, :6]
    # The localization noise is anisotropic (laterally a few hundredths of a millimetre,
    # in elevation up to a few tenths) and differs between views: the sandwich estimator
    # (White 1980; HC0 scaled by n / dof) reads each residual's own size instead of one
    # pooled variance. The larger of the two in every direction.
    meat = J.T @ (J * (r0**2)[:, None])
    cov_hc = (JtJ_inv @ meat @ JtJ_inv * len(r0) / dof)[:6, :6]
    cov_fo = _dominating(cov_fo, cov_hc)

    # ---- grouped jackknife: leave out one view (orientation group) at a time, re-solve.
    groups = orientation_groups(obs)
    g = int(groups.max()) + 1
    if g < 4:  # too few views to leave one out: the sweeps themselves
        groups, g = np.arange(len(obs)), len(obs)
    thetas = []
    for k in range(g):
        sub = [o for o, gk in zip(obs, groups, strict=True) if gk != k]
        if len({o.target for o in sub}) < len(targets) or len(sub) < 4:
            continue
        thetas.append(_resolve(sub, targets, cad, T_X, T_Y, layout, weight))
    thetas = np.array(thetas)
    m = len(thetas)
    if m >= 2:
        d = thetas - thetas.mean(axis=0)
        cov_jk = (m - 1) / m * d.T @ d
        dof_t = m - 1
    else:
        cov_jk, dof_t = np.zeros((6, 6)), max(dof, 1)
    fo_finite = bool(np.all(np.isfinite(cov_fo)))
    cov_stat = _dominating(cov_fo, cov_jk) if fo_finite else cov_jk
    # The jackknife estimates the covariance from g views: its 95 % quantile is
    # Student's, not normal; scale the statistical part accordingly. (The first order
    # alone has n − p degrees of freedom, near normal; scaling it by the views' t too
    # keeps a margin for the errors the views share, which neither estimate sees:
    # measured, it is what keeps an arm model that is slightly off and not refined
    # inside the bounds — benchmarks/uncertainty.py.)
    t_scale = (stdtrit(dof_t, 0.975) / ndtri(0.975)) ** 2
    cov_stat = cov_stat * t_scale
    cov_fo_t = cov_fo * t_scale if fo_finite else np.zeros((6, 6))

    # ---- declared systematic terms, first-order propagation through the solve.
    def propagate(D: Array, sigma: float) -> Array:
        """Covariance of ξ_X from independent perturbations, columns of D (∂r/∂e)."""
        A = -(JtJ_inv @ J.T @ D)[:6]
        return sigma**2 * A @ A.T

    A_rt = _to_rotvec_translation(T_X)
    terms = {"first_order": _rss(cov_fo, A_rt), "jackknife": _rss(cov_jk, A_rt)}
    cov_sys = np.zeros((6, 6))
    h = 1e-6

    if multi and not n_layout:
        D = _layout_columns(f, x0, r0, n_s, h)
        layout_observed = _layout_mismatch(obs, targets, J, D, r0)
        sigma = max(inputs.print_tolerance_m, layout_observed)
        if sigma > 0:
            c = propagate(D, sigma)
            terms["sphere_layout"] = _rss(c, A_rt) | {"sigma_mm": sigma * _MM}
            cov_sys += c
    elif multi:
        # An estimated layout: the print tolerance is the fit's prior, its uncertainty in
        # the covariance above (the prior's rows). What the data show beyond it — a
        # sphere whose centres are off alike in every view (its printed radius, a
        # localization bias), which the prior treats as a misprint of σ_tol at most —
        # is a term: the per-sphere offsets the exact-CAD residuals show (method of
        # moments), less the tolerance, propagated through the fit that estimated them.
        f_cad, _, _, _ = _residual_model(obs, targets, cad, T_X, T_Y)
        x_cad = _gauss_newton(f_cad, np.zeros(12), 3)  # the exact-CAD loss's own minimum
        r_cad, J_cad = _jacobian(f_cad, x_cad)
        D_cad = _layout_columns(f_cad, x_cad, r_cad, n_s, h)
        observed = _layout_mismatch(obs, targets, J_cad, D_cad, r_cad)
        excess = float(np.sqrt(max(observed**2 - inputs.print_tolerance_m**2, 0.0)))
        if excess > 0:
            c = propagate(_layout_columns(f, x0, r0, n_s, h), excess)
            terms["sphere_layout"] = _rss(c, A_rt) | {"sigma_mm": excess * _MM}
            cov_sys += c
    # Each view's beam (the us frame's axial axis) in the base frame, through the estimate.
    beams = np.array([(o.T_base_ee @ T_X)[:3, 1] for o in obs])
    if inputs.axial_bias_m > 0:
        # One column: every centre moved along its beam alike.
        D = ((f(x0, e_pt=h * beams) - r0) / h)[:, None]
        c = propagate(D, inputs.axial_bias_m)
        terms["axial_bias"] = _rss(c, A_rt)
        cov_sys += c
    if inputs.radius_tolerance_m > 0:
        # One column per sphere: its centres moved along their views' beams.
        D = np.empty((len(r0), n_s))
        for j, t in enumerate(targets):
            e = np.zeros((len(obs), 3))
            rows = np.array([o.target == t for o in obs])
            e[rows] = h * beams[rows]
            D[:, j] = (f(x0, e_pt=e) - r0) / h
        c = propagate(D, inputs.radius_tolerance_m)
        terms["sphere_radius"] = _rss(c, A_rt)
        cov_sys += c
    c_kin = None
    if inputs.kinematic_modes is not None:
        # The model's own error: one draw moves every sweep (gauge taken out).
        E = _gauge_free_displacements(obs, inputs.kinematic_modes, T_X, image_points_us)
        D = np.stack([(f(x0, e_pt=h * E[:, j]) - r0) / h for j in range(E.shape[1])], axis=1)
        c_kin = propagate(D, 1.0)
    elif inputs.kinematic_sigma_m > 0:
        # Only a size known: shared by the sweeps of one view of one sphere (a smooth
        # function of the configuration), independent between views and spheres.
        keys = sorted({(o.target, gk) for o, gk in zip(obs, groups, strict=True)})
        D = np.empty((len(r0), 3 * len(keys)))
        for j, key in enumerate(keys):
            rows = np.array([(o.target, gk) == key for o, gk in zip(obs, groups, strict=True)])
            for a in range(3):
                e = np.zeros((len(obs), 3))
                e[rows, a] = h
                D[:, 3 * j + a] = (f(x0, e_pt=e) - r0) / h
        c_kin = propagate(D, inputs.kinematic_sigma_m)
    if c_kin is not None:
        terms["kinematics"] = _rss(c_kin, A_rt)
        # What differs between views of it the jackknife over views measures too:
        # declared, it is the floor of that measurement (first order plus it, where few
        # views leave the jackknife short), not an addition, which would count it twice.
        cov_stat = _dominating(cov_stat, cov_fo_t + c_kin)
    if inputs.axial_scale_sigma > 0:
        D = ((f(x0, e_scale=h) - r0) / h)[:, None]
        c = propagate(D, inputs.axial_scale_sigma)
        terms["axial_scale"] = _rss(c, A_rt)
        cov_sys += c
    if inputs.mount_sigma_m > 0 or inputs.mount_sigma_rad > 0:
        # The mount's origin moved in the flange frame (ξ's ρ) and the mount turned about
        # that origin (ω, with ρ = t × ω so the origin stays): the whole declared error
        # goes into T_ee_us, none of it into the residuals.
        turn = np.vstack([se3.hat(T_X[:3, 3]), np.eye(3)])  # (6, 3): ξ of a turn about it
        c = np.zeros((6, 6))
        c[:3, :3] = inputs.mount_sigma_m**2 * np.eye(3)
        c += inputs.mount_sigma_rad**2 * turn @ turn.T
        terms["mount"] = _rss(c, A_rt)
        cov_sys += c
    cov = cov_stat + cov_sys
    terms["total"] = _rss(cov, A_rt)

    # ---- bounds: 95th percentiles of the error measures over draws of ξ.
    rng = np.random.default_rng(_DRAWS_SEED)
    w, V = np.linalg.eigh((cov + cov.T) / 2)
    xi = rng.standard_normal((n_draws, 6)) @ (V * np.sqrt(np.clip(w, 0.0, None))).T
    T = se3.exp(xi) @ T_X
    rot = np.linalg.norm(xi[:, 3:], axis=1)
    trans = np.linalg.norm(T[:, :3, 3] - T_X[:3, 3], axis=1)
    P = np.asarray(image_points_us, dtype=float)
    P_est = se3.apply(T_X, P)
    diff = T[:, :3, :3] @ P.T + (T[:, :3, 3][:, :, None] - P_est.T[None])  # (k, 3, m)
    image = np.sqrt(np.einsum("kam,kam->km", diff, diff)).mean(axis=1)
    q = lambda v: float(np.percentile(v, 95))  # noqa: E731
    return Bound95(
        float(np.degrees(q(rot))),
        q(trans) * _MM,
        q(image) * _MM,
        A_rt @ cov @ A_rt.T,
        g,
        terms,
        time.perf_counter() - t0,
    )


def alternation_bound(
    alt: AlternationResult,
    image_points_us: Array,
    *,
    cad_centres: Mapping[str, Array] | None = None,
    inputs: UncertaintyInputs = UncertaintyInputs(),
) -> Bound95:
    """:func:`bound95` of an alternation's final calibration (its observations)."""
    return bound95(
        alt.observations, alt.result, image_points_us, cad_centres=cad_centres, inputs=inputs
    )


def image_grid(width_m: float, depth_m: float, *, n: int = 21) -> Array:
    """An n × n grid of points (n², 3) covering an image ``width_m`` wide and
    ``depth_m`` deep, metres in the ``us`` frame (the image error's points)."""
    spacing = (width_m / (n - 1), depth_m / (n - 1))
    P = pixel_to_us(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), n, spacing)
    return P.reshape(-1, 3)
