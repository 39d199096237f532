"""Volumetric reconstruction of the cone and prism phantoms (paper, "Volumetric
Reconstruction of Different Phantoms").

Per B-mode frame (the central frames of each sweep):

1. **Otsu threshold** (scikit-image) → binary mask, after a light blur about one speckle
   grain wide. Otsu picks the threshold that best splits the frame's own grey-level
   histogram into two classes: like the sphere localizer's per-frame mean, it is derived
   from the image, never set by hand.
2. **Two bright boundaries**: a cross-section near the cone's apex or across the prism's
   ridge shows the two sides of a "Λ". The mask's regions (specks removed) are the
   candidates; lines are fitted robustly (RANSAC, scikit-image) to their pixels, the first
   line's inliers are removed and the second line is fitted to the rest.
3. **Samples**: for each lateral position (image column) along each fitted line, the
   maximum-intensity pixel within a few pixels of the line is the boundary sample.

The samples are mapped to the base frame with the fold's kinematics and ``T_ee_us``,
registered to the CAD surface with point-to-point ICP (Besl & McKay; trimesh), and scored
by their point-to-surface distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from skimage.filters import gaussian, threshold_otsu
from skimage.measure import LineModelND, ransac
from skimage.morphology import remove_small_objects

from . import se3
from .image import pixel_to_us

__all__ = [
    "Boundary",
    "Registration",
    "distance_stats",
    "extract_boundaries",
    "register_icp",
    "samples_to_base",
    "surface_distances",
]

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Boundary:
    """One bright boundary of a frame: the fitted line (a point and a unit direction, in
    (column, row) pixels) and its samples (n, 2) as (column, row) pixels."""

    origin: Array
    direction: Array
    samples: Array


def _fit_line(points: Array, residual_px: float, rng: np.random.Generator):
    if len(points) < 10:
        return None, None
    model, inliers = ransac(
        points,
        LineModelND,
        min_samples=2,
        residual_threshold=residual_px,
        max_trials=200,
        rng=rng,
    )
    if model is None or inliers is None or inliers.sum() < 10:
        return None, None
    return model, inliers


def extract_boundaries(
    image: NDArray[np.uint8],
    n_boundaries: int = 2,
    residual_px: float = 3.0,
    search_px: int = 4,
    min_region_px: int = 30,
    smooth_px: float = 2.0,
    seed: int = 0,
) -> list[Boundary]:
    """The bright boundaries of one frame (see the module docstring).

    Parameters
    ----------
    image : (H, W) uint8
    n_boundaries : lines to fit (two for a cone or prism section)
    residual_px : RANSAC inlier distance from a line, pixels
    search_px : per column, the sample is the brightest pixel within ± this many rows of
        the fitted line
    min_region_px : connected bright regions smaller than this are speckle, not surface
    smooth_px : Gaussian blur (σ, pixels) before the threshold, about a speckle grain
    seed : RANSAC's random seed (deterministic results)
    """
    img = np.asarray(image)
    H, W = img.shape
    if img.max() == img.min():
        return []
    # Speckle is grainy at the scale of the resolution cell; a light blur before Otsu keeps
    # single grains out of the mask (the samples below come from the unblurred frame).
    smooth = gaussian(img.astype(float), sigma=smooth_px, preserve_range=True)
    mask = smooth > threshold_otsu(smooth)
    # Isolated specks above the threshold are not surfaces.
    mask = remove_small_objects(mask, max_size=min_region_px - 1)
    rows, cols = np.nonzero(mask)
    points = np.column_stack([cols, rows]).astype(float)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_boundaries):
        model, inliers = _fit_line(points, residual_px, rng)
        if model is None:
            break
        origin = np.asarray(model.origin, dtype=float)
        direction = np.asarray(model.direction, dtype=float)
        if abs(direction[0]) < 1e-6:
            points = points[~inliers]
            continue  # a vertical line has no row per column: not a boundary section
        span = points[inliers, 0]
        samples = []
        for c in range(int(np.ceil(span.min())), int(np.floor(span.max())) + 1):
            r_line = origin[1] + (c - origin[0]) * direction[1] / direction[0]
            lo = max(int(np.floor(r_line)) - search_px, 0)
            hi = min(int(np.ceil(r_line)) + search_px + 1, H)
            if hi <= lo or not 0 <= c < W:
                continue
            r = lo + int(np.argmax(img[lo:hi, c]))
            samples.append((c, r))
        out.append(Boundary(origin, direction, np.array(samples, dtype=float).reshape(-1, 2)))
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
    the points), ``distances_mm`` their point-to-surface distances after it."""

    T: Array
    distances_mm: Array


def surface_distances(mesh: trimesh.Trimesh, points: ArrayLike) -> Array:
    """Unsigned distance (same unit as the mesh) of each point to the mesh surface."""
    _, d, _ = trimesh.proximity.closest_point(mesh, np.asarray(points, dtype=float))
    return d


def register_icp(
    points: ArrayLike,
    mesh: trimesh.Trimesh,
    initial: ArrayLike | None = None,
    max_iterations: int = 50,
    threshold: float = 1e-12,
    refine_iterations: int = 5,
    surface_samples: int = 100_000,
) -> Registration:
    """Point-to-point ICP (Besl & McKay) of points (metres) onto a mesh surface, from
    ``initial`` (e.g. the nominal placement; identity by default), with trimesh's
    implementation.

    The iterations run first against a dense, even sample of the surface (nearest
    neighbours from a KD-tree: trimesh's exact closest-point query on the mesh costs ≈ 30×
    more per iteration), then ``refine_iterations`` more against the exact surface, which
    removes the sampling's small bias. Distances are point-to-surface.
    """
    P = np.asarray(points, dtype=float)
    T0 = np.eye(4) if initial is None else np.asarray(initial, dtype=float)
    cloud, _ = trimesh.sample.sample_surface_even(mesh, surface_samples, seed=0)
    T, moved = T0, se3.apply(T0, P)
    for target, iterations in ((cloud, max_iterations), (mesh, refine_iterations)):
        if iterations > 0:
            T, moved, _ = trimesh.registration.icp(
                P,
                target,
                initial=T,
                threshold=threshold,
                max_iterations=iterations,
                reflection=False,
                scale=False,
            )
    return Registration(np.asarray(T), surface_distances(mesh, moved) * 1e3)


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
