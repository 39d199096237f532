"""The alternation of localization and calibration (paper §III-F, "Single-marker
calibration"): localize every sweep, calibrate, re-stack the sweeps with the new
``T_ee_us`` (which removes the shear a wrong calibration puts into the stack),
re-localize about the previous centres, until the estimate stops changing.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..errors import CalibrationError
from ..localize import (
    LocalizerConfig,
    SweepLocalization,
    apparent_sphere_radius,
    localize_sphere,
)
from ..records import Sweep
from .markers import (
    CalibrationResult,
    Observation,
    calibrate,
    centres_in_base,
    centroid_distances_mm,
    consensus_initialisation,
)

__all__ = ["AlternationResult", "AlternationSettings", "alternate"]

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class AlternationResult:
    """Calibration after alternating localization and calibration.

    ``history`` holds one entry per iteration: the estimate, its change from the previous
    one (mm, degrees) and the loss; ``localizations`` the final per-sweep results;
    ``sphere_size`` the radius the localizer was given and the one the first sphere's
    images draw (metres, :func:`calib.localize.apparent_sphere_radius`) with the sweeps
    it rests on, when measured. ``averaged``: where the alternation reached its
    iteration limit without converging, how many estimates its ``T_ee_us`` is the mean
    of (0: it converged, or too few to average). ``lost_on_restack``: why the alternation
    stopped where re-stacked under its own estimate the sweeps no longer showed enough of
    the sphere to fit again (the estimate is far off; the last fit stands, unconverged);
    empty when it did not.
    """

    result: CalibrationResult
    observations: list[Observation]
    localizations: dict[str, list[SweepLocalization]]
    history: list[dict[str, float]]
    sphere_size: tuple[float, float, int] | None = None
    averaged: int = 0
    lost_on_restack: str = ""

    def retained_localizations(self) -> dict[str, list[SweepLocalization]]:
        """The final localizations as the calibration used them: a centre the localizer
        accepted but the calibration rejected as an outlier is not a localized sphere
        (it is marked rejected, with the calibration's reason). What a user is shown;
        ``localizations`` keeps the localizer's own verdicts (seeds for a next run)."""
        reasons = self.result.rejection_reasons
        dropped = {
            (o.target, o.pose_id): reasons.get(f"{o.target}/{o.pose_id}", "")
            for o, k in zip(self.observations, self.result.retained, strict=True)
            if not k
        }
        out: dict[str, list[SweepLocalization]] = {}
        for target, locs in self.localizations.items():
            out[target] = [
                replace(
                    loc,
                    accepted=False,
                    centre=np.full(3, np.nan),
                    reason="rejected by the calibration: "
                    + (dropped[(target, loc.pose_id)] or "an outlier of the fit"),
                )
                if loc.accepted and (target, loc.pose_id) in dropped
                else loc
                for loc in locs
            ]
        return out


def _observations(
    sweeps: Mapping[str, Sequence[Sweep]], locs: Mapping[str, Sequence[SweepLocalization]]
) -> list[Observation]:
    obs = []
    for target, ss in sweeps.items():
        for sweep, loc in zip(ss, locs[target], strict=True):
            if loc.accepted:
                obs.append(
                    Observation(
                        target, sweep.pose_id, loc.centre, sweep.T_base_ee[sweep.reference_index]
                    )
                )
    return obs


def _consensus_seeds(
    sweeps: Mapping[str, Sequence[Sweep]],
    locs: Mapping[str, Sequence[SweepLocalization]],
    obs: Sequence[Observation],
    result: CalibrationResult,
    rejected: set[tuple[str, int]],
) -> dict[str, list[Array | None]]:
    """Where each sweep the calibration rejected, or the localizer found nothing in,
    should find its sphere: the retained sweeps' centroid (base frame) through the new
    calibration into the sweep's reference frame; None for the others. So one bad sweep
    (a plate or a reverberation taken for the sphere) is searched again about its
    siblings' consensus instead of over its whole grid, which found the wrong thing."""
    X = centres_in_base(obs, result.T_ee_us)
    out: dict[str, list[Array | None]] = {}
    for t, ss in sweeps.items():
        idx = [i for i, o in enumerate(obs) if o.target == t and result.retained[i]]
        n_obs = sum(o.target == t for o in obs)
        if len(idx) < max(4, n_obs // 2):
            # Fewer than half retained: the consensus itself is in doubt (the fit may
            # have followed the wrong detections); those sweeps get their whole grid.
            out[t] = [None] * len(ss)
            continue
        centroid = X[idx].mean(axis=0)
        out[t] = [
            se3.apply(se3.invert(s.T_base_ee[s.reference_index] @ result.T_ee_us), centroid)
            if (t, s.pose_id) in rejected or not loc.accepted
            else None
            for s, loc in zip(ss, locs[t], strict=True)
        ]
    return out


def _mean_pose(Ts: Sequence[Array]) -> Array:
    """The mean of nearby poses: the rotation nearest the mean of their matrices (its
    polar factor), the mean translation."""
    R = se3.nearest_rotation(np.mean([T[:3, :3] for T in Ts], axis=0))
    return se3.make(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def _change(T: Array, T_prev: Array) -> tuple[float, float]:
    """How far an estimate moved from another: (mm, degrees)."""
    return (
        1e3 * float(se3.translation_distance(T, T_prev)),
        float(np.degrees(se3.rotation_angle(T, T_prev))),
    )


def _stopped_among(estimates: Sequence[Array], steps: Sequence[dict[str, float]]) -> int:
    """How many trailing ``estimates`` an alternation stopped among: those within twice
    its last two updates (mm and degrees, ``steps``' ``change_mm`` / ``change_deg``) of
    the last. An estimate moving back and forth keeps them all; one still drifting
    towards its fixed point (a start far off: each re-stack under the last estimate
    closes only part of the gap) keeps its last few, whose mean is not pulled back
    towards where it started. A mount 37° / 14 mm off its coarse estimate, sweeps 20° off
    the normal in depth: updates 10.6° → 0.015° over ten fits; the mean of the nine after
    the first lay 1.6° off about the lateral axis (0.79 mm over the image, its bound
    0.27 mm), the last ones 0.4°."""
    wobble_mm = 2.0 * max(s["change_mm"] for s in steps[-2:])
    wobble_deg = 2.0 * max(s["change_deg"] for s in steps[-2:])
    n = 1
    while n < len(estimates):
        d_mm, d_deg = _change(estimates[-n - 1], estimates[-1])
        if d_mm > wobble_mm or d_deg > wobble_deg:
            break
        n += 1
    return n


def _first_or_next(
    obs: Sequence[Observation],
    cad_centres: Mapping[str, Array] | None,
    T_prev: Array | None,
    layout_sigma_mm: float,
) -> CalibrationResult:
    """The alternation's calibration: from the previous estimate, or, the first time,
    from the closed form; where that keeps fewer than half the observations (or none fit),
    the first localization is contaminated and the largest agreeing set's closed form
    (:func:`consensus_initialisation`) is tried too: the result keeping more sweeps wins."""
    if T_prev is not None:
        return calibrate(obs, cad_centres, T_init=T_prev, layout_sigma_mm=layout_sigma_mm)
    result, failure = None, None
    try:
        result = calibrate(obs, cad_centres, layout_sigma_mm=layout_sigma_mm)
        if 2 * result.retained.sum() >= len(obs):
            return result
    except CalibrationError as exc:
        failure = exc
    try:
        T0, agree = consensus_initialisation(obs)
        other = calibrate(
            obs, cad_centres, T_init=T0, layout_sigma_mm=layout_sigma_mm, first_fit=agree
        )
    except CalibrationError:
        if result is None:
            raise failure from None
        return result
    if result is None or other.retained.sum() > result.retained.sum():
        return other
    return result


@dataclass(frozen=True)
class AlternationSettings:
    """How the alternation runs.

    Attributes
    ----------
    localizer : the localizer's settings
    axial_scale : float
        c_medium / c_assumed of the images (1 when the speed-of-sound correction is off;
        :func:`calib.sound.speed_ratio`).
    max_iterations : int
        Calibrations at most.
    tol_mm, tol_deg : float
        The estimate has converged when it changes by less than both.
    layout_sigma_mm : float
        The phantom's print tolerance (1 σ per axis of a sphere centre; see
        :func:`calib.calibration.markers.calibrate`); 0 takes the CAD layout as exact.
    threads : int
        Spheres localized side by side (the localizer's kernels release the GIL).
    """

    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    axial_scale: float = 1.0
    max_iterations: int = 5
    tol_mm: float = 0.01
    tol_deg: float = 0.01
    layout_sigma_mm: float = 0.0
    threads: int = 1


def alternate(
    sweeps: Mapping[str, Sequence[Sweep]],
    radius: float,
    settings: AlternationSettings,
    *,
    cad_centres: Mapping[str, Array] | None = None,
    T_coarse: Array | None = None,
    initial: Mapping[str, Sequence[SweepLocalization]] | None = None,
) -> AlternationResult:
    """Localize → calibrate → re-stack with the new ``T_ee_us`` → re-localize, until the
    estimate changes by less than ``settings.tol_mm`` and ``settings.tol_deg`` or
    ``settings.max_iterations`` (paper §III-F, "Single-marker calibration"). An
    alternation that reaches the limit without converging (the estimate moving back and
    forth: the localizations follow it) returns the mean of the estimates it stopped
    among (:func:`_stopped_among`), rather than wherever it stopped, and says so
    (``averaged``).

    The first localization stacks at the robot-measured spacing (``initial`` may hand it
    in, e.g. shared by several folds) and the first calibration starts from the
    closed-form initialisation; ``T_coarse`` (the holder's CAD) is only a fallback check:
    if the closed form lands far from it, a start from the coarse estimate is tried too
    and the lower loss wins. Each re-localization searches around the previous centres.
    ``cad_centres`` (sphere name → (3,) metres, phantom frame) are used with two or more
    spheres (:func:`calib.calibration.markers.calibrate`).
    """
    localizer = settings.localizer
    layout_sigma_mm = settings.layout_sigma_mm

    def localize_all(
        T: Array | None,
        previous: Mapping[str, Sequence[SweepLocalization | None]] | None,
        expected: Mapping[str, Sequence[Array | None]] | None = None,
    ) -> tuple[dict[str, list[SweepLocalization]], float]:
        t0 = time.perf_counter()

        def one(t: str) -> list[SweepLocalization]:
            prev = previous[t] if previous else None
            exp = expected[t] if expected else None
            return localize_sphere(
                sweeps[t],
                T,
                radius,
                localizer,
                axial_scale=settings.axial_scale,
                previous=prev,
                expected=exp,
                consensus=False,
            )

        if settings.threads > 1 and len(sweeps) > 1:
            with ThreadPoolExecutor(min(settings.threads, len(sweeps))) as ex:
                out = dict(zip(sweeps, ex.map(one, sweeps), strict=True))
        else:
            out = {t: one(t) for t in sweeps}
        return out, time.perf_counter() - t0

    if initial is not None:
        locs, t_localize = {t: list(initial[t]) for t in sweeps}, 0.0
    else:
        locs, t_localize = localize_all(None, None)
    history: list[dict[str, float]] = []
    iterates: list[tuple[CalibrationResult, list[Observation], dict]] = []
    T_prev: Array | None = None
    result = None
    converged = settings.max_iterations <= 1
    lost = ""
    for it in range(settings.max_iterations):
        obs = _observations(sweeps, locs)
        t0 = time.perf_counter()
        try:
            fitted = _first_or_next(obs, cad_centres, T_prev, layout_sigma_mm)
        except CalibrationError as exc:
            if T_prev is None:
                raise
            # Re-stacked under the last estimate, too few sweeps show the sphere to fit
            # again: that estimate is far off (e.g. a rotation the sweeps do not
            # determine). The last fit stands, on the localizations it used, unconverged.
            lost = f"{exc} after re-stacking under the estimate of iteration {it - 1}"
            result, obs, used = iterates[-1]
            break
        result, used = fitted, locs
        if T_prev is None and T_coarse is not None:
            far = (
                se3.translation_distance(result.T_ee_us, T_coarse) > 0.03
                or np.degrees(se3.rotation_angle(result.T_ee_us, T_coarse)) > 30
            )
            if far:
                # The coarse start is a second opinion: where it leaves too few sweeps to
                # fit (it followed the wrong detections), the first result stands.
                try:
                    other = calibrate(
                        obs, cad_centres, T_init=T_coarse, layout_sigma_mm=layout_sigma_mm
                    )
                except CalibrationError:
                    other = None
                # More sweeps explained wins, then the lower loss.
                if other is not None and (other.retained.sum(), -other.cost) > (
                    result.retained.sum(),
                    -result.cost,
                ):
                    result = other
        t_calibrate = time.perf_counter() - t0
        change_mm = change_deg = float("inf")
        if T_prev is not None:
            change_mm, change_deg = _change(result.T_ee_us, T_prev)
        history.append(
            {
                "iteration": it,
                "cost_mm2": result.cost,
                "change_mm": change_mm,
                "change_deg": change_deg,
                "n_observations": len(obs),
                "n_retained": int(result.retained.sum()),
                "localize_s": t_localize,
                "calibrate_s": t_calibrate,
            }
        )
        iterates.append((result, obs, used))
        if change_mm < settings.tol_mm and change_deg < settings.tol_deg:
            converged = True
            break
        if it == settings.max_iterations - 1:
            break  # no re-localization that no calibration would use
        T_prev = result.T_ee_us
        # Re-localize around the previous centres, except for sweeps the calibration
        # rejected: their centre may be a false detection, so they get the whole grid.
        rejected = {
            (o.target, o.pose_id) for o, k in zip(obs, result.retained, strict=True) if not k
        }
        seeds = {
            t: [
                None if (t, s.pose_id) in rejected else loc
                for s, loc in zip(sweeps[t], ls, strict=True)
            ]
            for t, ls in locs.items()
        }
        expected = (
            None
            if localizer.method == "paper"
            else _consensus_seeds(sweeps, locs, obs, result, rejected)
        )
        locs, t_localize = localize_all(T_prev, seeds, expected)
    assert result is not None
    averaged = 0
    if not converged and not lost and len(iterates) >= 3:
        # Stopped at the limit with the estimate still moving (the localizations follow
        # it back and forth): where it stopped is as good as chance. The estimate is the
        # mean of those it stopped among (:func:`_stopped_among`; never the first, which stacks
        # at the robot-measured spacing), on the last localizations. On quick.yaml with
        # the paper's localizer (16 seeds that did not converge in 5; the estimates moving
        # back and forth, so all after the first were averaged) the true image error went
        # from median 0.42 / max 0.77 mm (the last iterate) to 0.36 / 0.56; re-stacking at
        # the mean and fitting once more gave 0.51 / 0.66 (the localizer's wobble again),
        # and the iterate of least loss 0.49 / 0.77 (the loss of different localizations
        # is no guide).
        n = _stopped_among([r.T_ee_us for r, _, _ in iterates[1:]], history[1:])
        later = [r for r, _, _ in iterates[-n:]]
        X = _mean_pose([r.T_ee_us for r in later])
        Y = None
        if result.T_base_phantom is not None:
            Y = _mean_pose([r.T_base_phantom for r in later if r.T_base_phantom is not None])
        dist = centroid_distances_mm(obs, X, result.retained)
        result = replace(
            result,
            T_ee_us=X,
            T_base_phantom=Y,
            residuals_mm=dist,
            cost=float(np.sum(dist[result.retained] ** 2)),
        )
        averaged = len(later)
    # What the images say of the radius the localizer was told (the first sphere; a
    # check for the verdict, not an input).
    first = next(iter(sweeps))
    size = apparent_sphere_radius(
        sweeps[first],
        used[first],
        result.T_ee_us,
        radius,
        localizer,
        axial_scale=settings.axial_scale,
    )
    sphere_size = None if size is None else (radius, size[0], size[1])
    return AlternationResult(result, obs, used, history, sphere_size, averaged, lost)
