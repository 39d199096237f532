"""The count-based exhaustive search (paper §III-E-3) and what method "refined" adds to it:
the seed of each sweep.

Candidate centres lie on a 1 mm grid over the sweep, starting one radius below the face
(with method "refined" and an expected depth, only within the plan's window). Each
candidate samples a proximal shell at radius R (Fibonacci directions) and the proximal
half-ball (volume-distributed points); each sample takes its nearest voxel and asks
whether it is bright (:mod:`calib.localize.volume`). Samples outside the acquired volume
count in neither numerator nor denominator. The score is ``f_shell − f_interior``; its
argmax is the seed (:func:`score_grid`, compiled; :func:`score_candidates` for a list).

Method "refined" looks at the grid's ``_HYPOTHESES`` best separate maxima on a grid twice
as fine and judges each by its confined contrast (:func:`_hypothesis_search`), and where
nothing with a sphere's whole cap is found, searches the specular arc alone
(:func:`_arc_search`). A sweep with a previous or an expected centre is searched about it
(:func:`_seed_search`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .kernels import grid_sums
from .settings import LocalizerConfig
from .volume import LABEL_UNIT, SweepVolume, candidate_step

__all__ = ["fibonacci_hemisphere", "half_ball_samples", "score_candidates", "score_grid"]

Array = NDArray[np.float64]

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
# The confinement test's band (× the CAD radius) on the probe side: a sphere's echo ends
# at its surface, a flat reflector's (a plate, the tank floor) runs on past it.
_OUTER_BAND = (1.3, 1.8)
# Separate local maxima of the coarse grid searched finely (method "refined").
_HYPOTHESES = 4
_M_PER_MM = 1e-3


# ----------------------------------------------------------------------------- samples


def fibonacci_hemisphere(n: int) -> Array:
    """``n`` near-uniform unit directions (n, 3) on the proximal hemisphere (y < 0: towards
    the transducer face, which looks along +y)."""
    i = np.arange(n) + 0.5
    y = -i / n  # uniform in (-1, 0): equal areas on the hemisphere
    r = np.sqrt(1.0 - y**2)
    phi = i * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), y, r * np.sin(phi)])


def half_ball_samples(n: int, radius: float, *, inner: float = 0.0) -> Array:
    """``n`` deterministic volume-distributed points (n, 3) in the proximal half-shell
    ``inner ≤ r ≤ radius`` (a half-ball for ``inner = 0``), y ≤ 0."""
    i = np.arange(n) + 0.5
    u = (i * 0.7548776662466927) % 1.0  # R2 sequence, second coordinate: radius
    r = np.cbrt(inner**3 + u * (radius**3 - inner**3))
    return fibonacci_hemisphere(n) * r[:, None]


# ----------------------------------------------------------------------------- scoring


_OFFSETS_CACHE: dict[tuple[tuple[float, ...], bytes], NDArray[np.int64]] = {}


def _offsets_vox(vol: SweepVolume, P: Array) -> NDArray[np.int64]:
    """Sample offsets (m, 3) in metres → integer voxel offsets (m, 3) as (k, r, c), in
    memory order (consecutive lookups then touch neighbouring cache lines).

    Memoised on the spacing and the samples' values: a localization asks for the same
    few sample sets thousands of times (an eighth of a refined localization was spent
    converting and sorting them again)."""
    key = (tuple(vol.spacing), np.ascontiguousarray(P, dtype=np.float64).tobytes())
    cached = _OFFSETS_CACHE.get(key)
    if cached is not None:
        return cached
    dx, dy, dz = vol.spacing
    o = np.column_stack(
        [np.rint(P[:, 2] / dz), np.rint(P[:, 1] / dy), np.rint(P[:, 0] / dx)]
    ).astype(np.int64)
    o = o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]
    o.flags.writeable = False
    if len(_OFFSETS_CACHE) >= 256:
        _OFFSETS_CACHE.clear()
    _OFFSETS_CACHE[key] = o
    return o


def _bright_fraction(sums: NDArray[np.integer], n_samples: int, min_coverage: float) -> Array:
    """Bright share of the valid samples from encoded label sums; NaN where fewer than
    ``min_coverage`` of the ``n_samples`` (or none) were inside the volume."""
    valid, bright = sums % LABEL_UNIT, sums // LABEL_UNIT
    enough = (valid > 0) & (valid >= min_coverage * n_samples)
    return np.where(enough, bright / np.maximum(valid, 1), np.nan)


def _contrast(fractions: dict[str, Array]) -> tuple[Array, Array, Array]:
    """(score, f_shell, f_interior): score = f_shell − f_interior, −inf where undefined."""
    score = fractions["shell"] - fractions["interior"]
    return np.where(np.isnan(score), -np.inf, score), fractions["shell"], fractions["interior"]


def score_candidates(
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
    *,
    min_coverage: float = 0.0,
) -> tuple[Array, Array, Array]:
    """Scores of candidate centres (voxel indices (N, 3) as (k, r, c)).

    Returns ``(score, f_shell, f_interior)``, each (N,); candidates with fewer than
    ``min_coverage`` of their shell or interior samples inside the volume (or none) score
    −inf. Samples take the voxel at candidate + rounded offset, so a candidate on the
    voxel grid sees exactly the voxels the reference implementation looks up one by one.
    """
    fractions = {
        "shell": _fractions(vol, candidates, shell, min_coverage),
        "interior": _fractions(vol, candidates, interior, min_coverage),
    }
    return _contrast(fractions)


def _fractions(
    vol: SweepVolume, candidates: NDArray[np.int64], P: Array, min_coverage: float
) -> Array:
    """Bright share of the samples ``P`` (m, 3) about each candidate voxel (N, 3), NaN
    where fewer than ``min_coverage`` of them lie inside the volume."""
    o = _offsets_vox(vol, P)
    sums = vol.label_sums(candidates, o)
    return _bright_fraction(sums, len(o), min_coverage)


def score_grid(
    vol: SweepVolume,
    start: tuple[int, int, int],
    step: tuple[int, int, int],
    count: tuple[int, int, int],
    shell: Array,
    interior: Array,
    *,
    min_coverage: float = 0.0,
) -> tuple[Array, Array, Array]:
    """:func:`score_candidates` for a regular grid of candidates, (count) shaped."""
    if step[2] != vol.column_step:
        vol = vol.with_column_step(step[2])
    fractions = {}
    for name, P in (("shell", shell), ("interior", interior)):
        o = _offsets_vox(vol, P)
        sums = grid_sums(
            *vol.virtual_stack(),
            np.asarray(start, dtype=np.int64),
            np.asarray(step, dtype=np.int64),
            np.asarray(count, dtype=np.int64),
            o,
        )
        fractions[name] = _bright_fraction(sums, len(o), min_coverage)
    return _contrast(fractions)


# ----------------------------------------------------------------------------- search


def _candidate_grid(
    vol: SweepVolume, radius: float, grid: float, cfg: LocalizerConfig | None = None
) -> tuple[tuple[int, int, int], tuple[int, int, int], tuple[int, int, int]]:
    """(start, step, count) in voxels of the 1 mm candidate grid over the sweep, starting
    one radius below the face; with method "refined" and an expected depth, only within
    the plan's window (``expected_window_mm`` about the expected depth and the centre
    line)."""
    dx = vol.spacing[0]
    K, H, W = vol.shape
    step = candidate_step(vol.spacing, grid)
    # The image row one radius deep, and the centre line's column (x = 0).
    face_row, centre_col = vol.pixel(np.array([0.0, radius, 0.0]))
    lo = [0, max(int(np.ceil(face_row)) - vol.row0, 0), 0]
    hi = [K, H, W]  # exclusive
    if cfg is not None and cfg.method == "refined" and cfg.expected_depth_mm is not None:
        half = cfg.expected_window_mm * _M_PER_MM
        depth = cfg.expected_depth_mm * _M_PER_MM
        (top, bottom), _ = vol.pixel(np.array([[0.0, depth - half, 0.0], [0.0, depth + half, 0.0]]))
        centre_col = centre_col - vol.col0
        lo[1] = max(lo[1], int(np.ceil(top)) - vol.row0)
        hi[1] = min(hi[1], int(np.floor(bottom)) - vol.row0 + 1)
        lo[2] = max(lo[2], int(np.ceil(centre_col - half / dx)))
        hi[2] = min(hi[2], int(np.floor(centre_col + half / dx)) + 1)
    start = tuple(lo)
    count = tuple(max(0, -(-(n - s0) // st)) for n, s0, st in zip(hi, start, step, strict=True))
    return start, step, count


def _best_on_grid(vol, start, step, count, shell, interior, min_coverage):
    """(centre voxel, score, f_shell, f_interior) of the best candidate of a grid; score
    −inf for a grid without candidates (a window wholly outside the volume)."""
    if min(count) <= 0:
        return np.array(start), -np.inf, float("nan"), float("nan")
    score, fs, fi = score_grid(vol, start, step, count, shell, interior, min_coverage=min_coverage)
    i = np.unravel_index(int(np.argmax(score)), score.shape)
    cv = np.array(start) + np.array(step) * np.array(i)
    return cv, float(score[i]), float(fs[i]), float(fi[i])


@dataclass(frozen=True)
class _Hypothesis:
    """A candidate centre (voxel) with its confined contrast ``f_shell − max(f_interior,
    f_outer)`` and the three fractions."""

    voxel: NDArray[np.int64]
    score: float
    f_shell: float
    f_interior: float
    f_outer: float


def _outer_samples(n: int, radius: float) -> Array:
    """The confinement band's samples: the probe-side half-shell ``_OUTER_BAND`` × R."""
    return half_ball_samples(n, _OUTER_BAND[1] * radius, inner=_OUTER_BAND[0] * radius)


