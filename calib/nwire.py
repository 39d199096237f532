"""N-wire detection in a B-mode frame, threshold-free (issue "N-wire and wire targets",
item 2; the paper's spirit for spheres carried over to the field's standard phantom).

Each wire crosses the image plane as a small bright dot; the three wires of one N
pattern lie in one plane, so their dots lie on one line, the diagonal's between the
outer two, which are the patterns' outer spacing apart or more. The frame is searched by
its own intensity distribution and the phantom's geometry only: no intensity threshold
and no per-machine parameter.

1. **Candidates.** The frame smoothed at the dots' scale (a Gaussian of σ = 0.15 mm,
   about a wire's diameter), its local maxima within a dot's reach (1 mm), ranked by
   their smoothed grey level; the brightest ``4 × wires`` are kept (the rest of a frame's
   maxima are speckle and reverberation, far below them).
2. **Triples.** Every three candidates on one line (the middle one within
   ``collinear_mm`` of the line through the outer two, and between them), the outer two
   between 0.8 and 2 × the pattern's outer spacing apart (the image plane cuts the
   pattern obliquely, never shorter than square on).
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
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from .plus_config import NWirePattern

__all__ = ["NWireDetection", "detect_nwires", "middle_wire_point"]

Array = NDArray[np.float64]

#: PLUS's own tolerance for the dots of one pattern on one line (its segmentation's
#: ``CollinearPointsMaxDistanceFromLineMm``): a geometric fact of a printed N, not a
#: machine's.
COLLINEAR_MM = 0.6
_PARALLEL_DEG = 15.0
#: How far a wire's echo reaches from its maximum (its centroid's window, half-size): a
#: wire well under a millimetre thick, drawn by a beam about a millimetre wide laterally.
_DOT_REACH_MM = 2.0
#: The echo is where the frame stands out of the local background by its own spread.
_DOT_SPREADS = 2.0
_MAX_TRIPLES = 40


@dataclass(frozen=True)
class NWireDetection:
    """One frame's result: ``ok``, the wire dots (wire name → (column, row), pixels) and,
    when not found, why."""

    ok: bool
    points: dict[str, tuple[float, float]]
    reason: str = ""


def _candidates(frame: NDArray[np.uint8], spacing_mm: tuple[float, float], n: int) -> Array:
    sx, sy = spacing_mm
    smooth = ndimage.gaussian_filter(frame.astype(float), (0.15 / sy, 0.15 / sx))
    reach = (max(3, round(1.0 / sy) | 1), max(3, round(1.0 / sx) | 1))
    peaks = (smooth == ndimage.maximum_filter(smooth, size=reach)) & (smooth > 0)
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-smooth[rows, cols])[:n]
    return np.column_stack([cols[order], rows[order], smooth[rows[order], cols[order]]])


def _centroid(
    frame: NDArray[np.uint8], col: float, row: float, spacing_mm, reach_mm: float
) -> tuple[float, float]:
    """The dot's grey-weighted centroid over its whole echo: the connected region about
    its maximum where the (lightly smoothed) frame stands out of the local background by
    more than the background's own spread (median and 1.4826 × MAD of the window within
    ``reach_mm``). No level is chosen: measured on PLUS's frames the result does not move
    for 1–3 spreads, while a fixed window cut at the core (0.5 mm) biases the dot toward
    its brightest pixels (3-D error 0.517 against 0.475 mm)."""
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
        return float(col), float(row)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    return float((w * cc).sum() / w.sum()), float((w * rr).sum() / w.sum())


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
            f"{len(triples)} collinear triples of dots ({collinear_mm:g} mm from a line, the "
            f"outer two {lo:.0f}–{hi:.0f} mm apart); {k} patterns to find",
        )
    best, best_score = None, -np.inf
    brightness = cand[:, 2]
    # The brightest triples first; the search over sets of them is kept to the first
    # few dozen (a frame's real triples are its brightest dots).
    triples.sort(key=lambda t: -float(brightness[list(t[:3])].sum()))
    triples = triples[:_MAX_TRIPLES]
    for combo in itertools.combinations(range(len(triples)), k):
        used = [p for t in combo for p in triples[t][:3]]
        if len(set(used)) != len(used):
            continue
        angles = np.array([triples[t][3] for t in combo])
        spread = np.abs((angles[:, None] - angles[None, :] + 90) % 180 - 90).max()
        if spread > _PARALLEL_DEG:
            continue
        score = float(brightness[used].sum())
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
    points = {}
    used = [c for t in chosen for c in triples[t][:3]]
    for pattern, t in zip(patterns, chosen, strict=True):
        dots = sorted(triples[t][:3], key=lambda c: -cand[c, 0])
        for wire, c in zip(pattern.wires, dots, strict=True):
            # Half the way to the nearest other dot at most: one dot's echo only.
            nearest = min(float(np.hypot(*(xy[c] - xy[o]))) for o in used if o != c)
            reach = min(_DOT_REACH_MM, nearest / 2)
            points[wire.name] = _centroid(frame, cand[c, 0], cand[c, 1], spacing_mm, reach)
    return NWireDetection(True, points)


def middle_wire_point(pattern: NWirePattern, pa: ArrayLike, pm: ArrayLike, pb: ArrayLike) -> Array:
    """Where the image plane cuts the pattern's diagonal wire, in the phantom frame
    (metres), from the three dots ``pa``, ``pm``, ``pb`` (outer, diagonal, outer; image
    millimetres or any units of equal scale along their line).

    The N's geometry (the classic N-wire construction): the dots lie on the plane's cut
    through the N's plane, so the diagonal's dot divides the outer two in the ratio
    ``t = |pm − pa| / |pb − pa|``, an affine invariant; across the outer wires (the
    direction perpendicular to them in the N's plane) it therefore sits at the fraction
    ``t`` between them, and that one coordinate fixes the point on the diagonal."""
    a, m, b = pattern.wires
    pa, pm, pb = (np.asarray(p, dtype=float) for p in (pa, pm, pb))
    t = float(np.linalg.norm(pm - pa) / np.linalg.norm(pb - pa))
    d = a.direction
    across = b.front - a.front
    across = across - (across @ d) * d
    across /= np.linalg.norm(across)
    x = a.front @ across + t * ((b.front - a.front) @ across)
    u = (x - m.front @ across) / ((m.back - m.front) @ across)
    return m.front + u * (m.back - m.front)
