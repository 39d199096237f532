"""The evidence a centre must pass beyond its score (method "refined"), and each
rejected sweep's reason.

With a calibration the centres of one sphere must agree in the robot base: a seed that
disagrees with the densest cluster of its siblings' is searched again about it
(:func:`_consensus`), a centre that still disagrees is rejected with the distance, and
where no three centres agree none is confirmed (:func:`_reject_disagreeing`). A sphere
found in fewer than half its sweeps is at the noise floor (:func:`_reject_if_rarely_seen`).
The reasons a sweep is rejected: no sphere found (score, or the plan's window); not a
sphere (the echo runs on past the CAD radius); sphere cut by the image's lateral edge;
elevation not measured; disagrees with (or unconfirmed by) the sphere's other sweeps;
sphere at the noise floor.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..image import pixel_to_us
from ..records import Sweep
from ..robust import outlier_limit
from .search import _M_PER_MM, _OUTER_BAND, _seed_search
from .settings import LocalizerConfig, SweepLocalization

Array = NDArray[np.float64]

# Consensus of one sphere's sweeps in the base frame: centres within _CLUSTER_MM of
# each other form a cluster; a centre agrees with the densest cluster within
# max(_AGREE_FLOOR_MM, a robust 3σ of the cluster's spread).
_CLUSTER_MM = 2.0
_AGREE_FLOOR_MM = 1.0
_MIN_CLUSTER = 3  # centres that agree before any is confirmed
_MIN_SWEEPS_SEEN = 6  # sweeps of a sphere before its share of detections is judged


def _agreeing(base: Array, found: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], Array, float]:
    """(agree, consensus, limit_mm): which of the found centres (n, 3, base frame) agree
    with the densest cluster of them, its mean, and the distance limit. The densest
    cluster, not the mean of all: wrong candidates scatter (a plate offers one anywhere
    along it) while right ones agree, even when they are fewer than half."""
    idx = np.flatnonzero(found)
    pts = base[idx]
    if len(idx) == 0:
        return found.copy(), np.full(3, np.nan), float("inf")
    near = np.linalg.norm(pts[:, None] - pts[None], axis=-1) < _CLUSTER_MM * _M_PER_MM
    cluster = near[int(np.argmax(near.sum(axis=1)))]
    if cluster.sum() < _MIN_CLUSTER:
        return found.copy(), np.full(3, np.nan), float("inf")
    consensus = pts[cluster].mean(axis=0)
    d = np.linalg.norm(base - consensus, axis=1) / _M_PER_MM
    limit = outlier_limit(d[idx][cluster], _AGREE_FLOOR_MM)
    return found & (d <= limit), consensus, limit


def _in_base(sweeps, centres, T_ee_us) -> tuple[list[Array], Array]:
    """Each sweep's reference pose ``T_base_ee[ref] @ T_ee_us`` and its centre (3, in that
    frame) in the base frame, (n, 3)."""
    T_ref = [s.T_base_ee[s.reference_index] @ np.asarray(T_ee_us) for s in sweeps]
    return T_ref, np.array([se3.apply(T, c) for T, c in zip(T_ref, centres, strict=True)])


def _consensus(sweeps, vols, results, T_ee_us, radius, grid, shell, interior, cfg):
    """With a calibration every sweep's centre maps into the robot base, where all of one
    sphere's must agree: a sweep whose seed disagrees with its siblings' (a plate or a
    reverberation won its whole grid) or that found nothing is searched again only
    within ``relocalize_window_mm`` of their consensus mapped into its frame."""
    centres = [
        v.position(*np.asarray(r[0], dtype=float)) for v, r in zip(vols, results, strict=True)
    ]
    T_ref, base = _in_base(sweeps, centres, T_ee_us)
    found = np.array([r[1] >= cfg.min_score for r in results])
    agree, consensus, limit = _agreeing(base, found)
    notes: dict[int, str] = {}
    if not np.isfinite(consensus).all():
        return results, notes
    out = list(results)
    for i in np.flatnonzero(~agree):
        expected = se3.apply(se3.invert(T_ref[i]), consensus)
        out[i] = _seed_search(vols[i], radius, grid, shell, interior, cfg, None, expected)
        if found[i]:
            d = float(np.linalg.norm(base[i] - consensus) / _M_PER_MM)
            notes[i] = (
                f"disagrees with the sphere's other sweeps: its best candidate lay {d:.2f} mm "
                f"from their consensus (limit {limit:.2f} mm), and nothing near the "
                f"consensus looks like the sphere"
            )
    return out, notes


# A centre whose elevation the cap's echo gives only to worse than this (1 σ, metres) is
# rejected: at 2 σ it could be a millimetre off.
_MAX_ELEVATION_SIGMA = 0.5e-3


def _not_a_sphere(f_shell: float, f_outer: float) -> str:
    """Why a candidate whose cap does not stand out from the band just outside the CAD
    sphere (the confinement test) is no sphere."""
    return (
        f"not a sphere: its echo runs on outside the CAD radius (bright share "
        f"{f_shell:.2f} on the sphere, {f_outer:.2f} at "
        f"{_OUTER_BAND[0]:g}-{_OUTER_BAND[1]:g} R; a flat reflector?)"
    )


_ELEVATION_NOT_MEASURED = "elevation not measured"


def _elevation_not_measured(z_sigma: float, frame_step: float | None = None) -> str:
    """Why a centre whose elevation has a standard error ``z_sigma`` (metres) above
    ``_MAX_ELEVATION_SIGMA`` is not accepted (``frame_step``: the sweep's frame spacing,
    named when the error is that of an elevation known to a frame)."""
    if not np.isfinite(z_sigma):
        return (
            f"{_ELEVATION_NOT_MEASURED}: the cap's echo does not fall to half its peak on both "
            "sides across the sweep's frames (a longer sweep, or the sphere nearer its middle)"
        )
    sparse = frame_step is not None and z_sigma >= 0.25 * frame_step
    return (
        f"{_ELEVATION_NOT_MEASURED}: the cap's echo across the frames gives it to "
        f"± {z_sigma / _M_PER_MM:.2f} mm "
        f"(1 σ; at most {_MAX_ELEVATION_SIGMA / _M_PER_MM:g})"
        + (
            f": the frames are {frame_step / _M_PER_MM:.1f} mm apart; take more frames per sweep"
            if sparse
            else ""
        )
    )


_CUT_BY_EDGE = "sphere cut by the image's lateral edge"
_SEEN_BUT_UNMEASURED = (_CUT_BY_EDGE, _ELEVATION_NOT_MEASURED)


def _cut_by_lateral_edge(sweep: Sweep, centre: Array, radius: float) -> str:
    """Why a centre cannot be trusted if the sphere reaches past a lateral edge of the
    image (else ""): its sections there are cut off, and the centre fitted to what is
    left is pulled toward the image (measured on the twin: 0.2-0.5 mm once the sphere
    reaches 1 mm past the edge, against 0.02 mm inside)."""
    W = sweep.images.shape[2]
    half_width = float(pixel_to_us(0, W - 1, W, sweep.spacing)[0])  # x of the last column
    x = float(centre[0])
    if abs(x) + radius <= half_width:
        return ""
    return (
        f"{_CUT_BY_EDGE}: its centre is {x / _M_PER_MM:+.1f} mm "
        f"from the centre line, its radius {radius / _M_PER_MM:g} mm, the image reaches "
        f"± {half_width / _M_PER_MM:.1f} mm (the centre of a cut sphere is biased)"
    )


def _reject_if_rarely_seen(locs: list[SweepLocalization]) -> list[SweepLocalization]:
    """The plan keeps the sphere in view in every sweep: a sphere whose echo stands out
    in fewer than half of them is at the noise floor (an attenuating gel too deep, a low
    gain), where the few detections are the ones noise happened to shape; none of them
    is accepted, each with that reason."""
    n = len(locs)
    # A sphere cut by the image's edge, or whose elevation its frames could not measure,
    # was seen (its echo stood out), only not where or how it can be measured: sparse
    # frames are not a faint sphere.
    found = sum(r.accepted or r.reason.startswith(_SEEN_BUT_UNMEASURED) for r in locs)
    if n < _MIN_SWEEPS_SEEN or 2 * found >= n:
        return locs
    reason = (
        f"sphere at the noise floor: found in only {found} of its {n} sweeps (a sphere "
        f"in view is found in most; at least half needed to trust any)"
    )
    return [
        replace(r, accepted=False, centre=np.full(3, np.nan), reason=reason) if r.accepted else r
        for r in locs
    ]


def _not_found(score: float, cfg: LocalizerConfig) -> str:
    """Why a sweep has no centre: its best score stayed below ``min_score``, or no
    candidate centre lay in the image (the plan's window, if any, missed it)."""
    if np.isfinite(score):
        return f"no sphere found: best score {score:.2f} < {cfg.min_score:.2f}"
    where = (
        f"within {cfg.expected_window_mm:g} mm of the plan's target depth "
        f"{cfg.expected_depth_mm:g} mm and the centre line"
        if cfg.method == "refined" and cfg.expected_depth_mm is not None
        else "in the sweep"
    )
    return f"no sphere found: no candidate centre {where} lies in the image"


def _reject_disagreeing(sweeps, locs, T_ee_us) -> list[SweepLocalization]:
    """Evidence from the siblings: an accepted centre that disagrees with the consensus of
    the sphere's other sweeps (base frame, through the calibration) is rejected with the
    distance and the limit. Where no three accepted centres agree (the sphere at the
    noise floor: a few caps and a few spots of the plate, scattered), none is
    confirmed, and none is accepted."""
    _, base = _in_base(sweeps, [loc.centre for loc in locs], T_ee_us)
    found = np.array([loc.accepted for loc in locs])
    agree, consensus, limit = _agreeing(base, found)
    unconfirmed = len(locs) >= _MIN_CLUSTER and not np.isfinite(consensus).all()
    out = []
    for i, loc in enumerate(locs):
        reason = ""
        if loc.accepted and unconfirmed:
            reason = (
                f"unconfirmed: fewer than {_MIN_CLUSTER - 1} other sweeps of the sphere "
                f"put its centre within {_CLUSTER_MM:g} mm of this one's ({int(found.sum())} "
                f"of {len(locs)} sweeps found a candidate)"
            )
        elif loc.accepted and not agree[i]:
            d = float(np.linalg.norm(base[i] - consensus) / _M_PER_MM)
            reason = (
                f"disagrees with the sphere's other sweeps: {d:.2f} mm from their "
                f"consensus (limit {limit:.2f} mm)"
            )
        if reason:
            loc = replace(loc, centre=np.full(3, np.nan), accepted=False, reason=reason)
        out.append(loc)
    return out