def _best_nearby(
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
    outers: Sequence[Array],
    min_coverage: float,
) -> _Hypothesis:
    """The candidate the paper's contrast ``f_shell − f_interior`` prefers, with its
    confined contrast: its cap must stand out from the inside of the sphere *and* from
    each set of ``outers`` just outside it (the water on the probe side, the tangent
    plane), where a sphere has no echo and a flat reflector (plate, floor) does. A set
    wholly outside the image is no evidence either way."""
    fs = _fractions(vol, candidates, shell, min_coverage)
    fi = _fractions(vol, candidates, interior, min_coverage)
    paper = np.where(np.isnan(fs - fi), -np.inf, fs - fi)
    i = int(np.argmax(paper))
    fo = float(np.fmax.reduce([_fractions(vol, candidates[i : i + 1], P, 0.0)[0] for P in outers]))
    confined = fs[i] - np.fmax(fi[i], fo)
    return _Hypothesis(
        candidates[i],
        float(confined) if np.isfinite(confined) else -np.inf,
        float(fs[i]),
        float(fi[i]),
        fo,
    )


def _local_maxima(vol, start, step, count, score, radius, k: int) -> list[NDArray[np.int64]]:
    """Up to ``k`` best grid candidates more than ``radius`` apart (greedy, best first)."""
    flat = score.ravel()
    order = np.argsort(-flat, kind="stable")[:4096]
    finite = np.isfinite(flat[order])
    if not finite.all():
        order = order[: int(np.argmin(finite))]
    # Every ranked candidate's position at once, then each pick clears its neighbours in
    # one step (one candidate at a time in Python was a fifth of a refined localization).
    V = np.array(start) + np.array(step) * np.stack(np.unravel_index(order, score.shape), axis=1)
    P = vol.position(*V.T.astype(float))
    alive = np.ones(len(order), dtype=bool)
    chosen: list[NDArray[np.int64]] = []
    while len(chosen) < k and alive.any():
        i = int(np.argmax(alive))
        chosen.append(V[i])
        alive &= np.linalg.norm(P - P[i], axis=1) > radius
    return chosen


