"""One sphere localized in each of its sweeps: the stages of :mod:`calib.localize` in the
paper's order (§III-E), and what the localizer saw (:func:`sphere_profile`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..records import Sweep
from .baseline import localize_sphere_fixed_threshold
from .consensus import (
    _MAX_ELEVATION_SIGMA,
    _consensus,
    _cut_by_lateral_edge,
    _elevation_not_measured,
    _not_a_sphere,
    _not_found,
    _reject_disagreeing,
    _reject_if_rarely_seen,
)
from .refine import (
    _did_not_settle,
    _nothing_to_refine,
    _radial_band_passes,
    _refine_centre,
    apparent_radius,
    profile_bands,
    profile_crossings,
    radial_profile,
)
from .search import (
    _arc_search,
    _best_nearby,
    _fine_candidates,
    _outer_samples,
    _seed_search,
    fibonacci_hemisphere,
    half_ball_samples,
)
from .settings import LocalizerConfig, SweepLocalization
from .volume import SweepVolume, candidate_step, stack_sweep

__all__ = ["SphereProfile", "apparent_sphere_radius", "localize_sphere", "sphere_profile"]

Array = NDArray[np.float64]
# A sweep's best candidate: (centre voxel, score, f_shell, f_interior).
_Seed = tuple[NDArray[np.int64], float, float, float]


def localize_sphere(
    sweeps: Sequence[Sweep],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    *,
    axial_scale: float = 1.0,
    previous: Sequence[SweepLocalization | None] | None = None,
    expected: Sequence[Array | None] | None = None,
    consensus: bool = True,
) -> list[SweepLocalization]:
    """Localize one sphere in each of its sweeps (centres in each sweep's reference frame).

    Parameters
    ----------
    sweeps : the sweeps of one sphere
    T_ee_us : (4, 4) float or None
        Current calibration for re-stacking; None stacks at the robot-measured spacing.
    radius : float, metres
        The sphere radius: the only geometric prior.
    axial_scale : float
        c_medium / c_assumed (1 when the speed-of-sound correction is off).
    previous : the sweeps' localizations before this re-stack, if any
        Each sweep with one is then searched within ``relocalize_window_mm`` of its
        previous centre (falling back to the whole grid as described there); None entries
        get the whole grid.
    expected : a predicted centre (3,) per sweep, or None, in its reference frame (e.g. its
        siblings' consensus through the current calibration): the sweep is searched only
        within ``relocalize_window_mm`` of it (its whole grid found something else). It
        takes precedence over ``previous``.
    consensus : with ``T_ee_us`` (and a method other than "paper"), use the sphere's other
        sweeps as evidence: seeds that disagree with their consensus in the base frame
        are searched again about it, centres that still disagree are rejected. For a
        trusted calibration; the alternation turns it off (its estimate may still be far
        off, and the calibration's own outlier stage does the same about its consensus).

    Examples
    --------
    A synthetic sweep: 21 frames 0.5 mm apart, 0.2 mm pixels, the probe-facing half of a
    5 mm sphere's surface drawn bright (0.6 mm thick) about (1, 15, 0.3) mm:

    >>> from calib import se3
    >>> from calib.image import pixel_axes
    >>> from calib.records import Sweep
    >>> z = np.linspace(-5e-3, 5e-3, 21)
    >>> rows, cols = np.mgrid[0:151, 0:151]
    >>> x, y = pixel_axes(rows, cols, 151, (0.2e-3, 0.2e-3))  # the us frame
    >>> centre = np.array([1e-3, 15e-3, 0.3e-3])
    >>> def frame(zk):
    ...     d = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (zk - centre[2]) ** 2)
    ...     return np.where((abs(d - 5e-3) < 0.3e-3) & (y < centre[1]), 200, 0)
    >>> images = np.array([frame(zk) for zk in z], np.uint8)
    >>> poses = np.array([se3.make(np.eye(3), [0.0, 0.0, zk]) for zk in z])
    >>> sweep = Sweep("sphere_1", 0, images, (0.2e-3, 0.2e-3), np.zeros((21, 6)), poses)
    >>> (found,) = localize_sphere([sweep], np.eye(4), 5e-3, LocalizerConfig())
    >>> found.accepted, bool(np.linalg.norm(found.centre - centre) < 0.2e-3)
    (True, True)
    """
    if T_ee_us is not None:
        se3.check(T_ee_us, "T_ee_us")
    for sweep in sweeps:
        se3.check(sweep.T_base_ee, f"{sweep.target} sweep {sweep.pose_id}: T_base_ee", batch=True)
    if cfg.method == "fixed_threshold":
        return localize_sphere_fixed_threshold(
            sweeps, T_ee_us, radius, cfg, axial_scale=axial_scale
        )
    if previous is not None and len(previous) != len(sweeps):
        raise ValueError(f"{len(previous)} previous localizations for {len(sweeps)} sweeps")
    if expected is not None and len(expected) != len(sweeps):
        raise ValueError(f"{len(expected)} expected centres for {len(sweeps)} sweeps")
    grid = cfg.grid_mm * 1e-3
    shell = fibonacci_hemisphere(cfg.shell_samples) * radius
    interior = half_ball_samples(cfg.interior_samples, radius)
    # §III-E-1, 2: adaptive brightness, the sweep volume (re-stacked under T_ee_us).
    vols = [_stack(s, T_ee_us, axial_scale, cfg) for s in sweeps]
    # §III-E-3: the count-based search's seed of each sweep (or about its previous or
    # expected centre).
    seeds = [
        _seed_search(
            vol,
            radius,
            grid,
            shell,
            interior,
            cfg,
            previous[i] if previous else None,
            expected[i] if expected else None,
        )
        for i, vol in enumerate(vols)
    ]
    # The siblings as evidence: seeds that disagree are searched again about them.
    notes: dict[int, str] = {}
    use_consensus = consensus and T_ee_us is not None and cfg.method != "paper"
    if use_consensus:
        seeds, notes = _consensus(sweeps, vols, seeds, T_ee_us, radius, grid, shell, interior, cfg)
    # §III-E-4: the radial-band refinement passes.
    seeds = _radial_band_passes(vols, seeds, radius, grid, cfg)
    # Each sweep's centre, accepted or rejected with its reason.
    outer = _outer_samples(len(shell), radius)
    out = [
        _conclude(sweep, vol, seed, notes.get(i), radius, grid, (shell, interior, outer), cfg)
        for i, (sweep, vol, seed) in enumerate(zip(sweeps, vols, seeds, strict=True))
    ]
    if use_consensus:
        out = _reject_disagreeing(sweeps, out, T_ee_us)
    if cfg.method == "refined":
        out = _reject_if_rarely_seen(out)
    return out


def _stack(
    sweep: Sweep, T_ee_us: Array | None, axial_scale: float, cfg: LocalizerConfig
) -> SweepVolume:
    """The sweep's volume as the localizer searches it: its labels split for the
    candidate grid's column step (the sweep's bright bits are then memoised once, for
    every re-stack and for :func:`sphere_profile`), bright above the depth's noise floor
    too with method "refined"."""
    column_step = candidate_step((sweep.spacing[0], sweep.spacing[1], 1.0), cfg.grid_mm * 1e-3)[2]
    return stack_sweep(
        sweep,
        T_ee_us,
        axial_scale=axial_scale,
        column_step=column_step,
        noise_floor=cfg.method == "refined",
    )


def _conclude(
    sweep: Sweep,
    vol: SweepVolume,
    seed: _Seed,
    note: str | None,
    radius: float,
    grid: float,
    samples: tuple[Array, Array, Array],
    cfg: LocalizerConfig,
) -> SweepLocalization:
    """One sweep's result from its refined seed: accepted when it scores ``min_score``
    and, with method "refined", passes the confinement test (then its sub-voxel centre),
    or else is found by its specular arc alone; then the sphere must lie inside the
    image laterally and its elevation be measured. ``note`` is the consensus's reason
    for a seed it searched again (that sweep's arc is not searched); ``samples`` the
    shell, interior and outer-band samples."""
    shell, interior, outer = samples
    cv, score, fs, fi = seed
    centre = vol.position(*np.asarray(cv, dtype=float))
    fo = float("nan")
    z_sigma = 0.0
    accepted = bool(score >= cfg.min_score)
    reason = "" if accepted else (note if note is not None else _not_found(score, cfg))
    if accepted and cfg.method == "refined":
        # Evidence beyond the score that picked it: the CAD sphere's cap must stand
        # out from the water just outside it as well (a flat reflector does not).
        fine = _fine_candidates(vol, np.asarray(cv, dtype=np.int64), grid)
        h = _best_nearby(vol, fine, shell, interior, (outer,), 0.0)
        fo = h.f_outer
        if h.f_shell - h.f_outer < cfg.min_score:
            accepted, reason = False, _not_a_sphere(h.f_shell, h.f_outer)
        else:
            fit = _refine_centre(vol, centre, radius)
            if fit is None:
                accepted, reason = False, _did_not_settle()
            elif np.isnan(fit[1]):
                accepted, reason = False, _nothing_to_refine()
            else:
                centre, z_sigma = fit
    elif cfg.method == "refined" and note is None:
        # Nothing with a sphere's whole cap: perhaps only its specular arc echoes.
        arc = _arc_search(vol, radius, grid, cfg)
        if arc is not None and arc.score >= cfg.min_score:
            score, fs, fi, fo = arc.score, arc.f_shell, arc.f_interior, arc.f_outer
            fit = _refine_centre(vol, vol.position(*arc.voxel.astype(float)), radius)
            if fit is None:
                reason = _did_not_settle()
            elif np.isnan(fit[1]):
                reason = _nothing_to_refine()
            else:
                accepted, reason = True, ""
                centre, z_sigma = fit
    if accepted and cfg.method == "refined":  # the paper's method as published
        edge = _cut_by_lateral_edge(sweep, centre, radius)
        if edge:
            accepted, reason = False, edge
    if accepted and z_sigma > _MAX_ELEVATION_SIGMA:
        # The cap's echo is about as bright in many frames (a weak echo in a beam
        # wider than the sphere): its elevation is not measured well enough.
        accepted, reason = False, _elevation_not_measured(z_sigma, vol.spacing[2])
    return SweepLocalization(
        sweep.target,
        sweep.pose_id,
        centre if accepted else np.full(3, np.nan),
        score,
        fs,
        fi,
        accepted,
        reason,
        fo,
    )


@dataclass(frozen=True)
class SphereProfile:
    """The radial brightness profile of a sphere's sweeps about their localized centres
    (peak-normalised, averaged over the accepted sweeps) and the bands the localizer reads
    off it: ``interior`` (first rising 0.25 crossing), ``shell`` (rising and falling 0.75
    crossings); ``crossed`` says which of the three the profile has (the others are
    :func:`profile_bands`'s fall-backs, e.g. no 0.25 crossing when speckle keeps the
    interior above a quarter of the peak). Radii in metres."""

    radii: Array
    profile: Array
    interior: float
    shell: tuple[float, float]
    n_sweeps: int
    crossed: tuple[bool, bool, bool] = (True, True, True)


def sphere_profile(
    sweeps: Sequence[Sweep],
    localizations: Sequence[SweepLocalization],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    *,
    axial_scale: float = 1.0,
) -> SphereProfile:
    """:func:`radial_profile` and :func:`profile_bands` of localized sweeps, for showing
    what the localizer saw (the stacks are rebuilt under ``T_ee_us``, as the localization
    that produced the centres used)."""
    if len(localizations) != len(sweeps):
        raise ValueError(f"{len(localizations)} localizations for {len(sweeps)} sweeps")
    vols, centres = [], []
    for sweep, loc in zip(sweeps, localizations, strict=True):
        if loc.accepted:
            # The localizer's column step: the sweep's bright bits are then the ones it
            # already memoised (no second copy of them).
            vol = _stack(sweep, T_ee_us, axial_scale, cfg)
            vols.append(vol)
            centres.append(np.array(vol.index(loc.centre), dtype=float))
    if not vols:
        empty = np.zeros(0)
        return SphereProfile(empty, empty, float("nan"), (float("nan"),) * 2, 0)
    radii = np.arange(0.0, 1.6 * radius, min(vols[0].spacing[:2]))
    profile = radial_profile(vols, centres, radii, cfg.profile_directions)
    inner, rise, fall = profile_bands(radii, profile, radius)
    crossed = tuple(c is not None for c in profile_crossings(radii, profile))
    return SphereProfile(radii, profile, inner, (rise, fall), len(vols), crossed)


def apparent_sphere_radius(
    sweeps: Sequence[Sweep],
    localizations: Sequence[SweepLocalization],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    *,
    axial_scale: float = 1.0,
    at_most: int = 15,
) -> tuple[float, int] | None:
    """The median over (at most ``at_most``, evenly chosen) accepted sweeps of the
    sphere's radius as their images draw it (:func:`calib.localize.refine.
    apparent_radius`), and how many sweeps gave one; None unless most of them (and at least
    three) gave one."""
    accepted = [i for i, loc in enumerate(localizations) if loc.accepted]
    if not accepted:
        return None
    n = min(at_most, len(accepted))
    pick = [accepted[int(j)] for j in np.linspace(0, len(accepted) - 1, n)]
    found = []
    for i in dict.fromkeys(pick):
        vol = _stack(sweeps[i], T_ee_us, axial_scale, cfg)
        r = apparent_radius(vol, localizations[i].centre, radius)
        if r is not None:
            found.append(r)
    # Most of the sweeps tried must draw the cap's arc: where only its top echoes (gel)
    # the few fits that pass read speckle (2.3 mm for a 5 mm sphere, 2 sweeps of 15).
    if len(found) < max(3, (n + 1) // 2):
        return None
    return float(np.median(found)), len(found)
