"""N-wire detection in a B-mode frame, threshold-free (issue "N-wire and wire targets",
item 2; the paper's spirit for spheres carried over to the field's standard phantom).

Each wire crosses the image plane as a small bright dot; the three wires of one N
pattern lie in one plane, so their dots lie on one line, the diagonal's between the
outer two, which are the patterns' outer spacing apart or more. The frame is searched by
its own intensity distribution and the phantom's geometry only: no intensity threshold
and no per-machine parameter.

1. **Candidates.** The frame smoothed at the dots' scale (a Gaussian of σ = 0.15 mm,
   about a wire's diameter), its local maxima within a dot's reach (1 mm), ranked by
   their smoothed grey level, those that are dots (smoothed at a whole echo's scale,
   fallen to half their height 2 mm away on at least one side in every direction: not a
   plate's or the tank's line, granular as a printed surface draws it); the
   brightest ``4 × wires`` are kept (the rest of a frame's maxima are speckle and
   reverberation, far below them).
2. **Triples.** Every three candidates on one line (the middle one within
   ``collinear_mm`` of the line through the outer two, and between them), the outer two
   between 0.8 and 2 × the pattern's outer spacing apart (the image plane cuts the
   pattern obliquely, never shorter than square on), the line within 45° of the image's
   lateral axis (the patterns lie in planes the probe looks down on: stacked patterns'
   outer wires also line up, vertically).
3. **Patterns.** The set of disjoint triples, one per pattern, whose lines are nearly
   parallel (within 15°) with the greatest total brightness (among the 40 brightest
   triples); the patterns are named
   in the configuration's order from the shallowest line down, the wires along each line
   from the image's marked side.
4. **Sub-pixel centres.** Each dot's grey-weighted centroid over its whole echo: the
   connected region about its maximum that stands out of the local background by more
   than the background's own spread (no level chosen, see :func:`_centroid`).

A frame where no such set exists is rejected with the reason (too few candidates, no
collinear triple, not enough parallel lines).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.special import ndtri

from ..files.plus_config import NWirePattern

__all__ = ["NWireDetection", "detect_nwires", "detect_wire", "middle_wire_point"]

Array = NDArray[np.float64]

#: PLUS's own tolerance for the dots of one pattern on one line (its segmentation's
#: ``CollinearPointsMaxDistanceFromLineMm``): a geometric fact of a printed N, not a
#: machine's.
COLLINEAR_MM = 0.6
_PARALLEL_DEG = 15.0
#: A pattern's wires lie in one plane the probe looks down on: its dots' line is within
#: this of the image's lateral axis. Steeper lines are other dots that happen to line up
#: (the outer wires of stacked patterns form vertical lines of the same spacing).
_MAX_LINE_TILT_DEG = 45.0
#: How far a wire's echo reaches from its maximum (its centroid's window, half-size): a
#: wire well under a millimetre thick, drawn by a beam about a millimetre wide laterally.
_DOT_REACH_MM = 2.0
#: The echo is where the frame stands out of the local background by its own spread.
_DOT_SPREADS = 2.0
_MAX_TRIPLES = 40


@dataclass(frozen=True)
class NWireDetection:
    """One frame's result: ``ok``, the wire dots (wire name → (column, row), pixels) and,
    when not found, why; ``skew`` how far each dot's centre lies below its echo's peak
    (rows: a comet tail or a pulse's ring-down pulls the centre down)."""

    ok: bool
    points: dict[str, tuple[float, float]]
    reason: str = ""
    skew: dict[str, float] = field(default_factory=dict)  # centre − peak, rows


def _candidates(
    frame: NDArray[np.uint8], spacing_mm: tuple[float, float], n: int, isolated: bool = False
) -> Array:
    sx, sy = spacing_mm
    smooth = ndimage.gaussian_filter(frame.astype(np.float32), (0.15 / sy, 0.15 / sx))
    reach = (max(3, round(1.0 / sy) | 1), max(3, round(1.0 / sx) | 1))
    peaks = (smooth == ndimage.maximum_filter(smooth, size=reach)) & (smooth > 0)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-smooth[rows, cols], kind="stable")
    rows, cols = rows[order], cols[order]
    # One maximum per dot: a flat top (a saturated echo) has several; keep the first.
    # Greedy, brightest first: the next kept is the first not within 1 mm of one kept
    # (each kept one clears its neighbours at once: noise leaves thousands of maxima).
    keep: list[int] = []
    alive = np.ones(len(rows), dtype=bool)
    while len(keep) < 4 * n and alive.any():
        i = int(np.argmax(alive))
        keep.append(i)
        alive &= np.hypot((rows - rows[i]) * sy, (cols - cols[i]) * sx) > 1.0
    rows, cols = rows[keep], cols[keep]
    # The dot test at the scale of a whole echo (σ = 0.5 mm), where a surface's granular
    # echo is one continuous line and a wire's echo still one compact spot.
    # (On the frame averaged over blocks of about 0.2 mm: the same picture at that
    # scale, in a fraction of the time.)
    f = max(1, int(0.2 / min(sx, sy)))
    H2, W2 = (frame.shape[0] // f) * f, (frame.shape[1] // f) * f
    small = frame[:H2, :W2].astype(np.float32).reshape(H2 // f, f, W2 // f, f).mean(axis=(1, 3))
    coarse = ndimage.gaussian_filter(small, (0.5 / (sy * f), 0.5 / (sx * f)), truncate=2.5)
    first = slice(0, 4 * n)
    centre = ((rows[first] + 0.5) / f - 0.5, (cols[first] + 0.5) / f - 0.5)
    dot = _is_dot(coarse, *centre, (sx * f, sy * f), isolated=isolated)
    rows, cols = rows[: 4 * n][dot][:n], cols[: 4 * n][dot][:n]
    return np.column_stack([cols, rows, smooth[rows, cols]])


def _is_dot(smooth: Array, rows, cols, spacing_mm, *, isolated: bool = False) -> NDArray[np.bool_]:
    """Whether each maximum is a dot: at ``_DOT_REACH_MM`` from it, in every pair of
    opposite directions, at least one side has fallen below half its height over the
    frame's background (its median). A line (a plate's or the tank's surface) stays
    bright both ways along itself; a neighbouring dot, or a comet tail, on one side only.

    ``isolated`` (a lone wire, nothing else of the phantom beside it): both sides must
    have fallen in every direction but along the beam, where the side above suffices (a
    comet tail or reverberation hangs below a wire). A plate's corner or edge then is
    no dot (its surface stays bright on one side), nor is anything at the frame's edge
    (outside the frame nothing is known)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=bool)
    sx, sy = spacing_mm
    rows, cols = np.asarray(rows, dtype=float), np.asarray(cols, dtype=float)
    background = float(np.median(smooth))
    height = ndimage.map_coordinates(smooth, [rows, cols], order=1, mode="nearest")
    half = background + 0.5 * (height - background)
    angles = np.linspace(0.0, np.pi, 8, endpoint=False)
    dr, dc = _DOT_REACH_MM * np.sin(angles) / sy, _DOT_REACH_MM * np.cos(angles) / sx
    both = []
    for sign in (1.0, -1.0):
        r = rows[:, None] + sign * dr[None, :]
        c = cols[:, None] + sign * dc[None, :]
        # Outside the frame nothing is known: it never counts as fallen.
        seen = ndimage.map_coordinates(
            smooth, [r.ravel(), c.ravel()], order=1, mode="constant", cval=np.inf
        )
        both.append(seen.reshape(r.shape))
    if not isolated:
        low = np.minimum(both[0], both[1]) < half[:, None]
        return low.all(axis=1)
    fallen = np.maximum(both[0], both[1]) < half[:, None]
    # Along the beam (angle 90°, rows increasing downwards): the side above only.
    beam = np.isclose(angles, np.pi / 2)
    fallen[:, beam] = both[1][:, beam] < half[:, None]
    return fallen.all(axis=1)


def _centroid(
    frame: NDArray[np.uint8], col: float, row: float, spacing_mm, reach_mm: float
) -> tuple[float, float, float]:
    """The dot's grey-weighted centroid over its whole echo: the connected region about
    its maximum where the (lightly smoothed) frame stands out of the local background by
    more than the background's own spread (median and 1.4826 × MAD of the window within
    ``reach_mm``). No level is chosen: measured on PLUS's frames the result does not move
    for 1–3 spreads, while a fixed window cut at the core (0.5 mm) biases the dot toward
    its brightest pixels (3-D error 0.517 against 0.475 mm). Also returns how far the
    centre lies below the echo's peak (rows)."""
    sx, sy = spacing_mm
    hx, hy = max(2, round(reach_mm / sx)), max(2, round(reach_mm / sy))
    r0, r1 = max(int(row) - hy, 0), min(int(row) + hy + 1, frame.shape[0])
    c0, c1 = max(int(col) - hx, 0), min(int(col) + hx + 1, frame.shape[1])
    win = frame[r0:r1, c0:c1].astype(float)
    smooth = ndimage.gaussian_filter(win, (0.1 / sy, 0.1 / sx))
    background = float(np.median(win))
    spread = max(1.4826 * float(np.median(np.abs(win - background))), 1.0)
    labels, _ = ndimage.label(smooth > background + _DOT_SPREADS * spread)
    here = labels[int(row) - r0, int(col) - c0]
    w = np.clip(win - background, 0.0, None)
    if here > 0:
        w = w * (labels == here)
    if w.sum() <= 0:
        return float(col), float(row), 0.0
    rr, cc = np.mgrid[r0:r1, c0:c1]
    centre_row = float((w * rr).sum() / w.sum())
    # The echo's peak depth (sub-pixel: a parabola through the smoothed profile's top).
    profile = (smooth * (w > 0)).sum(axis=1)
    i = int(np.argmax(profile))
    peak = float(i)
    if 0 < i < len(profile) - 1:
        a, b, c = profile[i - 1], profile[i], profile[i + 1]
        if a - 2 * b + c < 0:
            peak += float(np.clip(0.5 * (a - c) / (a - 2 * b + c), -1.0, 1.0))
    return float((w * cc).sum() / w.sum()), centre_row, centre_row - (r0 + peak)


def detect_nwires(
    frame: NDArray[np.uint8],
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
    collinear_mm: float = COLLINEAR_MM,
) -> NWireDetection:
    """The N patterns' wire dots in one frame (see the module doc); ``spacing_mm`` the
    frame's pixel spacing (columns, rows), e.g. from PLUS's ``TransducerOriginPixel`` →
    ``TransducerOrigin`` definition."""
    sx, sy = spacing_mm
    k = len(patterns)
    cand = _candidates(frame, spacing_mm, 4 * 3 * k)
    if len(cand) < 3 * k:
        return NWireDetection(
            False, {}, f"{len(cand)} bright dots in the frame; {3 * k} wires to find"
        )
    xy = cand[:, :2] * np.array([sx, sy])  # mm
    outer = [float(np.linalg.norm(p.wires[2].front - p.wires[0].front)) * 1e3 for p in patterns]
    lo, hi = 0.8 * min(outer), 2.0 * max(outer)
    triples = []
    for i, j in itertools.combinations(range(len(cand)), 2):
        d = xy[j] - xy[i]
        length = float(np.hypot(*d))
        if not lo <= length <= hi:
            continue
        u = d / length
        if abs(u[1]) > abs(u[0]) * np.tan(np.radians(_MAX_LINE_TILT_DEG)):
            continue  # steeper than a pattern imaged from above can be
        rel = xy - xy[i]
        along = rel @ u
        off = np.abs(rel @ np.array([-u[1], u[0]]))
        for m in np.flatnonzero((off <= collinear_mm) & (along > 0) & (along < length)):
            if m not in (i, j):
                triples.append((i, int(m), j, float(np.degrees(np.arctan2(u[1], u[0])) % 180)))
    if len(triples) < k:
        return NWireDetection(
            False,
            {},
            f"{len(triples)} collinear triples of dots ({collinear_mm:g} mm from a line within "
            f"{_MAX_LINE_TILT_DEG:g}° of the image's lateral axis, the outer two "
            f"{lo:.0f}–{hi:.0f} mm apart); {k} patterns to find",
        )
    best, best_score = None, -np.inf
    brightness = cand[:, 2]
    # The brightest triples first; the search over sets of them is kept to the first
    # few dozen (a frame's real triples are its brightest dots).
    triples.sort(key=lambda t: -float(brightness[list(t[:3])].sum()))
    triples = triples[:_MAX_TRIPLES]
    # Each triple as the bit mask of its dots, its brightness and line angle (plain
    # Python over the few thousand sets: a NumPy call per set cost more than the test).
    masks = [(1 << t[0]) | (1 << t[1]) | (1 << t[2]) for t in triples]
    scores = [float(brightness[list(t[:3])].sum()) for t in triples]
    angles = [t[3] for t in triples]

    def apart(a: float, b: float) -> float:
        return abs((a - b + 90.0) % 180.0 - 90.0)

    for combo in itertools.combinations(range(len(triples)), k):
        mask, clash = 0, False
        for t in combo:
            if mask & masks[t]:
                clash = True
                break
            mask |= masks[t]
        if clash:
            continue
        if any(apart(angles[a], angles[b]) > _PARALLEL_DEG
               for a, b in itertools.combinations(combo, 2)):  # fmt: skip
            continue
        score = sum(scores[t] for t in combo)
        if score > best_score:
            best, best_score = combo, score
    if best is None:
        return NWireDetection(
            False,
            {},
            f"no {k} disjoint collinear triples on nearly parallel lines (within "
            f"{_PARALLEL_DEG:g}°) among {len(triples)}",
        )
    # Shallowest line first; along each line from the marked side (high column) over.
    chosen = sorted(best, key=lambda t: float(np.mean(cand[list(triples[t][:3]), 1])))
    points, skew = {}, {}
    used = [c for t in chosen for c in triples[t][:3]]
    for pattern, t in zip(patterns, chosen, strict=True):
        dots = sorted(triples[t][:3], key=lambda c: -cand[c, 0])
        for wire, c in zip(pattern.wires, dots, strict=True):
            # Half the way to the nearest other dot at most: one dot's echo only.
            nearest = min(float(np.hypot(*(xy[c] - xy[o]))) for o in used if o != c)
            reach = min(_DOT_REACH_MM, nearest / 2)
            x, y, skew[wire.name] = _centroid(frame, cand[c, 0], cand[c, 1], spacing_mm, reach)
            points[wire.name] = (x, y)
    return NWireDetection(True, points, skew=skew)


#: A lone wire's dot must stand out of the frame's other dots (speckle grains, noise,
#: reverberation) so far that, among that many of them, one would get there by chance
#: with at most this probability: a false-alarm rate, not a grey level.
_WIRE_FALSE_ALARM = 0.01
#: The frame's other dots, ranked by brightness, looked at: far more than a frame's
#: real targets, enough for their spread.
_WIRE_POPULATION = 64


def detect_wire(
    frame: NDArray[np.uint8], spacing_mm: tuple[float, float], name: str = "wire"
) -> NWireDetection:
    """A single wire's dot in one frame, threshold-free: the brightest dot of the frame
    that is compact and isolated at a whole echo's scale (:func:`_candidates`: not a
    plate's line, edge or corner, not at the frame's edge), kept only when it stands out
    of the frame's other compact maxima (speckle grains, noise; a plate's line is no
    such maximum) — above their median by more than the Gaussian quantile of a 1 % false
    alarm among that many, in units of their robust spread; with fewer than three
    others nothing competes with it — and centred over its whole echo
    (:func:`_centroid`)."""
    cand = _candidates(frame, spacing_mm, _WIRE_POPULATION, isolated=True)
    if len(cand) == 0:
        return NWireDetection(False, {}, "no compact, isolated bright dot in the frame")
    dots = _candidates(frame, spacing_mm, _WIRE_POPULATION)
    top = np.hypot(dots[:, 0] - cand[0, 0], dots[:, 1] - cand[0, 1]) < 0.5
    others = dots[~top, 2]
    if len(others) >= 3:
        centre = float(np.median(others))
        spread = max(1.4826 * float(np.median(np.abs(others - centre))), 1.0)
        k = float(ndtri(1.0 - _WIRE_FALSE_ALARM / len(others)))
        if cand[0, 2] < centre + k * spread:
            return NWireDetection(
                False,
                {},
                "the brightest dot does not stand out of the frame's other dots (beyond a "
                "1 % false alarm among them): no wire in the image plane",
            )
    x, y, skew = _centroid(frame, cand[0, 0], cand[0, 1], spacing_mm, _DOT_REACH_MM)
    return NWireDetection(True, {name: (x, y)}, skew={name: skew})


def middle_wire_point(pattern: NWirePattern, pa: ArrayLike, pm: ArrayLike, pb: ArrayLike) -> Array:
    """Where the image plane cuts the pattern's diagonal wire, in the phantom frame
    (metres), from the three dots ``pa``, ``pm``, ``pb`` (outer, diagonal, outer; image
    millimetres or any units of equal scale along their line).

    The N's geometry (the classic N-wire construction): the dots lie on the plane's cut
    through the N's plane, so the diagonal's dot divides the outer two in the ratio
    ``t = |pm − pa| / |pb − pa|``, an affine invariant; across the outer wires (the
    direction perpendicular to them in the N's plane) it therefore sits at the fraction
    ``t`` between them, and that one coordinate fixes the point on the diagonal. Points
    (n, 2) give n points (n, 3)."""
    a, m, b = pattern.wires
    pa, pm, pb = (np.asarray(p, dtype=float) for p in (pa, pm, pb))
    t = np.linalg.norm(pm - pa, axis=-1) / np.linalg.norm(pb - pa, axis=-1)
    d = a.direction
    across = b.front - a.front
    across = across - (across @ d) * d
    across /= np.linalg.norm(across)
    x = a.front @ across + t * ((b.front - a.front) @ across)
    u = (x - m.front @ across) / ((m.back - m.front) @ across)
    return m.front + np.asarray(u)[..., None] * (m.back - m.front)
