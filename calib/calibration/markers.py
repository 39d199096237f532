"""Single- and three-marker calibration (paper, "Single- and Three-Marker Calibration").

Each accepted sweep k of sphere s gives a localized centre ``p_sk`` in its reference
(centre-frame ``us``) frame; with the reported flange pose ``T_base_ee,k`` of that frame
it reconstructs to ``x_sk(X) = T_base_ee,k · X · p_sk`` (paper Eq. 1), ``X = T_ee_us``.
The loss (paper, distance objective) is

    L(X, Y) = Σ_s Σ_k ‖x_sk(X) − x̄_s(X)‖² + Σ_s n_s ‖x̄_s(X) − C_s(Y)‖²,

with ``C_s = R c_s^CAD + t`` the CAD sphere centres at the unknown phantom pose ``Y`` (only
for two or more markers; single-marker keeps the first term). Solved with scipy's
``least_squares(method="trf")``, residuals in millimetres, from a closed-form linear
initialisation that needs no coarse estimate.

The paper treats the CAD layout as exact. A printed phantom is not: with a stated print
tolerance σ_tol (1 σ per axis of a sphere centre) the multi-marker fit estimates the
printed layout too, ``C_s = Y (c_s^CAD + δ_s)``, with the CAD as a prior: each ``δ_s``
adds the residual ``(σ_loc / σ_tol) δ_s`` (σ_loc, per axis, the localized centres'
scatter about their sphere), the maximum a posteriori estimate when the misprint is
Gaussian. σ_tol → 0 gives the paper's exact layout; a loose tolerance lets each sphere
float and leaves the fit with what the spheres share (one ``T_ee_us``), never worse
than one marker.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from .. import se3
from ..errors import CalibrationError
from ..robust import outlier_limit, robust_inliers

__all__ = [
    "CalibrationConfig",
    "CalibrationResult",
    "Observation",
    "calibrate",
    "centres_in_base",
    "centroid_distances_mm",
    "consensus_initialisation",
    "linear_initialisation",
    "outlier_limit",
    "robust_inliers",
]

Array = NDArray[np.float64]

_MM = 1e3


@dataclass(frozen=True)
class CalibrationConfig:
    """Single- and three-marker calibration (paper, "Single- and Three-Marker Calibration")."""

    initial_error_mm: float = field(
        default=3.0,
        metadata={
            "doc": "Simulation: the coarse T_ee_us handed to the pipeline is off by up to "
            "± this per axis.",
            "ge": 0,
            "le": 50,
        },
    )
    initial_error_deg: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: coarse T_ee_us rotation error, up to ± this per axis.",
            "ge": 0,
            "le": 45,
        },
    )
    max_alternations: int = field(
        default=10,
        metadata={
            "doc": "Localize/calibrate alternations at most (from a coarse mount 20° off, "
            "quick.yaml's sphere 1 needs 9; an alternation that stops unconverged returns "
            "the mean of its estimates and its verdict says so).",
            "ge": 1,
            "le": 50,
        },
    )
    layout: Literal["estimated", "cad"] = field(
        default="estimated",
        metadata={
            "doc": "Multi-marker: 'estimated' fits the printed sphere layout with the CAD "
            "as its prior at the phantom's print tolerance (phantom."
            "tolerance_position_mm) and reports it; 'cad' takes the CAD layout as exact "
            "(the paper's loss)."
        },
    )
    mount_error_mm: float = field(
        default=0.0,
        metadata={
            "doc": "The rig's own error of the mount's position that no view shows, 1 σ "
            "per axis (mm): a holder bending under the probe's weight, the arm twisting "
            "differently under the touches' and the sweeps' loads, the localizer's bias on "
            "the phantom as printed. The same in every sweep, it moves T_ee_us as a whole "
            "and the residuals cannot show it; declared, it is a systematic term of the "
            "95 % bounds. `uscal budget` on the rig's twin measures it (its 'declare' "
            "line). 0 = none declared.",
            "ge": 0,
            "le": 50,
        },
    )
    mount_error_deg: float = field(
        default=0.0,
        metadata={
            "doc": "The rig's own error of the mount's orientation that no view shows, 1 σ "
            "per axis (degrees), about the image's origin; as mount_error_mm (`uscal "
            "budget` measures both). 0 = none declared.",
            "ge": 0,
            "le": 30,
        },
    )
    require_image_mm: float | None = field(
        default=None,
        metadata={
            "doc": "The calibration is accepted only if its 95 % bound over the image is at "
            "most this (mm); otherwise its verdict is 'rejected' and uscal run / calibrate "
            "exit with code 3 (also --require-image-mm). null = no requirement.",
            "gt": 0,
            "le": 1000,
        },
    )
    require_rotation_deg: float | None = field(
        default=None,
        metadata={
            "doc": "The calibration is accepted only if its 95 % rotation bound is at most "
            "this (degrees); as require_image_mm (also --require-rotation-deg).",
            "gt": 0,
            "le": 180,
        },
    )


@dataclass(frozen=True)
class Observation:
    """A localized sphere centre: ``p_us`` (3,) metres in the sweep's reference frame and
    the reported flange pose ``T_base_ee`` (4, 4) of that frame."""

    target: str
    pose_id: int
    p_us: Array
    T_base_ee: Array


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """An estimated ``T_ee_us`` and what it rests on.

    Attributes
    ----------
    T_ee_us : (4, 4) float
    T_base_phantom : (4, 4) float or None
        The phantom pose (two or more markers).
    retained : (n,) bool
        Observations kept (the rest rejected as outliers; ``rejection_reasons``).
    residuals_mm : (n,) float
        Distance of each reconstructed centre from its sphere's centroid.
    covariance : (6, 6) float
        Of (rotation vector in the ee frame, rad; translation, m) of ``T_ee_us``, from
        the Jacobian and the residuals' variance (first order).
    cost : float
        Final loss (mm²).
    layout : dict or None
        The estimated printed layout, sphere name → (3,) metres in the phantom frame
        (multi-marker with a print tolerance; None otherwise).
    layout_weight : float
        σ_loc / σ_tol of the layout prior (0: the CAD layout taken as exact).
    """

    T_ee_us: Array
    T_base_phantom: Array | None
    retained: NDArray[np.bool_]
    residuals_mm: Array
    covariance: Array
    cost: float
    rejection_reasons: dict[str, str] = field(default_factory=dict)
    layout: dict[str, Array] | None = None
    layout_weight: float = 0.0


def centres_in_base(obs: Sequence[Observation], T_ee_us: Array) -> Array:
    """Base-frame centres (n, 3) of observations under a calibration (paper Eq. 1)."""
    T = np.array([o.T_base_ee for o in obs]) @ T_ee_us
    P = np.array([o.p_us for o in obs])
    return np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3]


def centroid_distances_mm(
    obs: Sequence[Observation], T_ee_us: Array, keep: NDArray[np.bool_]
) -> Array:
    """(n,) distance (mm) of each reconstructed centre from its sphere's centroid over
    the ``keep`` observations (all of the sphere's where none is kept)."""
    X = centres_in_base(obs, T_ee_us)
    dist = np.zeros(len(obs))
    for s in dict.fromkeys(o.target for o in obs):
        idx = np.array([i for i, o in enumerate(obs) if o.target == s])
        centroid = X[idx[keep[idx]]].mean(axis=0) if keep[idx].any() else X[idx].mean(axis=0)
        dist[idx] = np.linalg.norm(X[idx] - centroid, axis=1) * _MM
    return dist


def linear_initialisation(obs: Sequence[Observation]) -> Array:
    """Closed-form ``T_ee_us`` from the common-point constraint, no prior needed.

    Each observation of sphere s gives ``R_k (R_X p_k + t_X) + t_k = c_s``: linear in
    ``vec(R_X)``, ``t_X`` and the unknown centres ``c_s``. The least-squares solution's
    rotation part is projected onto SO(3) (SVD) and the translation and centres are then
    re-solved with that rotation fixed.
    """
    targets = list(dict.fromkeys(o.target for o in obs))
    n_c = 3 * len(targets)
    A = np.zeros((3 * len(obs), 12 + n_c))
    b = np.zeros(3 * len(obs))
    for i, o in enumerate(obs):
        R, t = o.T_base_ee[:3, :3], o.T_base_ee[:3, 3]
        rows = slice(3 * i, 3 * i + 3)
        A[rows, 0:9] = np.kron(R, o.p_us[None, :])  # R · R_X · p, R_X row-major
        A[rows, 9:12] = R
        s = targets.index(o.target)
        A[rows, 12 + 3 * s : 15 + 3 * s] = -np.eye(3)
        b[rows] = -t
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    R_X = se3.nearest_rotation(sol[:9].reshape(3, 3))
    # Translation and centres again with the rotation fixed.
    b2 = b - A[:, 0:9] @ R_X.ravel()
    sol2, *_ = np.linalg.lstsq(A[:, 9:], b2, rcond=None)
    return se3.make(R_X, sol2[:3])


def consensus_initialisation(
    obs: Sequence[Observation], *, agree_mm: float = 5.0, trials: int = 200, seed: int = 0
) -> tuple[Array, NDArray[np.bool_]]:
    """Closed-form ``T_ee_us`` from the largest set of observations that agree, for
    localizations contaminated by wrong detections (RANSAC with a local optimisation
    step: Fischler & Bolles 1981; Chum et al. 2003).

    :func:`linear_initialisation` on all observations is a least-squares compromise
    between the sphere and whatever else was taken for it (a plate 20 mm away in half the
    sweeps) and can land far off, with the outlier stage then keeping a handful of
    accidental agreements. Here: the closed form on random minimal subsets (five sweeps
    per sphere, the fewest that fix it), each refitted on the observations that
    reconstruct within ``agree_mm`` of the centre the subset gives their sphere (a
    minimal subset's rotation is rough: a degree moves a centre 50 mm from the flange by
    almost a millimetre) and scored by how many agree then. Returns the best closed form and its
    agreeing set. Seeded: the same observations give the same start.
    """
    targets = list(dict.fromkeys(o.target for o in obs))
    groups = [np.array([i for i, o in enumerate(obs) if o.target == t]) for t in targets]
    groups = [g for g in groups if len(g) >= 5]
    if not groups:
        raise CalibrationError("calibration needs at least 5 localized sweeps of a sphere")
    rng = np.random.default_rng(seed)

    def agreeing(T: Array, members: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], float]:
        """Observations within agree_mm of the centre their sphere's ``members`` give."""
        X = centres_in_base(obs, T)
        ok = np.zeros(len(obs), dtype=bool)
        spread = 0.0
        for g in groups:
            d = np.linalg.norm(X[g] - X[g][members[g]].mean(axis=0), axis=1) * _MM
            ok[g] = d <= agree_mm
            spread += float(np.sum(np.minimum(d, agree_mm)))
        return ok, spread

    best_T, best_ok, best_key = None, np.zeros(len(obs), dtype=bool), (-1, 0.0)
    for _ in range(trials):
        ok = np.zeros(len(obs), dtype=bool)
        ok[np.concatenate([rng.choice(g, 5, replace=False) for g in groups])] = True
        T = linear_initialisation([o for o, k in zip(obs, ok, strict=True) if k])
        ok, spread = agreeing(T, ok)
        for _ in range(3):  # local optimisation: refit on the agreeing set
            if any(ok[g].sum() < 5 for g in groups):
                break
            T_new = linear_initialisation([o for o, k in zip(obs, ok, strict=True) if k])
            ok_new, spread_new = agreeing(T_new, ok)
            if (ok_new.sum(), -spread_new) <= (ok.sum(), -spread):
                break
            T, ok, spread = T_new, ok_new, spread_new
        key = (int(ok.sum()), -spread)
        if key > best_key:
            best_T, best_ok, best_key = T, ok, key
    if best_T is None or best_ok.sum() < 4:
        raise CalibrationError("no 4 localized sweeps agree on one sphere centre")
    return best_T, best_ok