def _fine_candidates(vol: SweepVolume, voxel: NDArray[np.int64], grid: float) -> NDArray[np.int64]:
    """Candidates within one coarse grid step of ``voxel`` at half its spacing, inside the
    volume: the coarse grid can miss a thin cap's shell by up to half a step."""
    half = candidate_step(vol.spacing, grid)
    fine = candidate_step(vol.spacing, grid / 2)
    axes = [
        np.arange(max(v - h, 0), min(v + h, n - 1) + 1, f)
        for v, h, f, n in zip(voxel, half, fine, vol.shape, strict=True)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int64)


def _hypothesis_search(
    vol: SweepVolume, radius: float, grid: float, shell: Array, interior: Array, cfg
) -> list[tuple[NDArray[np.int64], float, float, float]]:
    """The whole candidate grid scored as the paper scores it, then its ``_HYPOTHESES``
    best separate maxima searched finely and judged by their confined contrast there;
    best first, each as (grid voxel, score, f_shell, f_interior) of the grid point. A
    faint thin cap that the coarse grid straddles scores below a strong flat reflector
    there, and recovers its contrast on the fine grid, where the reflector
    gains little (it looks the same from any nearby point)."""
    start, step, count = _candidate_grid(vol, radius, grid, cfg)
    if min(count) <= 0:
        return []
    score, fs, fi = score_grid(
        vol, start, step, count, shell, interior, min_coverage=cfg.min_coverage
    )
    outer = _outer_samples(len(shell), radius)
    found = []
    for voxel in _local_maxima(vol, start, step, count, score, radius, _HYPOTHESES):
        fine = _fine_candidates(vol, voxel, grid)
        h = _best_nearby(vol, fine, shell, interior, (outer,), cfg.min_coverage)
        found.append((h.score, voxel))
    # Ranked by the confined contrast found nearby; each seed stays the coarse grid
    # point (the paper's seed whenever its best maximum wins).
    out = []
    for _, voxel in sorted(found, key=lambda f: -f[0]):
        i = tuple((voxel - np.array(start)) // np.array(step))
        out.append((voxel, float(score[i]), float(fs[i]), float(fi[i])))
    return out


# The specular arc (method "refined"): where the sphere's flanks are lost below the noise
# floor (an attenuating gel, a deep target at low gain) only the cap about normal
# incidence echoes, within _ARC_DEG of the beam axis (a mirror tilted by θ deflects the
# echo by 2θ, out of the receive aperture beyond ≈ 7-13°; the echo stays visible a little
# further). Its confinement: the tangent plane at the top, _TANGENT_BAND × R from the
# touching point, where a sphere has no echo and a flat reflector lies.
_ARC_DEG = 20.0
_TANGENT_BAND = (0.6, 1.4)


def _arc_samples(n: int, radius: float) -> Array:
    """Shell directions within ``_ARC_DEG`` of the beam axis (towards the face), × R."""
    d = fibonacci_hemisphere(int(np.ceil(n / (1.0 - np.cos(np.radians(_ARC_DEG))))))
    return d[-d[:, 1] >= np.cos(np.radians(_ARC_DEG))][:n] * radius


def _tangent_samples(n: int, radius: float) -> Array:
    """Points of the plane touching the sphere's top, ``_TANGENT_BAND`` × R from it
    (golden-angle spiral, uniform in area)."""
    i = np.arange(n) + 0.5
    lo, hi = _TANGENT_BAND
    r = radius * np.sqrt(lo**2 + (i / n) * (hi**2 - lo**2))
    phi = i * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), np.full(n, -radius), r * np.sin(phi)])


