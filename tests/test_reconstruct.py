"""Cone/prism reconstruction building blocks (calib/evaluation/reconstruct.py): boundary extraction
on synthetic frames with known lines, ICP on a sampled CAD surface, Table III statistics."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from calib import se3
from calib.evaluation.reconstruct import (
    closest_points,
    distance_stats,
    extract_boundaries,
    register_icp,
    samples_to_base,
    surface_distances,
)


def lambda_frame(rng, apex=(190.0, 120.0), slope=0.8, H=400, W=380):
    """A frame like the simulator's section of the cone near its apex: a bright "Λ" (two
    lines of ± slope from an apex at (column, row)) over grainy speckle and noise
    everywhere; returns the image and the true row of each line per column."""
    c = np.arange(W)
    left = apex[1] + slope * (apex[0] - c)  # the left side (c ≤ apex column)
    right = apex[1] + slope * (c - apex[0])
    r = np.arange(H)[:, None]
    img = rng.gamma(1.2, 14.0, (H, W))  # speckle and noise: grainy, up to ≈ 100
    for rows, keep in ((left, c <= apex[0]), (right, c >= apex[0])):
        img[:, keep] += 180 * np.exp(-0.5 * ((r - rows[keep][None, :]) / 1.5) ** 2)
    return np.clip(img, 0, 255).astype(np.uint8), left, right


def test_two_boundaries_of_a_lambda_are_found(rng):
    img, left, right = lambda_frame(rng)
    bounds = extract_boundaries(img)
    assert len(bounds) == 2
    c = np.arange(img.shape[1])
    errors = []
    for b in bounds:
        slope = b.direction[1] / b.direction[0]
        assert abs(abs(slope) - 0.8) < 0.02
        truth = left if slope < 0 else right
        cols = b.samples[:, 0].astype(int)
        errors.append(np.abs(b.samples[:, 1] - truth[cols]))
        # Samples cover that side of the Λ.
        assert len(cols) > 100
        assert set(cols) <= set(c)
    assert np.median(np.concatenate(errors)) <= 1.0
    assert np.percentile(np.concatenate(errors), 95) <= 2.0


def test_a_blank_frame_has_no_boundary():
    assert extract_boundaries(np.full((50, 40), 7, dtype=np.uint8)) == []


def test_a_frame_of_speckle_alone_has_no_boundary(rng):
    """No surface in view: Otsu splits the speckle itself; no line may come out of it."""
    for seed in range(5):
        img = np.random.default_rng(seed).gamma(1.2, 14.0, (400, 380)).clip(0, 255)
        assert extract_boundaries(img.astype(np.uint8), seed=seed) == []


def test_the_two_sides_are_found_beside_a_parallel_ghost(rng):
    """A fainter band parallel to one side (an echo of the same surface from another part
    of the beam) must not be taken for the other side: the two lines slope opposite ways
    and follow the true sides."""
    img, left, right = lambda_frame(rng)
    r = np.arange(img.shape[0])[:, None]
    c = np.arange(img.shape[1])
    ghost = left + 12.0
    keep = c <= 190
    extra = 90 * np.exp(-0.5 * ((r - ghost[keep][None, :]) / 1.5) ** 2)
    img = img.astype(float)
    img[:, keep] += extra
    bounds = extract_boundaries(np.clip(img, 0, 255).astype(np.uint8))
    assert len(bounds) == 2
    slopes = sorted(b.direction[1] / b.direction[0] for b in bounds)
    assert slopes[0] < 0 < slopes[1]
    for b in bounds:
        truth = left if b.direction[1] / b.direction[0] < 0 else right
        cols = b.samples[:, 0].astype(int)
        assert np.median(np.abs(b.samples[:, 1] - truth[cols])) <= 1.0


def test_samples_map_through_the_image_frame():
    samples = np.array([[0.0, 0.0], [10.0, 20.0]])  # (column, row)
    P = samples_to_base(samples, 21, (1e-3, 2e-3), np.eye(4))
    np.testing.assert_allclose(P, [[-10e-3, 0.0, 0.0], [0.0, 40e-3, 0.0]])


@pytest.mark.parametrize("shape", ["cone", "prism"])
def test_icp_recovers_a_known_rigid_perturbation(shape):
    if shape == "cone":
        mesh = trimesh.creation.cone(radius=0.03, height=0.04464, sections=96)
    else:
        mesh = trimesh.convex.convex_hull(
            np.array(
                [
                    [-0.06, -0.03, 0],
                    [0.06, -0.03, 0],
                    [-0.06, 0.03, 0],
                    [0.06, 0.03, 0],
                    [-0.06, 0, 0.04464],
                    [0.06, 0, 0.04464],
                ]
            )
        )
    pts, _ = trimesh.sample.sample_surface(mesh, 1500, seed=1)
    perturb = se3.exp(np.array([1.5e-3, -1.0e-3, 0.8e-3, 0.02, -0.015, 0.01]))
    moved = se3.apply(perturb, pts)
    assert surface_distances(mesh, moved).max() > 1e-3  # really off before ICP
    reg = register_icp(moved, mesh, max_iterations=300, tolerance=1e-12)
    assert reg.distances_mm.max() <= 0.01
    back = se3.apply(reg.T, moved)
    if shape == "cone":
        # A turn about the cone's axis is a symmetry: compare what it leaves unchanged.
        inv = lambda p: np.column_stack([np.hypot(p[:, 0], p[:, 1]), p[:, 2]])  # noqa: E731
        assert np.abs(inv(back) - inv(pts)).max() <= 0.01e-3
    else:
        # The registration undoes the perturbation: every point back in its place.
        assert np.abs(back - pts).max() <= 0.01e-3


@pytest.mark.parametrize("shape", ["cone", "prism"])
def test_closest_points_are_exact(shape, rng):
    """The all-faces kernel against trimesh's per-triangle closest point, every point
    against every face (the definition), for points inside, on and around the mesh."""
    if shape == "cone":
        mesh = trimesh.creation.cone(radius=0.03, height=0.04464, sections=48)
    else:
        mesh = trimesh.creation.box((0.12, 0.06, 0.04))
    pts = rng.uniform(mesh.bounds[0] - 0.01, mesh.bounds[1] + 0.01, (400, 3))
    pts = np.vstack([pts, mesh.vertices, trimesh.sample.sample_surface(mesh, 100, seed=2)[0]])
    tri = mesh.triangles
    brute = trimesh.triangles.closest_point(
        np.tile(tri, (len(pts), 1, 1)), np.repeat(pts, len(tri), axis=0)
    ).reshape(len(pts), len(tri), 3)
    d_brute = np.linalg.norm(brute - pts[:, None], axis=2)
    closest, d = closest_points(mesh, pts)
    np.testing.assert_allclose(d, d_brute.min(axis=1), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(closest - pts, axis=1), d, atol=1e-12)
    assert np.abs(d[400 : 400 + len(mesh.vertices)]).max() < 1e-12  # vertices lie on it


def test_distance_statistics():
    s = distance_stats([0.1, 0.2, 0.3, 0.4])
    assert s["mae"] == pytest.approx(0.25)
    assert s["sd"] == pytest.approx(np.std([0.1, 0.2, 0.3, 0.4], ddof=1))
    assert s["rmse"] == pytest.approx(np.sqrt(0.075))
    assert s["max"] == pytest.approx(0.4)


def test_boundaries_of_a_rendered_cone_lie_on_its_surface():
    """A frame the twin renders over the cone's apex: the extracted samples, mapped with
    the true kinematics and probe mount, lie on the true (printed) cone surface."""
    from bench.acquire_sim import make_imager, make_twin
    from bench.config.scenario import load_scenario
    from calib.acquisition.protocol import facing_pose

    s = load_scenario(None, ["robot.dh_error_scale=0", "phantom.kind=cone"], check_reach=False)
    twin = make_twin(s)
    imager = make_imager(s, twin)
    truth = twin.truth
    T_face = facing_pose(truth.landmarks_base["apex"], 20e-3)
    twin.robot.teach(T_face @ se3.invert(truth.T_ee_us))
    frame = imager.grab()
    bounds = extract_boundaries(frame.image, pixel_mm=frame.spacing[0] * 1e3)
    assert len(bounds) == 2
    T_base_us = twin.robot.truth.T_base_ee @ truth.T_ee_us
    W = frame.image.shape[1]
    sx, sy = frame.spacing
    from bench.config.method import axial_scale

    spacing = (sx, sy * axial_scale(s))
    P = np.concatenate([samples_to_base(b.samples, W, spacing, T_base_us) for b in bounds])
    printed = twin.scene.scene.phantom.mesh()
    d = surface_distances(printed, se3.apply(se3.invert(truth.T_base_phantom), P)) * 1e3
    assert len(P) > 150
    assert np.median(d) <= 0.3
    assert np.percentile(d, 95) <= 0.6
