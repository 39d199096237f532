"""Volumetric reconstruction of the cone and prism phantoms (paper, "Volumetric
Reconstruction of Different Phantoms").

Per B-mode frame (the central frames of each sweep):

1. **Otsu threshold** (scikit-image) → binary mask, after a light blur about one speckle
   grain wide; the mask closed over about two grains (a rough face's echo is granular).
   Otsu picks the threshold that best splits the frame's own grey-level
   histogram into two classes: like the sphere localizer's per-frame mean, it is derived
   from the image, never set by hand.
2. **Two bright boundaries**: a cross-section near the cone's apex or across the prism's
   ridge shows the two sides of a "Λ". The mask's regions (specks removed) are the
   candidates; lines are fitted robustly to their pixels (RANSAC, then a total-least-squares
   refit with scikit-image), the first line's inliers are removed and the second line is
   fitted to the rest.
3. **Samples**: for each lateral position (image column) along each fitted line, the
   maximum-intensity pixel within a few pixels of the line is the boundary sample.

The samples are mapped to the base frame with the fold's kinematics and ``T_ee_us``,
registered to the CAD surface with point-to-point ICP (Besl & McKay), and scored by their
exact point-to-surface distances.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from skimage.filters import gaussian, threshold_otsu
from skimage.measure import LineModelND, label
from skimage.morphology import isotropic_closing

from .. import se3
from ..image import pixel_to_us

__all__ = [
    "Boundary",
    "ReconstructionConfig",
    "Registration",
    "closest_points",
    "distance_stats",
    "extract_boundaries",
    "register_icp",
    "samples_to_base",
    "surface_distances",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ReconstructionConfig:
    """Cone and prism reconstruction with ICP (Table III), run with the evaluation.

    Paper, "Volumetric Reconstruction of Different Phantoms"; it uses the evaluation's
    three DH models.
    """

    phantoms: tuple[Literal["cone", "prism"], ...] = field(
        default=("cone", "prism"),
        metadata={"doc": "Phantoms scanned and reconstructed (empty: no reconstruction)."},
    )
    central_frames: int = field(
        default=10, metadata={"doc": "Central frames of each sweep used.", "ge": 1, "le": 401}
    )
    icp_max_iterations: int = field(
        default=100, metadata={"doc": "ICP iterations at most.", "ge": 1, "le": 1000}
    )
    icp_points: int = field(
        default=2000,
        metadata={
            "doc": "Points (a random subset) driving the ICP iterations; the distances "
            "reported are those of all points.",
            "ge": 100,
            "le": 1_000_000,
        },
    )
    remount_position_mm: float = field(
        default=1.0,
        metadata={
            "doc": "Simulation: the probe taken off and put back before these scans; its "
            "true mount moves by this (1 σ per axis).",
            "ge": 0,
            "le": 20,
        },
    )
    remount_rotation_deg: float = field(
        default=1.0,
        metadata={"doc": "Simulation: and turns by this (1 σ about each axis).", "ge": 0, "le": 20},
    )
    placement_error_mm: float = field(
        default=5.0,
        metadata={
            "doc": "Simulation: the cone or prism stands up to ± this (x, y) off the "
            "scenario's phantom position, the nominal placement ICP starts from.",
            "ge": 0,
            "le": 50,
        },
    )
    placement_error_deg: float = field(
        default=5.0,
        metadata={
            "doc": "Simulation: and turned up to ± this about the vertical.",
            "ge": 0,
            "le": 45,
        },
    )


@dataclass(frozen=True, eq=False)
class Boundary:
    """One bright boundary of a frame: the fitted line (a point and a unit direction, in
    (column, row) pixels) and its samples (n, 2) as (column, row) pixels."""

    origin: Array
    direction: Array
    samples: Array


def _fit_line(
    points: Array,
    residual_px: float,
    max_points: int,
    trials: int,
    rng: np.random.Generator,
    slope_sign: float = 0.0,
):
    """A robust line through the mask pixels (RANSAC), then the inliers among all pixels
    and a total-least-squares refit (scikit-image's ``LineModelND``).

    Written here rather than with ``skimage.measure.ransac``: that scores one hypothesis
    per Python call (≈ 0.2 ms each, ≈ 60 ms per frame for two lines), while the whole
    batch of hypotheses scores in one array operation (≈ 25× faster), and a
    reconstruction runs it on ≈ 900 frames. Hypotheses are pairs of mask pixels; a
    hypothesis scores the number of pixels (of a random subset of at most ``max_points``)
    within ``residual_px`` of its line. A non-zero ``slope_sign`` keeps only hypotheses
    whose slope (row per column) has that sign.
    """
    if len(points) < 10:
        return None, None
    trial = points
    if len(points) > max_points:
        trial = points[rng.choice(len(points), max_points, replace=False)]
    pairs = rng.integers(0, len(trial), (trials, 2))
    a, b = trial[pairs[:, 0]], trial[pairs[:, 1]]
    d = b - a
    length = np.hypot(d[:, 0], d[:, 1])
    ok = length > 0
    if slope_sign:
        ok &= np.sign(d[:, 0] * d[:, 1]) == slope_sign
    a, n = a[ok], np.column_stack([-d[ok, 1], d[ok, 0]]) / length[ok, None]  # unit normals
    if len(a) == 0:
        return None, None
    # Distance of every subset pixel from every hypothesis line: |(p - a) · n|.
    dist = np.abs(trial @ n.T - np.sum(a * n, axis=1))
    best = int(np.argmax((dist < residual_px).sum(axis=0)))
    inliers = np.abs((points - a[best]) @ n[best]) < residual_px
    if inliers.sum() < 10:
        return None, None
    # Refit to all inliers and take the inliers of the refit line.
    model = LineModelND.from_estimate(points[inliers])
    inliers = model.residuals(points) < residual_px
    if inliers.sum() < 10:
        return None, None
    return model, inliers


def extract_boundaries(
    image: NDArray[np.uint8],
    *,
    pixel_mm: float = 0.1,
    n_boundaries: int = 2,
    residual_mm: float = 0.3,
    search_mm: float = 0.4,
    min_region_mm2: float = 0.3,
    smooth_mm: float = 0.2,
    close_mm: float = 0.4,
    min_length_mm: float = 5.0,
    region_share: float = 0.25,
    min_coverage: float = 0.8,
    max_bright_share: float = 0.2,
    opposite_slopes: bool = True,
    max_points: int = 500,
    trials: int = 100,
    seed: int = 0,
) -> list[Boundary]:
    """The bright boundaries of one frame (see the module docstring).

    Parameters
    ----------
    image : (H, W) uint8
    pixel_mm : the frame's pixel size (mm); the lengths below are converted with it
    n_boundaries : lines to fit (two for a cone or prism section)
    residual_mm : RANSAC inlier distance from a line
    search_mm : per column, the sample is the brightest pixel within ± this of the line
    min_region_mm2 : connected bright regions smaller than this are speckle, not surface
    smooth_mm : Gaussian blur (σ) before the threshold, about a speckle grain
    close_mm : the threshold's mask is closed over a disc of this radius: about two
        speckle grains of a surface echo (a rough or obliquely met face draws a granular,
        broken line whose grains are ≈ 0.2-0.3 mm along it for a 13 MHz probe)
    min_length_mm : a boundary's inliers span at least this length along its line
    region_share : candidate regions are the mask's connected regions at least this
        share of the largest one's area
    min_coverage : share of a boundary's span along which its line runs inside the
        candidate regions, at least
    max_bright_share : the bright (above-Otsu) class is at most this share of the frame
        (two boundary sections about a millimetre thick cover a few per cent); when more,
        the frame has no boundary to speak of and Otsu has split the speckle itself
    opposite_slopes : the second line slopes the other way (the two sides of a "Λ")
    max_points : mask pixels RANSAC scores its hypotheses on (a random subset)
    trials : RANSAC hypotheses per line
    seed : RANSAC's random seed (deterministic results)

    None of these is an intensity: the only grey level used, Otsu's, comes from the frame.
    """
    img = np.asarray(image)
    H, W = img.shape
    if img.max() == img.min():
        return []
    residual_px = residual_mm / pixel_mm
    search_px = max(1, round(search_mm / pixel_mm))
    min_length_px = min_length_mm / pixel_mm
    # The mask and the lines are found on the frame binned to pixels of about the blur's
    # size (a 2 × 2 mean at 0.1 mm pixels: itself a light blur, and 4× fewer pixels to
    # threshold, label and fit); the samples come from the full frame.
    b = max(1, round(smooth_mm / pixel_mm))
    Hb, Wb = H // b, W // b
    # (A sum of the b × b strided sub-grids: numpy's mean over the reshaped axes (1, 3)
    # takes ≈ 8× longer, ≈ 2.6 ms of a frame's ≈ 10.)
    full = img[: Hb * b, : Wb * b].astype(np.float32)
    coarse = sum(full[i::b, j::b] for i in range(b) for j in range(b)) / np.float32(b * b)
    # Speckle is grainy at the scale of the resolution cell; a light blur before Otsu keeps
    # single grains out of the mask.
    sigma = np.sqrt(max((smooth_mm / pixel_mm) ** 2 - (b**2 - 1) / 12, 0.0)) / b
    if sigma > 0.3:
        coarse = gaussian(coarse, sigma=sigma, truncate=3.0, preserve_range=True)
    coarse = np.rint(coarse).astype(np.uint8)  # grey levels again: Otsu's histogram by count
    mask = coarse > threshold_otsu(coarse)
    if mask.mean() > max_bright_share:
        return []
    # A granular surface echo (speckle along a rough or obliquely met face) leaves its
    # mask broken into grains with dark gaps of about a grain between them: closing the
    # mask over a disc of radius ``close_mm`` joins them into one region along the
    # surface, without merging separate bands further apart than the disc's diameter.
    radius = round(close_mm / (b * pixel_mm))
    if radius >= 1:
        mask = isotropic_closing(mask, radius)
    # Candidate regions: the mask's large connected regions. A boundary crossing the
    # frame is one long region; the speckle left above the threshold is many small ones
    # (isolated specks below ``min_region_mm2`` are never surfaces).
    labels = label(mask, connectivity=2)
    if labels.max() == 0:
        return []
    areas = np.bincount(labels.ravel())
    areas[0] = 0
    keep = areas >= max(min_region_mm2 / (b * pixel_mm) ** 2, region_share * areas.max())
    candidate = keep[labels]
    rows, cols = np.nonzero(candidate)
    # Bin centres in full-frame pixels.
    points = np.column_stack([cols, rows]).astype(float) * b + (b - 1) / 2
    rng = np.random.default_rng(seed)
    out: list[Boundary] = []
    sign = 0.0
    for _ in range(n_boundaries):
        model, inliers = _fit_line(points, residual_px, max_points, trials, rng, sign)
        if model is None:
            break
        origin = np.asarray(model.origin, dtype=float)
        direction = np.asarray(model.direction, dtype=float)
        if abs(direction[0]) < 1e-6 or np.ptp(points[inliers] @ direction) < min_length_px:
            break  # vertical (no row per column) or too short: not a boundary section
        # A boundary is continuous: the line runs inside the candidate regions nearly all
        # along its span. A line through speckle (a frame without a boundary in view,
        # where Otsu splits the speckle itself) runs inside them only part of the way.
        span = points[inliers, 0]
        c = np.arange(max(int(np.ceil(span.min())), 0), min(int(np.floor(span.max())), W - 1) + 1)
        r_line = np.rint(origin[1] + (c - origin[0]) * direction[1] / direction[0]).astype(int)
        rb, cb = r_line // b, c // b
        on = (rb >= 0) & (rb < Hb) & (cb < Wb)
        coverage = float(candidate[rb[on], cb[on]].mean()) if on.any() else 0.0
        if coverage < min_coverage:
            break
        if opposite_slopes:
            sign = -np.sign(direction[0] * direction[1])
        # Per column along the line's span: the brightest pixel within ± search_px rows.
        span = points[inliers, 0]
        c = np.arange(max(int(np.ceil(span.min())), 0), min(int(np.floor(span.max())), W - 1) + 1)
        r_line = origin[1] + (c - origin[0]) * direction[1] / direction[0]
        window = np.floor(r_line).astype(int)[:, None] + np.arange(-search_px, search_px + 2)
        inside = (window >= 0) & (window < H)
        values = np.where(inside, img[np.clip(window, 0, H - 1), c[:, None]], -1)
        r = window[np.arange(len(c)), np.argmax(values, axis=1)]
        # Only where the boundary is there: the brightest pixel lies in a candidate region
        # (where the section curves away from the line, e.g. off the cone's apex, the
        # window holds only speckle, and its brightest pixel is no boundary sample).
        keep = inside.any(axis=1) & (c // b < Wb)
        keep[keep] &= candidate[np.minimum(r[keep] // b, Hb - 1), c[keep] // b]
        samples = np.column_stack([c[keep], r[keep]]).astype(float)
        out.append(Boundary(origin, direction, samples.reshape(-1, 2)))
        points = points[~inliers]
    return out


def samples_to_base(
    samples: Array, width: int, spacing: tuple[float, float], T_base_us: Array
) -> Array:
    """Boundary samples (n, 2) (column, row) of one frame to base-frame points (n, 3)."""
    P = pixel_to_us(samples[:, 1], samples[:, 0], width, spacing)
    return se3.apply(T_base_us, P)


@dataclass(frozen=True, eq=False)
class Registration:
    """ICP result: ``T`` maps the reconstructed points onto the CAD surface (applied to
    the points), ``distances_mm`` the point-to-surface distances of *all* points after it,
    ``iterations`` the ICP iterations run."""

    T: Array
    distances_mm: Array
    iterations: int


#: Meshes with at most this many faces use the exact all-faces kernel below; larger ones
#: trimesh's closest-point query.
_BRUTE_FORCE_FACES = 4096


def closest_points(mesh: trimesh.Trimesh, points: ArrayLike) -> tuple[Array, Array]:
    """Closest point on the mesh surface (n, 3) and its distance (n,) for each point.

    For the phantoms (convex CAD meshes of 8-200 faces) every point is tested against
    every face by a compiled kernel: exact, and ≈ 100× faster than trimesh's
    ``proximity.closest_point`` there (its bounding-box candidate search degenerates on
    long, thin faces such as a cone's sides; measured ≈ 4 s per 20 000 points on the cone,
    and ≈ 5 % of its answers up to 0.04 mm off). Large meshes use trimesh.
    """
    P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    if len(mesh.faces) > _BRUTE_FORCE_FACES:
        closest, d, _ = trimesh.proximity.closest_point(mesh, P)
        return np.asarray(closest), np.asarray(d)
    tri = np.ascontiguousarray(mesh.triangles, dtype=float)
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    # Unit face normals from the triangles themselves (degenerate faces: a zero normal,
    # so their plane bound never skips them).
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    offset = np.einsum("ij,ij->i", normal, tri[:, 0])
    closest = np.empty_like(P)
    d2 = np.empty(len(P))
    if len(P) and len(tri):
        _closest_on_triangles(P, tri, centre, radius, normal, offset, closest, d2)
    else:
        d2[:] = np.inf
    return closest, np.sqrt(d2)


@numba.njit(cache=True, nogil=True, boundscheck=False, inline="always")
def _on_triangle(px, py, pz, tri, f):  # pragma: no cover - compiled
    """Closest point of triangle ``f`` to p and its squared distance (Ericson, *Real-Time
    Collision Detection*, §5.1.5: the Voronoi region of the triangle's features that
    holds p)."""
    ax, ay, az = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
    abx, aby, abz = tri[f, 1, 0] - ax, tri[f, 1, 1] - ay, tri[f, 1, 2] - az
    acx, acy, acz = tri[f, 2, 0] - ax, tri[f, 2, 1] - ay, tri[f, 2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        u, v = 0.0, 0.0  # vertex A
    else:
        bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        if d3 >= 0.0 and d4 <= d3:
            u, v = 1.0, 0.0  # vertex B
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                u, v = d1 / (d1 - d3), 0.0  # edge AB
            else:
                cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
                d5 = abx * cpx + aby * cpy + abz * cpz
                d6 = acx * cpx + acy * cpy + acz * cpz
                if d6 >= 0.0 and d5 <= d6:
                    u, v = 0.0, 1.0  # vertex C
                else:
                    vb = d5 * d2 - d1 * d6
                    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                        u, v = 0.0, d2 / (d2 - d6)  # edge AC
                    else:
                        va = d3 * d6 - d5 * d4
                        if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))  # edge BC
                            u, v = 1.0 - w, w
                        else:
                            den = 1.0 / (va + vb + vc)  # inside the face
                            u, v = vb * den, vc * den
    qx = ax + u * abx + v * acx
    qy = ay + u * aby + v * acy
    qz = az + u * abz + v * acz
    return qx, qy, qz, (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _closest_on_triangles(P, tri, centre, radius, normal, offset, closest, d2):  # pragma: no cover
    """For each point the closest point over all triangles.

    A face cannot hold the closest point when its bounding sphere (``centre``,
    ``radius``) or its plane (unit ``normal``, ``offset`` = n · a) lies farther than the
    best distance so far; both bounds are a few multiplications. The search starts from
    the previous point's face: consecutive points (a boundary's samples in scan order) lie
    on the same face, so the best distance is small from the start and the bounds skip
    almost every other face (the sphere bound alone keeps every side of a cone, whose long
    thin faces all reach the apex).
    """
    last = 0
    for i in range(P.shape[0]):
        px, py, pz = P[i, 0], P[i, 1], P[i, 2]
        bx, by, bz, best = _on_triangle(px, py, pz, tri, last)
        best_d = np.sqrt(best)
        best_f = last
        for f in range(tri.shape[0]):
            if f == last:
                continue
            plane = normal[f, 0] * px + normal[f, 1] * py + normal[f, 2] * pz - offset[f]
            if abs(plane) > best_d:
                continue
            cx, cy, cz = px - centre[f, 0], py - centre[f, 1], pz - centre[f, 2]
            reach = best_d + radius[f]
            if cx * cx + cy * cy + cz * cz > reach * reach:
                continue
            qx, qy, qz, dd = _on_triangle(px, py, pz, tri, f)
            if dd < best:
                best, bx, by, bz, best_f = dd, qx, qy, qz, f
                best_d = np.sqrt(dd)
        last = best_f
        closest[i, 0], closest[i, 1], closest[i, 2] = bx, by, bz
        d2[i] = best


def surface_distances(mesh: trimesh.Trimesh, points: ArrayLike) -> Array:
    """Unsigned distance (same unit as the mesh) of each point to the mesh surface."""
    return closest_points(mesh, points)[1]


def register_icp(
    points: ArrayLike,
    mesh: trimesh.Trimesh,
    *,
    initial: ArrayLike | None = None,
    max_iterations: int = 100,
    tolerance: float = 1e-8,
    max_points: int = 2000,
    seed: int = 0,
) -> Registration:
    """Point-to-point ICP (Besl & McKay) of points (metres) onto a mesh surface, from
    ``initial`` (e.g. the nominal placement; identity by default).

    Each iteration pairs every point with its exact closest surface point
    (:func:`closest_points`) and solves the best rigid motion for the pairs (trimesh's
    ``registration.procrustes``, no scale or reflection). It stops when the RMS distance
    improves by less than ``tolerance`` (metres) — sliding along a symmetry of the shape
    (about the cone's axis, along the prism's ridge) changes nothing — or after
    ``max_iterations``. A random subset of at most ``max_points`` points drives the
    iterations (a cone scan has ≈ 10⁵); the distances returned are those of all points.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    T = np.eye(4) if initial is None else np.asarray(initial, dtype=float).copy()
    rng = np.random.default_rng(seed)
    # The subset keeps the points' order (see :func:`_closest_on_triangles`).
    drive = P if len(P) <= max_points else P[np.sort(rng.choice(len(P), max_points, replace=False))]
    previous = np.inf
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 - reported below
        moved = se3.apply(T, drive)
        target, d = closest_points(mesh, moved)
        rms = float(np.sqrt(np.mean(d**2)))
        if previous - rms < tolerance:
            break
        previous = rms
        step, _, _ = trimesh.registration.procrustes(
            moved, target, reflection=False, scale=False, return_cost=True
        )
        T = step @ T
    return Registration(T, surface_distances(mesh, se3.apply(T, P)) * 1e3, iterations)


def distance_stats(distances_mm: ArrayLike) -> dict[str, float]:
    """Table III's statistics of point-to-surface distances: MAE, SD, RMSE, Max (mm)."""
    d = np.abs(np.asarray(distances_mm, dtype=float))
    if len(d) == 0:
        return {"mae": float("nan"), "sd": float("nan"), "rmse": float("nan"), "max": float("nan")}
    return {
        "mae": float(d.mean()),
        "sd": float(d.std(ddof=1)) if len(d) > 1 else float("nan"),
        "rmse": float(np.sqrt(np.mean(d**2))),
        "max": float(d.max()),
    }
