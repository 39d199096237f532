"""A verdict with every calibration: ``accepted``, ``suspect`` or ``rejected``, each with
its reasons in one line a user can act on.

The pipeline already holds the evidence; a calibration is judged on these questions:

- **Did the alternation settle?** (paper §III-F: localize, calibrate, re-stack, until the
  estimate stops changing.) Its last update is compared with the estimate's own 95 %
  bound: an update of a quarter of the bound or more means the answer depends on where
  the iteration stopped.
- **Do the sweeps agree as localization noise predicts?** The retained centres of one
  sphere, mapped to the base through the arm and ``T_ee_us`` (paper Eq. 1), scatter by
  the localizer's noise within a view (the sweeps taken at one flange orientation) and,
  if the arm's kinematic model or the pose is off, by a pose-dependent error between
  views. A one-way random-effects analysis of variance per axis (views as groups)
  separates the two: the between-view component ``σ_b`` against the within-view scatter
  ``σ_w``. Where ``σ_b`` is significant (F test, 0.1 % level over every sphere and axis),
  larger than ``σ_w`` and than half a millimetre (rss over the axes), the poses, not the
  images, dominate the error, and the fit cannot show how far off its answer is: the
  bound, made from the same centres, shrinks with their number while a kinematic error
  does not.
- **Is the sphere the size it was said to be?** The cap's section in the frame through
  each centre gives the radius the images draw (:func:`calib.localize.
  apparent_sphere_radius`); a radius given wrong puts every centre off along its beam by
  the difference, an error the residuals cannot show. A printed sphere out of round draws
  its cap's own curvature instead (0.1 mm rms reads up to ≈ 0.5 mm off the radius), and
  its centre is off along the beam by the cap's own error: the reason names both.
- **Is the image's scale the one assumed?** ``T_ee_us`` refitted with the lateral and
  axial scale free (:func:`image_scale`): a pixel spacing the scanner reports wrong, or
  a speed of sound not corrected, shows as a scale off by more than 1 % and three
  standard errors. The scale is read from how the centres move with the flange, so an
  arm model that errs smoothly with the configuration reads as a scale too: a refined
  model's own error (the modes the bound carries) adds to the standard errors.
- **Do the data determine ``T_ee_us`` at all?** Sweeps from fewer than two distinct
  flange orientations, or an estimate whose 95 % bound is beyond 10° or 10 mm (where a
  first-order bound no longer describes the error, and the coarse mount from the CAD is
  as good: views too alike, or views that disagree), are rejected: the answer is
  whatever the fit stopped at.
- **Did the sweeps run along the image normal where the caps are shallow?** A sweep
  tilted towards depth off the image normal (the coarse mount it was planned through is
  off) moves a cap's depth from frame to frame; within about 14 mm of the face, where
  the cap's echo brightens fast with depth, that moves the elevation the localizer
  reads, by up to 0.1 mm a sweep, most for the shallowest caps: the centres' elevation
  errors then follow their depth, a rotation of ``T_ee_us`` about the image's lateral
  axis that no residual and so no bound shows. Such a single scan is suspect; a second
  scan along the calibrated normal removes it (:class:`SweepGeometry`).
- **Were enough centres kept?** A fit that drops more than a tenth of the localizer's
  centres as outliers saw errors that are not the noise it assumes (false detections,
  or poses that disagree).
- **Is it as good as the user asked?** ``require_image_mm`` / ``require_rotation_deg``
  against the 95 % bound: a bound above either (or none computed) rejects it. Without a
  requirement, a bound over the image above 1 mm makes it suspect: ``accepted`` means
  known to the millimetre.

The thresholds are stated once, below, each with its reason: a quarter of the bound (an
iteration's leftover motion well inside the estimate's own uncertainty), pose scatter
above the localizer's and above half a millimetre at a 0.1 % significance level, a radius
0.4 mm off, a scale 1 % and three standard errors off, sweeps 2.5° off the normal in
depth about caps within 14 mm of the face, a tenth of the centres, a millimetre of
bound.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

# The F distribution's survival function as scipy.stats computes it (f.sf is fdtrc),
# without importing scipy.stats (≈ 0.5 s a process).
from scipy.special import fdtrc

from .. import se3
from ..acquisition.protocol import sweep_axis_off_normal
from ..records import Sweep
from .alternation import AlternationResult, AlternationSettings
from .markers import centres_in_base
from .uncertainty import Bound95, modes_at, moved_by_modes, orientation_groups

__all__ = [
    "BoundFigures",
    "ImageScale",
    "PoseAgreement",
    "Requirements",
    "SweepGeometry",
    "Verdict",
    "image_scale",
    "judge",
    "pose_agreement",
    "sweep_geometry",
]

Array = NDArray[np.float64]
Status = Literal["accepted", "suspect", "rejected"]
_MM = 1e3


@dataclass(frozen=True)
class BoundFigures:
    """A 95 % bound's three figures, as ``metrics.json``'s ``bound95`` keeps them (where
    the :class:`calib.calibration.uncertainty.Bound95` itself was made elsewhere)."""

    rotation_deg: float
    translation_mm: float
    image_mm: float

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> BoundFigures:
        return cls(float(d["rotation_deg"]), float(d["translation_mm"]), float(d["image_mm"]))


#: The alternation has settled when its last update is below this share of the bound
#: (a stop that far from the fixed point adds at most ≈ 3 % to the bound in quadrature).
SETTLED_SHARE_OF_BOUND = 0.25
#: Significance level of the between-view scatter (over every sphere and axis together).
POSE_SIGNIFICANCE = 1e-3
#: Pose-dependent scatter (rss, mm) that matters: points mapped through the arm and the
#: calibration then disagree across poses by more than the half millimetre the method is
#: for (the paper's sub-millimetre claim); below it a small kinematic error is part of
#: the noise its bound already carries through the jackknife over views.
POSE_SCATTER_MM = 0.5
#: The sphere's radius as the images draw it may differ from the one given by this (mm):
#: the estimate (the cap's half-amplitude edge) reads −0.07 to +0.17 mm off on the twin
#: over 16 conditions of gain, depth and radius (:func:`calib.localize.refine.
#: apparent_radius`), so a radius given 0.5 mm or more off shows, a scale error of a few
#: per cent does not.
RADIUS_MISMATCH_MM = 0.4
#: The images' scale (lateral, axial) may differ from the one assumed by this share, and
#: by three of its standard errors: at the 25–40 mm the spheres are imaged, 1 % moves a
#: centre 0.25–0.4 mm along the beam, the size of the localizer's noise.
SCALE_MISMATCH = 0.01
#: A single scan whose sweeps ran this far (median, degrees) off the calibrated image
#: normal towards depth, about caps whose tops lie (median) less than ``SHALLOW_CAPS_M``
#: under the face, is suspect. Measured on the twin (quick.yaml's rig, 62 single- and
#: three-marker calibrations at 10-18 mm targets, 47 at 20-40 mm; each its own seed):
#: accepted single scans there fell outside their 95 % bounds 12 times, 11 of them with
#: the sweeps 2.6-10° off in depth, none with the caps 15 mm or deeper; the thresholds
#: set from those, then checked on 72 calibrations of 37 more seeds with the probe's
#: frequency (9-13 MHz), lens (3-5 mm, focus 14-30 mm) and the spheres' radius
#: (3.5-6.5 mm) drawn at random: 9 of the 39 they make suspect fell outside their bounds,
#: none of the 33 they leave accepted. Measured for these linear probes and printed
#: spheres; another probe's near field may reach deeper.
TILTED_SWEEP_DEG = 2.5
SHALLOW_CAPS_M = 14e-3
#: A fit dropping more than this share of the localizer's centres is suspect.
MAX_DROPPED_SHARE = 0.1
#: Beyond these 95 % bounds a calibration has learnt nothing a CAD drawing would not
#: tell (a holder's drawing places the probe to a few millimetres and degrees), and a
#: first-order bound no longer describes the error: rejected.
UNDETERMINED_DEG = 10.0
UNDETERMINED_MM = 10.0
#: Without a requirement of the user's, ``accepted`` means known to this (95 % bound over
#: the image, mm): a bound above it is suspect (the data do not pin the mount down).
DEFAULT_IMAGE_MM = 1.0


@dataclass(frozen=True)
class Requirements:
    """What the user asked of the calibration (None: not asked): its 95 % bound over the
    image (mm) and in rotation (degrees) at most this."""

    image_mm: float | None = None
    rotation_deg: float | None = None

    def __post_init__(self) -> None:
        for name, value in (("image_mm", self.image_mm), ("rotation_deg", self.rotation_deg)):
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ValueError(f"required {name} must be a positive number, got {value!r}")

    @property
    def any(self) -> bool:
        return self.image_mm is not None or self.rotation_deg is not None


@dataclass(frozen=True)
class PoseAgreement:
    """How the retained centres of each sphere scatter in the base frame: within views
    (``within_mm``, per axis, pooled over the spheres) and between them (``between_mm``,
    the random-effects component, per axis), the smallest F-test p-value over spheres and
    axes (Bonferroni-corrected) and the views the analysis had."""

    within_mm: Array
    between_mm: Array
    p_value: float
    views: int

    @property
    def within_rss_mm(self) -> float:
        return float(np.sqrt(np.sum(self.within_mm**2)))

    @property
    def between_rss_mm(self) -> float:
        return float(np.sqrt(np.sum(self.between_mm**2)))

    @property
    def disagree(self) -> bool:
        """The pose-dependent scatter is significant, larger than the localizer's and
        larger than :data:`POSE_SCATTER_MM`."""
        return (
            self.p_value < POSE_SIGNIFICANCE
            and self.between_rss_mm > self.within_rss_mm
            and self.between_rss_mm > POSE_SCATTER_MM
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "within_view_mm": [round(float(v), 4) for v in self.within_mm],
            "between_view_mm": [round(float(v), 4) for v in self.between_mm],
            "p_value": self.p_value,
            "views": self.views,
        }


@dataclass(frozen=True)
class ImageScale:
    """The scale of the images (lateral, axial) against the one the pipeline assumed
    (1 = as assumed), fitted with ``T_ee_us`` and the spheres' centres, and its
    standard errors: ``lateral_se`` / ``axial_se`` in all, of which ``lateral_se_arm`` /
    ``axial_se_arm`` the arm model's own error carried through the fit (0: none
    declared)."""

    lateral: float
    axial: float
    lateral_se: float
    axial_se: float
    lateral_se_arm: float = 0.0
    axial_se_arm: float = 0.0

    def off(self) -> list[tuple[str, float, float]]:
        """The axes whose scale is off by more than :data:`SCALE_MISMATCH` and three
        standard errors: (name, per cent, its standard error in per cent)."""
        out = []
        for name, s, se in (
            ("laterally", self.lateral, self.lateral_se),
            ("in depth", self.axial, self.axial_se),
        ):
            if abs(s - 1.0) > max(SCALE_MISMATCH, 3.0 * se):
                out.append((name, 100.0 * (s - 1.0), 100.0 * se))
        return out

    def as_dict(self) -> dict[str, float]:
        out = {
            "lateral": round(self.lateral, 5),
            "axial": round(self.axial, 5),
            "lateral_se": round(self.lateral_se, 5),
            "axial_se": round(self.axial_se, 5),
        }
        if self.lateral_se_arm or self.axial_se_arm:
            out["lateral_se_arm"] = round(self.lateral_se_arm, 5)
            out["axial_se_arm"] = round(self.axial_se_arm, 5)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> ImageScale:
        return cls(
            float(d["lateral"]),
            float(d["axial"]),
            float(d["lateral_se"]),
            float(d["axial_se"]),
            float(d.get("lateral_se_arm", 0.0)),
            float(d.get("axial_se_arm", 0.0)),
        )


def image_scale(
    alt: AlternationResult, kinematic_modes: Mapping[tuple[str, int], Array] | None = None
) -> ImageScale | None:
    """:class:`ImageScale` of a calibration's retained centres: ``T_ee_us`` refitted with
    the image's lateral and axial scale free (``P_base = T_base_ee T_ee_us diag(s_x, s_y,
    1) p_us``, each sphere's centre free: the similarity PLUS's ImageToProbe allows), the
    scales' standard errors from the fit's Jacobian and residuals. The protocol's
    in-plane offsets and tilts make the scale observable: on the twin's quick.yaml to
    ± 0.2–0.4 %. None with too few centres.

    The scale is read from how the centres move with the flange's position and tilt, and
    an arm whose model errs smoothly with its configuration moves them alike: on the
    paper's rig (its DH model refined from touches) the arm's errors alone read 1.35 %
    in depth where the images' scale is right. ``kinematic_modes`` (the refined model's
    own error at the sweeps' poses, :func:`calib.kinematics.kinematic_modes`, as the 95 %
    bound takes it) are carried through the fit to first order and add to the standard
    errors in quadrature, as they add to the bound's first order: where the arm's model
    is that uncertain, a scale reading as far off is no evidence against the spacing."""
    keep = alt.result.retained
    obs = [o for o, k in zip(alt.observations, keep, strict=True) if k]
    targets = list(dict.fromkeys(o.target for o in obs))
    n_params = 8 + 3 * len(targets)
    if 3 * len(obs) <= n_params + 3:
        return None
    sphere = np.array([targets.index(o.target) for o in obs])
    T0 = alt.result.T_ee_us
    T_base_ee = np.array([o.T_base_ee for o in obs])
    p_us = np.array([o.p_us for o in obs])

    def centres(x: Array) -> Array:
        T = T_base_ee @ (T0 @ se3.exp(x[:6]))
        P = p_us * np.array([x[6], x[7], 1.0])
        return np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3]

    start = centres(np.r_[np.zeros(6), 1.0, 1.0])
    c0 = np.array([start[sphere == k].mean(axis=0) for k in range(len(targets))])

    def residuals(x: Array) -> Array:  # mm
        return ((centres(x) - x[8:].reshape(-1, 3)[sphere]) * _MM).ravel()

    x0 = np.r_[np.zeros(6), 1.0, 1.0, c0.ravel()]
    scale = np.r_[np.full(6, 1e-3), 0.01, 0.01, np.full(c0.size, 1e-3)]
    fit = least_squares(residuals, x0, x_scale=scale)
    dof = len(fit.fun) - len(x0)
    JtJ_inv = np.linalg.pinv(fit.jac.T @ fit.jac)
    cov = JtJ_inv * float(fit.fun @ fit.fun) / dof
    se = np.sqrt(np.clip(np.diag(cov)[6:8], 0.0, None))
    arm = np.zeros(2)
    if kinematic_modes is not None:
        # Each mode moves every centre (metres, (n, k, 3)); the residuals' columns are
        # those moves (mm), and dx = −(JᵀJ)⁻¹ Jᵀ D the fit's answer to them.
        moved = moved_by_modes(modes_at(obs, kinematic_modes), se3.apply(T0, p_us))
        D = moved.transpose(0, 2, 1).reshape(-1, moved.shape[1]) * _MM
        dx = -(JtJ_inv @ fit.jac.T @ D)[6:8]
        arm = np.sqrt(np.sum(dx**2, axis=1))
    total = np.hypot(se, arm)
    return ImageScale(
        float(fit.x[6]),
        float(fit.x[7]),
        float(total[0]),
        float(total[1]),
        float(arm[0]),
        float(arm[1]),
    )


@dataclass(frozen=True)
class SweepGeometry:
    """How a calibration's sweeps met its spheres: ``in_depth_deg`` the kept sweeps'
    median tilt towards depth off the calibrated image normal
    (:func:`calib.acquisition.protocol.sweep_axis_off_normal`) and ``cap_depth_m`` the
    median depth of the caps' tops under the face (the kept centres' depth less the
    radius)."""

    in_depth_deg: float
    cap_depth_m: float

    def as_dict(self) -> dict[str, float]:
        """As ``metrics.json`` keeps it (degrees, mm)."""
        return {"in_depth_deg": self.in_depth_deg, "cap_depth_mm": self.cap_depth_m * _MM}

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> SweepGeometry:
        return cls(float(d["in_depth_deg"]), float(d["cap_depth_mm"]) / _MM)

    @property
    def tilted_over_shallow_caps(self) -> bool:
        return bool(
            abs(self.in_depth_deg) >= TILTED_SWEEP_DEG and self.cap_depth_m < SHALLOW_CAPS_M
        )


def sweep_geometry(
    alt: AlternationResult, sweeps: Sequence[Sweep], radius: float
) -> SweepGeometry | None:
    """The :class:`SweepGeometry` of a calibration of spheres of ``radius`` (m) from
    ``sweeps`` (those of its dataset; the ones it kept are read); None without a kept
    centre or a sweep that moved."""
    kept = {
        (o.target, o.pose_id): o.p_us
        for o, k in zip(alt.observations, alt.result.retained, strict=True)
        if k
    }
    used = [s for s in sweeps if (s.target, s.pose_id) in kept]
    if not used:
        return None
    tilt = sweep_axis_off_normal(used, alt.result.T_ee_us)["in_depth_deg"]
    if not np.isfinite(tilt):
        return None
    caps = float(np.median([p[1] for p in kept.values()])) - radius
    return SweepGeometry(float(tilt), caps)


@dataclass(frozen=True)
class Verdict:
    """``status`` and its ``reasons`` (one line each, what to do about it), with the
    evidence: whether the alternation ``settled`` (its last update, mm and degrees), the
    centres the fit kept of those the localizer gave, the pose agreement, and the bound
    against the requirements."""

    status: Status
    reasons: tuple[str, ...]
    settled: bool
    last_update: tuple[float, float]
    kept: tuple[int, int]
    agreement: PoseAgreement | None
    requirements: Requirements = Requirements()
    radius_mm: tuple[float, float] | None = None  # given, as the images draw it
    scale: ImageScale | None = None
    averaged: int = 0  # not converged: the estimates averaged before the final fit

    def line(self) -> str:
        """One line: the status and its reasons."""
        return self.status + (": " + "; ".join(self.reasons) if self.reasons else "")

    def as_dict(self) -> dict[str, Any]:
        """``metrics.json``'s ``verdict`` of a calibration."""
        out: dict[str, Any] = {
            "status": self.status,
            "reasons": list(self.reasons),
            "settled": self.settled,
            "last_update_mm": self.last_update[0],
            "last_update_deg": self.last_update[1],
            "kept": self.kept[0],
            "localized": self.kept[1],
        }
        if self.averaged:
            out["averaged_estimates"] = self.averaged
        if self.agreement is not None:
            out["pose_agreement"] = self.agreement.as_dict()
        if self.radius_mm is not None:
            out["radius_given_mm"], out["radius_seen_mm"] = self.radius_mm
        if self.scale is not None:
            out["image_scale"] = self.scale.as_dict()
        if self.requirements.any:
            out["required"] = {
                "image_mm": self.requirements.image_mm,
                "rotation_deg": self.requirements.rotation_deg,
            }
        return out