def _arc_search(
    vol: SweepVolume, radius: float, grid: float, cfg: LocalizerConfig
) -> _Hypothesis | None:
    """The best candidate whose specular arc stands out from the sphere's inside, from the
    water or gel just above it and from its tangent plane, among the plan window's
    ``_HYPOTHESES`` best separate maxima of the arc's contrast, each searched finely."""
    start, step, count = _candidate_grid(vol, radius, grid, cfg)
    if min(count) <= 0:
        return None
    arc = _arc_samples(cfg.shell_samples, radius)
    interior = half_ball_samples(cfg.interior_samples, radius)
    above = arc * (0.5 * sum(_OUTER_BAND))  # the outer band straight above the arc
    tangent = _tangent_samples(cfg.shell_samples, radius)
    score, _, _ = score_grid(vol, start, step, count, arc, interior, min_coverage=cfg.min_coverage)
    best = None
    for voxel in _local_maxima(vol, start, step, count, score, radius, _HYPOTHESES):
        fine = _fine_candidates(vol, voxel, grid)
        h = _best_nearby(vol, fine, arc, interior, (above, tangent), cfg.min_coverage)
        if best is None or h.score > best.score:
            best = h
    return best


def _local_window(
    centre_vox: Array, vol: SweepVolume, window: float, grid: float
) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """(start, step, count) of the candidate grid within ± ``window`` of a centre voxel,
    clipped to the volume."""
    step = candidate_step(vol.spacing, grid)
    start, count = [], []
    for centre, s, st, size in zip(centre_vox, vol.spacing[::-1], step, vol.shape, strict=True):
        half = int(np.rint(window / s))
        ax = np.arange(centre - half, centre + half + 1, st)
        ax = ax[(ax >= 0) & (ax < size)]
        start.append(int(ax[0]) if len(ax) else 0)
        count.append(len(ax))
    return tuple(start), step, tuple(count)