def _params_to_T(x: Array, T0: Array) -> Array:
    return se3.exp(x) @ T0


def calibrate(
    obs: Sequence[Observation],
    cad_centres: Mapping[str, Array] | None = None,
    *,
    T_init: Array | None = None,
    outlier_mm: float = 2.0,
    layout_sigma_mm: float = 0.0,
    first_fit: NDArray[np.bool_] | None = None,
) -> CalibrationResult:
    """Estimate ``T_ee_us`` from localized sphere centres.

    Parameters
    ----------
    obs : observations of one (single-marker) or several (multi-marker) spheres
    cad_centres : sphere name → (3,) metres in the phantom frame; used (with the phantom
        pose as an unknown) when two or more spheres are observed
    T_init : starting calibration; None uses :func:`linear_initialisation`
    outlier_mm : an observation farther than ``max(outlier_mm, 3·1.4826·MAD)`` from its
        sphere's centroid after a robust fit is rejected, and the fit repeated without it
    layout_sigma_mm : the phantom's print tolerance (1 σ per axis of a sphere centre):
        with two or more markers the printed layout is estimated with the CAD as its
        prior (module docstring); 0 takes the CAD layout as exact
    first_fit : the observations the first fit uses (default all), e.g. the agreeing set
        of :func:`consensus_initialisation`; the outlier stage then re-admits every
        observation within its limit

    Raises
    ------
    CalibrationError
        Too few observations, or a degenerate problem.

    Examples
    --------
    One sphere seen from twelve flange poses, its centres localized to 10 µm (1 σ): the
    single-marker fit recovers the mount to a few hundredths of a degree and of a
    millimetre.

    >>> from calib import se3
    >>> rng = np.random.default_rng(0)
    >>> T_ee_us = se3.make(se3.matrix_from_rotvec([0.0, 0.0, np.pi / 2]), [0.0, 0.01, 0.1])
    >>> centre = np.array([0.3, 0.0, 0.05])
    >>> obs = []
    >>> for i in range(12):
    ...     T_base_ee = se3.make(
    ...         se3.matrix_from_rotvec(rng.normal(0, 0.2, 3)),
    ...         centre + [0.0, 0.0, 0.15] + rng.normal(0, 0.005, 3),
    ...     )
    ...     p_us = se3.apply(se3.invert(T_base_ee @ T_ee_us), centre)
    ...     obs.append(Observation("sphere_1", i, p_us + rng.normal(0, 1e-5, 3), T_base_ee))
    >>> result = calibrate(obs)
    >>> round(float(np.degrees(se3.rotation_angle(result.T_ee_us, T_ee_us))), 2)
    0.03
    >>> round(float(se3.translation_distance(result.T_ee_us, T_ee_us)) * 1e3, 2)
    0.08
    """
    obs = list(obs)
    targets = list(dict.fromkeys(o.target for o in obs))
    if len(obs) < 4:
        raise CalibrationError(f"calibration needs at least 4 localized sweeps, got {len(obs)}")
    se3.check([o.T_base_ee for o in obs], "the observations' flange poses T_base_ee", batch=True)
    if T_init is not None:
        se3.check(T_init, "T_init")
    multi = len(targets) >= 2 and cad_centres is not None
    T0 = linear_initialisation(obs) if T_init is None else np.asarray(T_init, dtype=float)
    keep = np.ones(len(obs), dtype=bool) if first_fit is None else np.array(first_fit, bool)
    if keep.shape != (len(obs),) or keep.sum() < 4:
        raise CalibrationError("the first fit needs at least 4 of the observations")
    reasons: dict[str, str] = {}
    if layout_sigma_mm < 0:
        raise ValueError(f"layout_sigma_mm must be ≥ 0, got {layout_sigma_mm}")
    weight = 0.0
    for _ in range(5):
        kept = [o for o, k in zip(obs, keep, strict=True) if k]
        if multi and layout_sigma_mm > 0:
            weight = _localization_sigma_mm(kept, targets, T0) / layout_sigma_mm
        sol, T_base_phantom = _solve(kept, targets, cad_centres if multi else None, T0, weight)
        T_X = _params_to_T(sol.x[:6], T0)
        dist = centroid_distances_mm(obs, T_X, keep)
        limit = outlier_limit(dist[keep], outlier_mm)
        new_keep = dist <= limit
        for i in np.flatnonzero(keep & ~new_keep):
            reasons[f"{obs[i].target}/{obs[i].pose_id}"] = (
                f"{obs[i].target} sweep {obs[i].pose_id}: {dist[i]:.2f} mm from the centroid "
                f"(limit {limit:.2f} mm)"
            )
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
        T0 = T_X
        if keep.sum() < 4:
            raise CalibrationError("fewer than 4 sweeps left after outlier rejection")
    J = sol.jac  # residuals in mm per (m, rad) of the se(3) increment (ρ, ω), then Y, δ
    dof = max(len(sol.fun) - len(sol.x), 1)
    sigma2 = 2 * sol.cost / dof  # mm², so the covariance below is in m² and rad²
    try:
        # Marginal over the phantom pose and layout (they are estimated too).
        cov = np.linalg.inv(J.T @ J)[:6, :6] * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    # The increment acts on the left, T = exp(ρ, ω) T_X: to first order the rotation
    # vector is ω (ee frame) and the translation changes by ρ + ω × t = ρ − [t]× ω.
    t = T_X[:3, 3]
    t_hat = se3.hat(t)
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)  # rotation vector ← ω
    A[3:, :3] = np.eye(3)  # translation ← ρ
    A[3:, 3:] = -t_hat  # … − [t]× ω
    cov = A @ cov @ A.T
    layout = None
    if multi and weight > 0:
        names = [
            t for t in targets if any(o.target == t for o, k in zip(obs, keep, strict=True) if k)
        ]
        delta = sol.x[12:].reshape(-1, 3)
        layout = {
            t: np.asarray(cad_centres[t], dtype=float) + d
            for t, d in zip(names, delta, strict=True)
        }
    return CalibrationResult(
        T_X,
        T_base_phantom,
        keep,
        dist,
        cov,
        float(2 * sol.cost),
        reasons,
        layout,
        weight,
    )