def pose_agreement(alt: AlternationResult) -> PoseAgreement | None:
    """:class:`PoseAgreement` of a calibration's retained centres; None with fewer than
    two views of any sphere that holds two centres in one view (nothing to compare)."""
    obs, keep = alt.observations, alt.result.retained
    if not keep.any():
        return None
    P = centres_in_base(obs, alt.result.T_ee_us) * _MM
    views = orientation_groups(obs)
    targets = np.array([o.target for o in obs])
    ss_within = np.zeros(3)
    df_within = 0
    between: list[Array] = []
    weights: list[int] = []
    p_values: list[float] = []
    n_views = 0
    for t in dict.fromkeys(targets):
        m = keep & (targets == t)
        g = views[m]
        labels, counts = np.unique(g, return_counts=True)
        if len(labels) < 2 or len(g) <= len(labels):
            continue
        X = P[m]
        means = np.array([X[g == u].mean(axis=0) for u in labels])
        resid = X - means[np.searchsorted(labels, g)]
        ssw = np.sum(resid**2, axis=0)
        dfw = len(g) - len(labels)
        ssb = np.sum(counts[:, None] * (means - X.mean(axis=0)) ** 2, axis=0)
        dfb = len(labels) - 1
        msw, msb = ssw / dfw, ssb / dfb
        # Random-effects variance component: (MSB − MSW) / n0, n0 the effective group size.
        n0 = (len(g) - np.sum(counts**2) / len(g)) / dfb
        between.append(np.maximum(msb - msw, 0.0) / n0)
        weights.append(dfb)
        with np.errstate(divide="ignore", invalid="ignore"):
            F = np.where(msw > 0, msb / msw, np.inf)
        p_values.extend(float(fdtrc(dfb, dfw, f)) if np.isfinite(f) else 0.0 for f in F)
        ss_within += ssw
        df_within += dfw
        n_views = max(n_views, len(labels))
    if not p_values:
        return None
    within = np.sqrt(ss_within / df_within)
    between_sd = np.sqrt(np.average(np.array(between), axis=0, weights=weights))
    p = min(1.0, min(p_values) * len(p_values))  # Bonferroni over spheres and axes
    return PoseAgreement(within, between_sd, p, n_views)


