"""Threshold-free sphere localization (paper, "Threshold-Free Sphere Localization").

Per sweep:

1. **Adaptive brightness.** A pixel is bright when it is above the mean of its own frame
   (no user-chosen intensity cut-off).
2. **Sweep volume.** The frames are stacked at the robot-measured spacing; once a
   ``T_ee_us`` is known they are re-stacked into the sweep's reference frame (the centre
   frame's ``us`` frame), which removes the shear a wrong calibration puts into the stack.
3. **Count-based exhaustive search.** Candidate centres on a 1 mm grid over the sweep,
   starting one radius below the face. Each candidate samples a proximal shell at radius R
   (Fibonacci directions) and the proximal half-ball (volume-distributed points); each
   sample takes its nearest voxel and asks whether it is bright. Samples outside the
   acquired volume count in neither numerator nor denominator. The score is
   ``f_shell − f_interior``; its argmax is the seed.
4. **Radial-band refinement.** Around the current centres, the bright fraction on proximal
   hemispheres of trial radius, averaged over all sweeps of the sphere and normalised to its
   peak, gives a radial profile: the interior extends to its first rising 0.25 crossing, the
   shell band lies between its 0.75 crossings. Those bands replace the initial samples for
   the refinement passes.

``method="paper"`` stops there (grid-point centres). ``method="refined"`` differs in
seven ways, each for a failure of the paper's score measured on the twin (a bright plate
or floor taken for the sphere in ≈ 10-60 % of sweeps at low gain, a small sphere or a deep
target; a biased centre where the cap saturates):

- *Brightness above the noise floor.* A pixel must also stand above its depth's noise
  floor (each image row's median plus two robust σ over the sweep, see
  :func:`frame_levels`): where the gain lifts electronic noise above the frame mean, half
  the water would otherwise be "bright" and a clearly visible cap would fail the
  confinement test; a laterally uniform band (ring-down, a plate) stands out less.
- *The plan's window.* With ``expected_depth_mm`` (the protocol's target depth) the
  search covers only ± ``expected_window_mm`` about it and about the centre line, where
  the plan put the sphere: where the cap sinks into the noise floor, the plate under
  the sphere (the same spot from every view, so the siblings agree on it) is not there
  to be found.
- *Hypotheses.* The exhaustive search keeps the grid's ``_HYPOTHESES`` best maxima more
  than R apart and looks at each on a grid twice as fine: a faint thin cap straddled by
  the 1 mm grid recovers its contrast there, a flat reflector does not.
- *Confinement.* Each is judged by ``f_shell − max(f_interior, f_outer)``, ``f_outer`` the
  bright share in the band ``_OUTER_BAND`` × R outside the sphere on the probe side: water
  for a sphere, more of the reflector for a plate. A detection whose cap does not stand
  out from that band by ``min_score`` is rejected with its reason.
- *The specular arc.* Where nothing with a sphere's whole cap is found (an attenuating
  gel, a deep target at low gain: the flanks sink below the noise and only the cap about
  normal incidence echoes), a cone of the shell within ``_ARC_DEG`` of the beam axis is
  searched the same way, confined by the band above it and by its tangent plane (where
  a flat reflector lies and a sphere has no echo).
- *The other sweeps as evidence* (with a calibration, ``consensus=True``): the centres of
  one sphere must agree in the robot base. A seed that disagrees with the densest
  cluster is searched again about it; a centre that still disagrees is rejected with the
  distance, and where no three centres agree none is confirmed (see ``_consensus``,
  ``_reject_disagreeing``).
- *Sub-voxel centre* from the moments of the cap's echo (see ``_refine_centre``), its
  elevation from a least-squares parabola through the cap's peak grey level per slice,
  slices clipped at 255 left out (``_elevation_vertex``); a centre whose elevation that
  fit gives only to worse than ``_MAX_ELEVATION_SIGMA`` (1 σ) is rejected with it.

Frames of one sweep share their orientation (a linear sweep); the re-stack applies each
frame's in-plane and elevational offset and treats the frames as parallel (the residual
rotation between frames of a sweep is the robot's repeatability, micro-radians).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from . import se3
from .baseline import localize_sphere_fixed_threshold
from .localization import LocalizerConfig, SweepLocalization, frame_offsets
from .records import Sweep
from .robust import outlier_limit
from .stacking import (
    LABEL_BRIGHT,
    LABEL_UNIT,
    SweepVolume,
    candidate_step,
    cap_weights,
    grid_sums,
    stack_sweep,
)

__all__ = [
    "SphereProfile",
    "fibonacci_hemisphere",
    "half_ball_samples",
    "localize_sphere",
    "score_candidates",
    "score_candidates_reference",
    "score_grid",
    "sphere_profile",
]

Array = NDArray[np.float64]

_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
_REFINE_ROUNDS = 4
# The confinement test's band (× the CAD radius) on the probe side: a sphere's echo ends
# at its surface, a flat reflector's (a plate, the tank floor) runs on past it.
_OUTER_BAND = (1.3, 1.8)
# Separate local maxima of the coarse grid searched finely (method "refined").
_HYPOTHESES = 4
# A centre whose elevation the cap's echo gives only to worse than this (1 σ, metres) is
# rejected: at 2 σ it could be a millimetre off.
_MAX_ELEVATION_SIGMA = 0.5e-3
_REFINE_TOL = 5e-6  # metres: a twentieth of a pixel
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


def half_ball_samples(n: int, radius: float, inner: float = 0.0) -> Array:
    """``n`` deterministic volume-distributed points (n, 3) in the proximal half-shell
    ``inner ≤ r ≤ radius`` (a half-ball for ``inner = 0``), y ≤ 0."""
    i = np.arange(n) + 0.5
    u = (i * 0.7548776662466927) % 1.0  # R2 sequence, second coordinate: radius
    r = np.cbrt(inner**3 + u * (radius**3 - inner**3))
    return fibonacci_hemisphere(n) * r[:, None]


# ----------------------------------------------------------------------------- scoring


def _offsets_vox(vol: SweepVolume, P: Array) -> NDArray[np.int64]:
    """Sample offsets (m, 3) in metres → integer voxel offsets (m, 3) as (k, r, c), in
    memory order (consecutive lookups then touch neighbouring cache lines)."""
    dx, dy, dz = vol.spacing
    o = np.column_stack(
        [np.rint(P[:, 2] / dz), np.rint(P[:, 1] / dy), np.rint(P[:, 0] / dx)]
    ).astype(np.int64)
    return o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]


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
    sums = np.empty(len(candidates), dtype=np.int64)
    for s in range(0, len(candidates), 2048):
        idx = candidates[s : s + 2048, None, :] + o[None, :, :]
        block = vol.label_at(idx[..., 0], idx[..., 1], idx[..., 2])
        sums[s : s + 2048] = block.sum(axis=1, dtype=np.int64)
    return _bright_fraction(sums, len(o), min_coverage)


def score_grid(
    vol: SweepVolume,
    start: tuple[int, int, int],
    step: tuple[int, int, int],
    count: tuple[int, int, int],
    shell: Array,
    interior: Array,
    min_coverage: float = 0.0,
) -> tuple[Array, Array, Array]:
    """:func:`score_candidates` for a regular grid of candidates, (count) shaped."""
    if step[2] != vol.column_step:
        vol = vol.with_column_step(step[2])
    H, W = vol._frames.shape[1:]
    fractions = {}
    for name, P in (("shell", shell), ("interior", interior)):
        o = _offsets_vox(vol, P)
        sums = grid_sums(
            vol.bits,
            vol._nearest,
            vol._frame_rows,
            vol._frame_cols,
            H,
            W,
            np.asarray(start, dtype=np.int64),
            np.asarray(step, dtype=np.int64),
            np.asarray(count, dtype=np.int64),
            o,
        )
        fractions[name] = _bright_fraction(sums, len(o), min_coverage)
    return _contrast(fractions)


def score_candidates_reference(
    sweep: Sweep,
    T_ee_us: Array | None,
    axial_scale: float,
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
) -> Array:
    """The same scores computed the obvious way, one sample at a time, from the frames.

    For each sample: its voxel (candidate + rounded offset), that voxel's position in the
    reference frame, the nearest frame in elevation, the pixel of that frame under the
    voxel (through the frame's offset), and the comparison with that frame's mean. Slow;
    the test oracle of :func:`score_candidates`.
    """
    offsets = frame_offsets(sweep, T_ee_us)
    n, H, W = sweep.images.shape
    sx, sy = sweep.spacing[0], sweep.spacing[1] * axial_scale
    means = sweep.images.reshape(n, -1).mean(axis=1)
    slice_z = vol.z0 + np.arange(vol.shape[0]) * vol.spacing[2]
    out = np.empty(len(candidates))
    for i, cand in enumerate(candidates):
        fractions = []
        for P in (shell, interior):
            bright = valid = 0
            for o in _offsets_vox(vol, P):
                k, r, c = cand + o
                if not 0 <= k < len(slice_z):
                    continue  # outside the swept elevations
                j = int(np.argmin(np.abs(slice_z[k] - offsets[:, 2])))
                x, y, _ = vol.position(np.float64(k), np.float64(r), np.float64(c))
                # The pixel of frame j under the voxel, through the frame's offset.
                col = int(np.rint((x - offsets[j, 0]) / sx + (W - 1) / 2))
                row = int(np.rint((y - offsets[j, 1]) / sy))
                if not (0 <= row < H and 0 <= col < W):
                    continue
                valid += 1
                bright += int(sweep.images[j, row, col] > means[j])
            fractions.append(bright / valid if valid else np.nan)
        s = fractions[0] - fractions[1]
        out[i] = -np.inf if np.isnan(s) else s
    return out


# ----------------------------------------------------------------------------- search


def _candidate_grid(
    vol: SweepVolume, radius: float, grid: float, cfg: LocalizerConfig | None = None
) -> tuple[tuple[int, int, int], tuple[int, int, int], tuple[int, int, int]]:
    """(start, step, count) in voxels of the 1 mm candidate grid over the sweep, starting
    one radius below the face; with method "refined" and an expected depth, only within
    the plan's window (``expected_window_mm`` about the expected depth and the centre
    line)."""
    dx, dy = vol.spacing[:2]
    K, H, W = vol.shape
    step = candidate_step(vol.spacing, grid)
    lo = [0, max(int(np.ceil(radius / dy)) - vol.row0, 0), 0]
    hi = [K, H, W]  # exclusive
    if cfg is not None and cfg.method == "refined" and cfg.expected_depth_mm is not None:
        half = cfg.expected_window_mm * _M_PER_MM
        depth = cfg.expected_depth_mm * _M_PER_MM
        centre_col = (vol.width - 1) / 2 - vol.col0
        lo[1] = max(lo[1], int(np.ceil((depth - half) / dy)) - vol.row0)
        hi[1] = min(hi[1], int(np.floor((depth + half) / dy)) - vol.row0 + 1)
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
    score, fs, fi = score_grid(vol, start, step, count, shell, interior, min_coverage)
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
    return half_ball_samples(n, _OUTER_BAND[1] * radius, _OUTER_BAND[0] * radius)


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
    chosen: list[NDArray[np.int64]] = []
    where: list[Array] = []
    for i in order:
        if not np.isfinite(flat[i]):
            break
        v = np.array(start) + np.array(step) * np.array(np.unravel_index(i, score.shape))
        p = vol.position(*v.astype(float))
        if all(np.linalg.norm(p - q) > radius for q in where):
            chosen.append(v)
            where.append(p)
            if len(chosen) == k:
                break
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
    score, fs, fi = score_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
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
    score, _, _ = score_grid(vol, start, step, count, arc, interior, cfg.min_coverage)
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


def radial_profile(
    vols: Sequence[SweepVolume], centres_vox: Sequence[Array], radii: Array, n_dirs: int
) -> Array:
    """Peak-normalised bright fraction on proximal hemispheres of trial radius, averaged
    over sweeps; (len(radii),)."""
    dirs = fibonacci_hemisphere(n_dirs)
    total = np.zeros(len(radii))
    count = np.zeros(len(radii))
    for vol, cv in zip(vols, centres_vox, strict=True):
        centre = vol.position(*np.asarray(cv, dtype=float))
        P = centre[None, None, :] + radii[:, None, None] * dirs[None, :, :]
        k, r, c = vol.index(P)
        lab = vol.label_at(k, r, c)
        valid = (lab > 0).sum(axis=1)
        bright = (lab == LABEL_BRIGHT).sum(axis=1)
        ok = valid > 0
        total[ok] += bright[ok] / valid[ok]
        count[ok] += 1
    profile = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    peak = profile.max()
    return profile / peak if peak > 0 else profile


def profile_crossings(
    radii: Array, profile: Array
) -> tuple[float | None, float | None, float | None]:
    """(first rising 0.25 crossing, rising and falling 0.75 crossings around the peak) of
    a peak-normalised radial profile, linearly interpolated; None where it has none."""
    peak = int(np.argmax(profile))

    def crossing(level: float, rising: bool) -> float | None:
        idx = range(1, peak + 1) if rising else range(peak + 1, len(profile))
        for i in idx:
            a, b = profile[i - 1], profile[i]
            if (a < level <= b) if rising else (a >= level > b):
                return float(radii[i - 1] + (level - a) / (b - a) * (radii[i] - radii[i - 1]))
        return None

    return crossing(0.25, True), crossing(0.75, True), crossing(0.75, False)


def profile_bands(radii: Array, profile: Array, radius: float) -> tuple[float, float, float]:
    """(interior limit, shell inner, shell outer) from a peak-normalised radial profile:
    first rising 0.25 crossing; rising and falling 0.75 crossings around the peak. Falls
    back to (0.8 R, 0.9 R, 1.1 R) pieces when a crossing is missing, and to all three
    when the bands are not a shell outside an interior (a profile that peaks at the
    centre, e.g. from sweeps too sparse to resolve the cap, would otherwise turn the
    shell inside out and lose every sweep)."""
    inner, rise, fall = profile_crossings(radii, profile)
    bands = (
        inner if inner is not None else 0.8 * radius,
        rise if rise is not None else 0.9 * radius,
        fall if fall is not None else 1.1 * radius,
    )
    if not bands[0] <= bands[2] or not bands[1] < bands[2]:
        return 0.8 * radius, 0.9 * radius, 1.1 * radius
    return bands


def _refine_centre(vol: SweepVolume, centre: Array, radius: float) -> tuple[Array, float]:
    """Sub-voxel centre from the moments of the cap's echo, and the standard error of its
    elevation (0 where not estimated; see :func:`_elevation_vertex`).

    The probe-facing cap is mirror-symmetric about the centre's lateral and elevational
    coordinates, so the echo-weighted mean of x over the cap gives it, and z is the
    vertex of the top's peak grey level across the slices (:func:`_elevation_vertex`); the
    top of the cap (normal incidence, the strongest echo, seen in every nearby frame
    through the slice thickness) lies one radius above the centre, so the depth of its
    echo's peak (:func:`_axial_peak`) plus R gives y. A least-squares sphere fit would be
    pulled upwards instead: the elevation beam smears that top echo over neighbouring
    frames and flattens the stacked cap. Weights are grey levels above their brightness
    level (the frame mean, and the depth's noise floor with method "refined"); a few
    rounds re-centre the windows.
    """
    dx, dy, dz = vol.spacing
    seed = np.asarray(centre, dtype=float)
    current = seed
    z_sigma = 0.0
    K, H, W = vol.shape
    for _ in range(_REFINE_ROUNDS):
        x_c, y_c, z_c = current
        k0, _, c0 = (int(v) for v in vol.index(current))
        # Cap window: ±R laterally and in elevation, a band of ±R/2 about the cap's depth.
        ks = np.arange(max(k0 - int(radius / dz) - 1, 0), min(k0 + int(radius / dz) + 2, K))
        rs = np.arange(
            max(int((y_c - 1.5 * radius) / dy) - vol.row0, 0),
            min(int((y_c - 0.5 * radius) / dy) - vol.row0 + 1, H),
        )
        cs = np.arange(max(c0 - int(radius / dx) - 1, 0), min(c0 + int(radius / dx) + 2, W))
        if not (len(ks) and len(rs) and len(cs)):
            break
        # Coordinates are separable on the grid: keep them as three axes.
        zs = vol.z0 + ks * dz
        ys = (rs + vol.row0) * dy
        xs = (cs + vol.col0 - (vol.width - 1) / 2) * dx
        # Echo above its level, inside the shell band |d − R| ≤ R/2.
        w = cap_weights(
            vol._frames,
            vol._levels,
            vol._nearest,
            vol._frame_rows,
            vol._frame_cols,
            ks,
            rs,
            cs,
            (zs - z_c) ** 2,
            (ys - y_c) ** 2,
            (xs - x_c) ** 2,
            (0.5 * radius) ** 2,
            (1.5 * radius) ** 2,
        )
        total = w.sum()
        if total <= 0:
            break
        # Each slice's frame sits off its integer stacking shift by up to half a pixel.
        x_new = float(w.sum(axis=(0, 1)) @ xs / total)
        x_new += float(vol.residual_shift(ks, w.sum(axis=(1, 2)))[0])
        z_mean = float(w.sum(axis=(1, 2)) @ zs / total)
        near_x = np.abs(xs - x_new) <= 0.5 * _M_PER_MM
        near_y = np.abs(ys - (y_c - radius)) <= 0.75 * _M_PER_MM
        # Elevation from the top of the cap only (where the echo stands far above noise),
        # over every slice: beyond the elevation focus the beam is wider than a small
        # sphere and its echo of the top follows the beam profile well past ± R.
        # One brightness level for every slice: the vertex of the profile must not move
        # with the level. Each frame's level follows its own rows, and where the sphere's
        # echoes raise the depth's noise floor about the cap, the frames' in-plane drift
        # along the sweep (its axis a little off the image normal) slides the cap across
        # that bump: a level varying linearly with elevation tilts the profile and moved
        # the vertex by up to 0.15 mm at 45 mm.
        ks_all = np.arange(K)
        frame_of = vol._nearest[ks_all]
        rows = np.clip(
            rs[near_y][None, :] - vol._frame_rows[frame_of][:, None], 0, vol._frames.shape[1] - 1
        )
        level = 0.0
        if rows.size:
            level = float(
                np.median(np.take_along_axis(vol._levels[frame_of], rows, axis=1).max(axis=1))
            )
        top = np.maximum(vol.intensity(ks_all, rs[near_y], cs[near_x], level), 0.0)
        # A slice's top at a grey level of 255 is saturated.
        clip = np.full(K, 255.0 - level)
        zs_all = vol.z0 + ks_all * dz
        z_new, z_sigma = _elevation_vertex(
            top, zs_all, z_mean, dz, clip, np.abs(zs_all - z_mean) <= radius
        )
        # Top of the cap: the column under (x, z) in the nearest frames.
        col = np.abs(xs - x_new) <= max(dx, 0.25 * _M_PER_MM)
        frames = np.abs(zs - z_new) <= 0.75 * dz
        wt = w[frames][:, :, col].sum(axis=(0, 2))
        if wt.sum() <= 0:
            break
        y_top = _axial_peak(vol.intensity(ks[frames], rs, cs[col], level), 255.0 - level, ys, wt)
        y_top += float(vol.residual_shift(ks[frames], w[frames][:, :, col].sum(axis=(1, 2)))[1])
        new = np.array([x_new, y_top + radius, z_new])
        moved = np.linalg.norm(new - current)
        current = new
        if moved < _REFINE_TOL:
            break
    # A refinement that wanders far from the grid seed is not trusted.
    if np.linalg.norm(current - seed) > 3.0 * max(dx, dy, dz, _M_PER_MM):
        return seed, 0.0
    return current, z_sigma


def _axial_peak(grey: Array, clip: float, ys: Array, w: Array) -> float:
    """Depth of the cap's top echo: the vertex of the parabola through the brightest row
    of the column's grey levels (``grey`` (slices, rows, columns), less one level, at
    ``clip`` where saturated; rows at depths ``ys``) and its two neighbours.

    The echo of the top is not symmetric in depth: the rest of the cap within the slice
    thickness lies deeper (e²/2R at elevation e), so the echo rises sharply and trails
    off below. Its peak is the top; a weighted mean over the echo lies in its tail, and
    by how much depends on where the brightness level cuts the tail, i.e. on the gain
    (0.08 mm deeper at −10 dB than at 0 dB, 45 mm deep). Where the peak is saturated or
    on the band's edge, the mean of the weights ``w`` (rows) over the echo."""
    profile = grey.sum(axis=(0, 2))
    i = int(np.argmax(profile))
    saturated = (grey[:, max(i - 1, 0) : i + 2] >= clip - 0.5).any()
    if 0 < i < len(profile) - 1 and not saturated:
        g_m, g_0, g_p = profile[i - 1 : i + 2]
        curvature = g_m - 2.0 * g_0 + g_p
        if curvature < 0:
            return float(ys[i] + 0.5 * (g_m - g_p) / curvature * (ys[1] - ys[0]))
    return float(w @ ys / w.sum())