def _on_window_edge(index: tuple[int, ...], start, count, full_start, full_count, step) -> bool:
    """Whether a window's best candidate lies on an edge of the window that is not also an
    edge of the whole candidate grid (the peak may then lie outside the window)."""
    for i, s0, n, fs, fn, st in zip(index, start, count, full_start, full_count, step, strict=True):
        last = s0 + st * (n - 1)
        if i == 0 and s0 - st >= fs:
            return True
        if i == n - 1 and last + st <= fs + st * (fn - 1):
            return True
    return False


def _seed_search(vol, radius, grid, shell, interior, cfg, previous, expected=None):
    """The exhaustive search, or around a previous centre when there is one, or only
    around an expected centre when one is given."""
    full_start, step, full_count = _candidate_grid(vol, radius, grid, cfg)
    if expected is not None:
        k, r, c = (int(v) for v in vol.index(np.asarray(expected, dtype=float)))
        start, step, count = _local_window(
            (k, r, c), vol, cfg.relocalize_window_mm * _M_PER_MM, grid
        )
        start = tuple(max(s0, fs) for s0, fs in zip(start, full_start, strict=True))
        return _best_on_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
    if previous is not None and previous.accepted:
        k, r, c = (int(v) for v in vol.index(previous.centre))
        start, step, count = _local_window(
            (k, r, c), vol, cfg.relocalize_window_mm * _M_PER_MM, grid
        )
        start = tuple(max(s0, fs) for s0, fs in zip(start, full_start, strict=True))
        if all(n > 0 for n in count):
            best = _best_on_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
            index = tuple(int(v) for v in (best[0] - np.array(start)) // np.array(step))
            if np.isfinite(best[1]) and not _on_window_edge(
                index, start, count, full_start, full_count, step
            ):
                return best
    if cfg.method == "refined":
        hyps = _hypothesis_search(vol, radius, grid, shell, interior, cfg)
        if hyps:
            return hyps[0]
    return _best_on_grid(vol, full_start, step, full_count, shell, interior, cfg.min_coverage)