def _bound_scale(
    alt: AlternationResult, bound: Bound95 | BoundFigures | None
) -> tuple[float, float]:
    """The estimate's own uncertainty (mm, degrees) the last update is compared with:
    its 95 % bound, else twice the first-order 1 σ (rss over the axes)."""
    if bound is not None:
        return bound.translation_mm, bound.rotation_deg
    sd = np.sqrt(np.clip(np.diag(alt.result.covariance), 0.0, None))
    return 2.0 * float(np.linalg.norm(sd[3:])) * _MM, 2.0 * float(
        np.degrees(np.linalg.norm(sd[:3]))
    )


def judge(
    alt: AlternationResult,
    bound: Bound95 | BoundFigures | None = None,
    requirements: Requirements | None = None,
    *,
    geometry: SweepGeometry | None = None,
    kinematic_modes: Mapping[tuple[str, int], Array] | None = None,
    scale: ImageScale | None = None,
    tol_mm: float = AlternationSettings.tol_mm,
    tol_deg: float = AlternationSettings.tol_deg,
) -> Verdict:
    """The verdict on one calibration (see the module's questions). ``geometry``: how its
    sweeps met the spheres (:func:`sweep_geometry`; None: not asked).
    ``kinematic_modes``: the refined arm model's own error at the sweeps' poses (as the
    bound's :class:`calib.calibration.uncertainty.UncertaintyInputs` holds it; None: the
    controller's model, none declared), which the scale's standard errors carry
    (:func:`image_scale`); ``scale``: that image scale when it was computed already
    (e.g. where the modes were). ``tol_mm`` / ``tol_deg``: the alternation's own
    tolerances (an update below both has converged whatever the bound)."""
    requirements = requirements or Requirements()
    suspect: list[str] = []
    rejected: list[str] = []
    last = alt.history[-1] if alt.history else {}
    d_mm = float(last.get("change_mm", 0.0))
    d_deg = float(last.get("change_deg", 0.0))
    if len(alt.history) <= 1:
        d_mm = d_deg = 0.0  # one fit, no update (e.g. localizations handed in as final)
    scale_mm, scale_deg = _bound_scale(alt, bound)
    settled = (d_mm <= tol_mm and d_deg <= tol_deg) or (
        d_mm <= SETTLED_SHARE_OF_BOUND * scale_mm and d_deg <= SETTLED_SHARE_OF_BOUND * scale_deg
    )
    if not settled:
        kept = (
            f"T_ee_us is the mean of its last {alt.averaged} estimates, which moved by that "
            "much between iterations"
            if alt.averaged
            else "the answer depends on where the alternation stopped"
        )
        suspect.append(
            f"did not converge: its last update moved T_ee_us by {d_mm:.2f} mm / "
            f"{d_deg:.2f}° (more than a quarter of its bound, {scale_mm:.2f} mm / "
            f"{scale_deg:.2f}°); {kept} — check the localizations (rejections, the sphere "
            "profile) or use the refined localizer"
        )
    if alt.lost_on_restack:
        rejected.append(
            f"re-stacked under its own estimate the sweeps no longer showed the sphere "
            f"({alt.lost_on_restack}): the estimate is far off and the alternation stopped "
            "there"
        )
    agreement = pose_agreement(alt)
    if agreement is not None and agreement.disagree:
        suspect.append(
            f"the sweeps disagree by {agreement.between_rss_mm:.2f} mm between views "
            f"where localization explains {agreement.within_rss_mm:.2f} mm within them: "
            "the arm's kinematic model (or the poses it reports) is likely off; refine it "
            "from touches, or check the robot's calibration"
        )
    if alt.sphere_size is not None:
        given, seen, n_seen = alt.sphere_size
        if abs(seen - given) * _MM > RADIUS_MISMATCH_MM:
            suspect.append(
                f"the images draw the sphere {seen * _MM:.2f} mm in radius where "
                f"{given * _MM:g} mm was given (over {n_seen} sweeps): check the radius "
                "(phantom.sphere_radius_mm or the dataset's), the pixel spacing and the speed "
                "of sound — a radius given wrong puts every centre off along its beam by the "
                "difference; a printed sphere out of round by a tenth of a millimetre draws "
                "its cap as much as half a millimetre off its radius too, and its centre "
                "off along the beam by its cap's own error"
            )
    if scale is None:
        scale = image_scale(alt, kinematic_modes)
    if scale is not None and scale.off():
        parts = " and ".join(f"{p:+.1f} % {name} (± {se:.1f} %)" for name, p, se in scale.off())
        suspect.append(
            f"the images' scale looks off: {parts} against the pixel spacing and speed of "
            "sound assumed; check the spacing the scanner reports and the speed-of-sound "
            "correction (imaging.sound_speed_correction, the medium's temperature)"
        )
    if geometry is not None and geometry.tilted_over_shallow_caps:
        suspect.append(
            f"its sweeps ran {geometry.in_depth_deg:+.1f}° off the calibrated image normal "
            f"towards depth with the caps' tops {geometry.cap_depth_m * _MM:.1f} mm under "
            "the face: there a sweep's tilt moves the elevation the localizer reads (the "
            "cap's echo changes with its depth from frame to frame), a rotation of T_ee_us "
            "about the image's lateral axis that its bound cannot show — scan again along "
            "the calibrated normal (protocol.second_pass; on a rig, a second acquisition "
            "with this calibration as the coarse mount), or image the spheres deeper"
        )
    kept = [o for o, k in zip(alt.observations, alt.result.retained, strict=True) if k]
    views = len(np.unique(orientation_groups(kept))) if kept else 0
    image_bound = bound.image_mm if bound is not None else None
    undetermined: list[str] = []
    if views < 2:
        undetermined.append(
            f"the kept sweeps were taken from {views} flange orientation"
            f"{'' if views == 1 else 's'}: the poses do not determine T_ee_us's rotation; "
            "add sweeps turned about other axes (uscal plan --optimize)"
        )
    elif scale_deg > UNDETERMINED_DEG or max(scale_mm, image_bound or 0.0) > UNDETERMINED_MM:
        # Why: the views disagree (said below) or, if they agree, they are too alike.
        disagree = agreement is not None and agreement.disagree
        undetermined.append(
            f"the data do not determine T_ee_us: its 95 % bound is {scale_deg:.1f}° / "
            f"{scale_mm:.1f} mm"
            + ("" if image_bound is None else f" ({image_bound:.1f} mm over the image)")
            + f", beyond {UNDETERMINED_DEG:g}° / {UNDETERMINED_MM:g} mm"
            + (
                ""
                if disagree
                else "; the sweeps' views are too alike — add sweeps turned about other "
                "axes (uscal plan --optimize)"
            )
        )
    n_kept = int(alt.result.retained.sum())
    n_given = len(alt.observations)
    if n_given and (n_given - n_kept) > MAX_DROPPED_SHARE * n_given:
        suspect.append(
            f"the fit dropped {n_given - n_kept} of the {n_given} localized centres as "
            "outliers (more than a tenth): false detections or disagreeing poses; look at "
            "the rejected sweeps' reasons"
        )
    if (
        requirements.image_mm is None
        and bound is not None
        and bound.image_mm > DEFAULT_IMAGE_MM
        and not undetermined
    ):
        suspect.append(
            f"its 95 % bound over the image, {bound.image_mm:.2f} mm, is above "
            f"{DEFAULT_IMAGE_MM:g} mm: the data and the errors declared do not pin T_ee_us "
            "down to the millimetre; acquire more sweeps or views, or state what you need "
            "(--require-image-mm)"
        )
    if requirements.any:
        if bound is None:
            rejected.append("no 95 % bound was computed to check the requirements against")
        else:
            if requirements.image_mm is not None and bound.image_mm > requirements.image_mm:
                rejected.append(
                    f"its 95 % bound over the image, {bound.image_mm:.2f} mm, is above the "
                    f"required {requirements.image_mm:g} mm: acquire more sweeps or views "
                    "(uscal plan --optimize)"
                )
            if (
                requirements.rotation_deg is not None
                and bound.rotation_deg > requirements.rotation_deg
            ):
                rejected.append(
                    f"its 95 % rotation bound, {bound.rotation_deg:.2f}°, is above the "
                    f"required {requirements.rotation_deg:g}°: acquire more sweeps or views"
                )
        if suspect:
            # A requirement is met only by an answer that can be trusted.
            rejected.append("not accepted, so not within the requirements")
    rejected = undetermined + rejected
    status: Status = "rejected" if rejected else "suspect" if suspect else "accepted"
    return Verdict(
        status,
        tuple(undetermined + suspect + rejected[len(undetermined) :]),
        settled,
        (d_mm, d_deg),
        (n_kept, n_given),
        agreement,
        requirements,
        None
        if alt.sphere_size is None
        else (round(alt.sphere_size[0] * _MM, 4), round(alt.sphere_size[1] * _MM, 4)),
        scale,
        alt.averaged,
    )