def _elevation_vertex(
    w: Array,
    zs: Array,
    z_mean: float,
    dz: float,
    clip: Array | None = None,
    search: NDArray[np.bool_] | None = None,
) -> tuple[float, float]:
    """Sub-slice elevation of the cap and its standard error (0 where not estimated) from
    its peak grey level per slice (``w`` is
    (slices, ...), ``zs`` the slices' elevations, ``clip`` each slice's ``w`` at a grey
    level of 255, ``search`` the slices where the brightest is looked for).

    The peak grey level per slice is log-compressed (dB), in which a Gaussian beam profile
    is a parabola; its vertex is unbiased where a weighted mean over slices is biased by
    where the centre falls between frames. The parabola is fitted by least squares to the
    contiguous run of slices above half the maximum: three slices where the beam is thin
    (its vertex through them), more where it is wide beyond the elevation focus (there the
    three-slice vertex is a difference of nearly equal noisy peaks). Slices clipped at 255
    (high gain) are left out: the flanks on both sides still fix the vertex of a symmetric
    profile. Without a clipped slice, the fit is then refined in a window centred on its
    own vertex (:func:`_centred_vertex`). Without a usable fit, the midpoint of the
    half-maximum crossings.
    """
    if w.size == 0:
        return z_mean, 0.0
    peaks = w.reshape(len(w), -1).max(axis=1)
    k = int(np.argmax(np.where(search, peaks, -np.inf) if search is not None else peaks))
    if peaks[k] <= 0:
        return z_mean, 0.0
    half = 0.5 * peaks[k]
    lo = hi = k
    while lo > 0 and peaks[lo - 1] >= half:
        lo -= 1
    while hi < len(peaks) - 1 and peaks[hi + 1] >= half:
        hi += 1
    # One slice beyond the run on each side: the parabola needs the fall on both sides.
    lo, hi = max(lo - 1, 0), min(hi + 1, len(peaks) - 1)
    run = np.arange(lo, hi + 1)
    clipped = peaks[run] >= clip[run] - 0.5 if clip is not None else np.zeros(len(run), dtype=bool)
    use = run[~clipped & (peaks[run] > 0)]
    # Slices on both sides of the peak, or on both sides of a clipped top.
    if len(use) >= 3 and (use[0] < k < use[-1] or clipped.any()):
        u = (zs[use] - zs[k]) / dz
        fit = _parabola_vertex(u, peaks[use])
        if fit is not None and u[0] <= fit[0] <= u[-1]:
            if not clipped.any():
                fit = _centred_vertex(peaks, (zs - zs[k]) / dz, fit, 0.25 * (hi - lo), clip)
            return float(zs[k] + fit[0] * dz), fit[1] * dz
    top = run[clipped] if clipped.any() else np.array([k])
    return _half_maximum_midpoint(peaks, zs, int(top[0]), int(top[-1]), z_mean), 0.0