def _localization_sigma_mm(obs, targets, T0) -> float:
    """σ_loc: 1 σ per axis (mm) of the localized centres about their sphere, from the
    fit of the first term alone (every sphere free; it needs no layout)."""
    sol, _ = _solve(obs, targets, None, T0)
    n_s = len({o.target for o in obs})
    dof = max(3 * len(obs) - 3 * n_s - 6, 1)
    return float(np.sqrt(2 * sol.cost / dof))


def _solve(obs, targets, cad_centres, T0, layout_weight: float = 0.0):
    """One TRF solve of the paper's loss; parameters: se(3) increment of X (6), then the
    phantom pose (6) when markers' CAD geometry is used, then the per-sphere misprints δ
    (3 each, metres, phantom frame) when ``layout_weight`` (σ_loc / σ_tol) > 0."""
    T_b = np.array([o.T_base_ee for o in obs])
    P = np.array([o.p_us for o in obs])
    groups = [np.array([i for i, o in enumerate(obs) if o.target == s]) for s in targets]
    groups = [g for g in groups if len(g)]
    multi = cad_centres is not None
    floating = multi and layout_weight > 0
    if multi:
        C_cad = np.array([cad_centres[obs[g[0]].target] for g in groups])

    def residuals(x: Array) -> Array:
        T_X = se3.exp(x[:6]) @ T0
        T = T_b @ T_X
        X = np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3]
        res = []
        means = []
        for g in groups:
            m = X[g].mean(axis=0)
            means.append(m)
            res.append((X[g] - m).ravel())
        if multi:
            Y = se3.exp(x[6:12])
            delta = x[12:].reshape(-1, 3) if floating else 0.0
            C = se3.apply(Y, C_cad + delta)
            for g, m, c in zip(groups, means, C, strict=True):
                res.append(np.sqrt(len(g)) * (m - c))
            if floating:
                res.append(layout_weight * x[12:])  # the CAD layout as a prior
        return np.concatenate(res) * _MM

    x0 = np.zeros(6 + 6 * multi + 3 * len(groups) * floating)
    if multi:
        # Phantom pose start: align the CAD centres to the centroids under T0 (Kabsch).
        X0 = centres_in_base(obs, T0)
        centroids = np.array([X0[g].mean(axis=0) for g in groups])
        x0[6:12] = se3.log(se3.kabsch(C_cad, centroids))
    sol = least_squares(residuals, x0, method="trf", x_scale="jac")
    T_base_phantom = se3.exp(sol.x[6:12]) if multi else None
    return sol, T_base_phantom