def _centred_vertex(
    peaks: Array, u: Array, start: tuple[float, float], width: float, clip: Array | None
) -> tuple[float, float]:
    """The vertex ``start`` (slices from the brightest, and its standard error) refitted
    with the slices weighted by a Gaussian window centred on the vertex itself (1 σ of
    ``width`` slices, at least one), a few times over.

    The profile in dB is a parabola only near its top (its flanks fall into the speckle
    and level off). A window fixed by which slices clear half the maximum changes as the
    centre moves between two frames, and the shape's departure from a parabola then
    pulls the vertex towards the middle between frames (measured on the twin: ± 0.044 mm
    with the centre's phase between frames 1 mm apart, within 0.057 mm of scatter). A
    window centred on the vertex is symmetric about it whatever the phase: 0.015 mm, and
    0.048 mm of scatter. Where the refit cannot be made (too few slices, a clipped slice
    in the window, a parabola that does not open downwards, a vertex that jumps by more
    than a slice), ``start``."""
    width = max(width, 1.0)
    clipped = peaks >= clip - 0.5 if clip is not None else np.zeros(len(peaks), dtype=bool)
    vertex, sigma = start
    for _ in range(4):
        near = np.abs(u - vertex) <= 3.0 * width
        if clipped[near].any():
            return start
        near &= peaks > 0  # below the brightness level: no echo to fit
        window = np.exp(-0.5 * ((u[near] - vertex) / width) ** 2)
        fit = _parabola_vertex(u[near], peaks[near], window)
        if fit is None or abs(fit[0] - start[0]) > 1.0:
            return start
        moved = abs(fit[0] - vertex)
        vertex, sigma = fit
        if moved < 1e-3:
            break
    return vertex, sigma


def _parabola_vertex(
    u: Array, y: Array, weights: Array | None = None
) -> tuple[float, float] | None:
    """Vertex of the (window-weighted) least-squares parabola through (u, y) and its
    standard error (the points' scatter about it, alike for every point, through the
    fit by the delta method; 0 where fewer than 5 points, in effect, leave no honest
    estimate of it); None unless it opens downwards."""
    if len(u) < 3:
        return None
    wt = np.ones(len(u)) if weights is None else np.asarray(weights, dtype=float)
    V = np.vander(u, 3)
    Minv = np.linalg.pinv(V.T @ (wt[:, None] * V))
    coef = Minv @ (V.T @ (wt * y))
    a, b = coef[0], coef[1]
    if a >= 0:
        return None
    vertex = -b / (2 * a)
    n_effective = wt.sum() ** 2 / np.sum(wt**2)  # Kish's; n for equal weights
    if n_effective - 3 < 2:
        return float(vertex), 0.0
    # The residuals' degrees of freedom under the window: n − 3 for equal weights.
    s2 = float(np.sum(wt * (V @ coef - y) ** 2)) / (wt.sum() * (1 - 3 / n_effective))
    cov = s2 * (Minv @ (V.T @ ((wt**2)[:, None] * V)) @ Minv)[:2, :2]
    g = np.array([b / (2 * a * a), -1 / (2 * a)])  # ∂vertex / ∂(a, b)
    return float(vertex), float(np.sqrt(max(g @ cov @ g, 0.0)))


def _half_maximum_midpoint(
    peaks: Array, zs: Array, first: int, last: int, fallback: float
) -> float:
    """Midpoint of the elevations where ``peaks`` crosses half its maximum below slice
    ``first`` and above slice ``last`` (linearly interpolated); ``fallback`` when the
    profile does not fall to half on both sides."""
    half = 0.5 * peaks[first : last + 1].max()

    def crossing(inner: int, step: int) -> float | None:
        i = inner
        while 0 <= i + step < len(peaks):
            a, b = peaks[i], peaks[i + step]
            if b < half <= a:
                return float(zs[i] + (a - half) / (a - b) * (zs[i + step] - zs[i]))
            i += step
        return None

    lo, hi = crossing(first, -1), crossing(last, +1)
    return fallback if lo is None or hi is None else 0.5 * (lo + hi)


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


def localize_sphere(
    sweeps: Sequence[Sweep],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
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
    >>> from calib.records import Sweep
    >>> z = np.linspace(-5e-3, 5e-3, 21)
    >>> rows, cols = np.mgrid[0:151, 0:151]
    >>> x, y = (cols - 75) * 0.2e-3, rows * 0.2e-3  # the us frame (calib.image)
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
        return localize_sphere_fixed_threshold(sweeps, T_ee_us, radius, cfg, axial_scale)
    grid = cfg.grid_mm * 1e-3
    shell = fibonacci_hemisphere(cfg.shell_samples) * radius
    interior = half_ball_samples(cfg.interior_samples, radius)
    if previous is not None and len(previous) != len(sweeps):
        raise ValueError(f"{len(previous)} previous localizations for {len(sweeps)} sweeps")
    if expected is not None and len(expected) != len(sweeps):
        raise ValueError(f"{len(expected)} expected centres for {len(sweeps)} sweeps")
    vols = []
    for s in sweeps:
        column_step = candidate_step((s.spacing[0], s.spacing[1], 1.0), grid)[2]
        vols.append(stack_sweep(s, T_ee_us, axial_scale, column_step, cfg.method == "refined"))
    results = [
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
    notes: dict[int, str] = {}
    use_consensus = consensus and T_ee_us is not None and cfg.method != "paper"
    if use_consensus:
        results, notes = _consensus(
            sweeps, vols, results, T_ee_us, radius, grid, shell, interior, cfg
        )
    radii = np.arange(0.0, 1.6 * radius, min(vols[0].spacing[:2]))
    for _ in range(cfg.refinement_passes):
        ok = [i for i, r in enumerate(results) if r[1] >= cfg.min_score]
        if not ok:
            break
        profile = radial_profile(
            [vols[i] for i in ok], [results[i][0] for i in ok], radii, cfg.profile_directions
        )
        inner, rise, fall = profile_bands(radii, profile, radius)
        shell_p = half_ball_samples(cfg.shell_samples, fall, rise)
        interior_p = half_ball_samples(cfg.interior_samples, inner)
        results = [
            _best_on_grid(
                vol,
                *_local_window(res[0], vol, cfg.refine_window_mm * 1e-3, grid),
                shell_p,
                interior_p,
                cfg.min_coverage,
            )
            for vol, res in zip(vols, results, strict=True)
        ]
    out = []
    outer = _outer_samples(len(shell), radius)
    for i, (sweep, vol, (cv, score, fs, fi)) in enumerate(zip(sweeps, vols, results, strict=True)):
        centre = vol.position(*np.asarray(cv, dtype=float))
        fo = float("nan")
        z_sigma = 0.0
        accepted = bool(score >= cfg.min_score)
        reason = "" if accepted else notes.get(i, _not_found(score, cfg))
        if accepted and cfg.method == "refined":
            # Evidence beyond the score that picked it: the CAD sphere's cap must stand
            # out from the water just outside it as well (a flat reflector does not).
            fine = _fine_candidates(vol, np.asarray(cv, dtype=np.int64), grid)
            h = _best_nearby(vol, fine, shell, interior, (outer,), 0.0)
            fo = h.f_outer
            if h.f_shell - h.f_outer < cfg.min_score:
                accepted = False
                reason = (
                    f"not a sphere: its echo runs on outside the CAD radius (bright share "
                    f"{h.f_shell:.2f} on the sphere, {h.f_outer:.2f} at "
                    f"{_OUTER_BAND[0]:g}-{_OUTER_BAND[1]:g} R; a flat reflector?)"
                )
            else:
                centre, z_sigma = _refine_centre(vol, centre, radius)
        elif cfg.method == "refined" and i not in notes:
            # Nothing with a sphere's whole cap: perhaps only its specular arc echoes.
            arc = _arc_search(vol, radius, grid, cfg)
            if arc is not None and arc.score >= cfg.min_score:
                accepted, reason = True, ""
                score, fs, fi, fo = arc.score, arc.f_shell, arc.f_interior, arc.f_outer
                seed = vol.position(*arc.voxel.astype(float))
                centre, z_sigma = _refine_centre(vol, seed, radius)
        if accepted and cfg.method == "refined":  # the paper's method as published
            edge = _cut_by_lateral_edge(sweep, centre, radius)
            if edge:
                accepted, reason = False, edge
        if accepted and z_sigma > _MAX_ELEVATION_SIGMA:
            # The cap's echo is about as bright in many frames (a weak echo in a beam
            # wider than the sphere): its elevation is not measured well enough.
            accepted = False
            reason = (
                f"elevation not measured: the cap's echo across the frames gives it to "
                f"± {z_sigma / _M_PER_MM:.2f} mm "
                f"(1 σ; at most {_MAX_ELEVATION_SIGMA / _M_PER_MM:g})"
            )
        out.append(
            SweepLocalization(
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
        )
    if use_consensus:
        out = _reject_disagreeing(sweeps, out, T_ee_us)
    if cfg.method == "refined":
        out = _reject_if_rarely_seen(out)
    return out


_CUT_BY_EDGE = "sphere cut by the image's lateral edge"


def _cut_by_lateral_edge(sweep: Sweep, centre: Array, radius: float) -> str:
    """Why a centre cannot be trusted if the sphere reaches past a lateral edge of the
    image (else ""): its sections there are cut off, and the centre fitted to what is
    left is pulled toward the image (measured on the twin: 0.2-0.5 mm once the sphere
    reaches 1 mm past the edge, against 0.02 mm inside)."""
    half_width = (sweep.images.shape[2] - 1) / 2 * sweep.spacing[0]
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
    # A sphere cut by the image's edge was seen, only not where it can be measured.
    found = sum(r.accepted or r.reason.startswith(_CUT_BY_EDGE) for r in locs)
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
    axial_scale: float = 1.0,
) -> SphereProfile:
    """:func:`radial_profile` and :func:`profile_bands` of localized sweeps, for showing
    what the localizer saw (the stacks are rebuilt under ``T_ee_us``, as the localization
    that produced the centres used)."""
    if len(localizations) != len(sweeps):
        raise ValueError(f"{len(localizations)} localizations for {len(sweeps)} sweeps")
    grid = cfg.grid_mm * 1e-3
    vols, centres = [], []
    for sweep, loc in zip(sweeps, localizations, strict=True):
        if loc.accepted:
            # The localizer's column step: the sweep's bright bits are then the ones it
            # already memoised (no second copy of them).
            step = candidate_step((sweep.spacing[0], sweep.spacing[1], 1.0), grid)[2]
            vol = stack_sweep(sweep, T_ee_us, axial_scale, step, cfg.method == "refined")
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
