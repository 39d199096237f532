"""Phantom dimensions (the paper's numbers), landmarks, convexity, tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from twin.phantoms import PhantomConfig, build_phantom, build_tank, phantom_pair

MM = 1e-3
GEOM_TOL = 1e-4 * MM  # mesh construction is exact up to float rounding / facet sagitta


def test_four_sphere_phantom_layout():
    p = build_phantom(PhantomConfig())
    centres = np.array([p.landmarks[f"sphere_{i}"] for i in range(1, 5)])
    vertices = np.array([p.landmarks[f"vertex_{j}"] for j in range(1, 5)])
    # Corners of a 50 mm square, radius 5 mm.
    sides = np.linalg.norm(np.roll(centres, -1, axis=0) - centres, axis=1)
    np.testing.assert_allclose(sides, 50 * MM, atol=GEOM_TOL)
    np.testing.assert_allclose(np.linalg.norm(centres[0] - centres[2]), 50 * np.sqrt(2) * MM)
    assert all(r == pytest.approx(5 * MM) for r in p.sphere_radii.values())
    # The sphere mesh really has that radius around that centre (icosphere: ≤ 4 µm sagitta).
    sphere = {part.name: part.mesh for part in p.parts}["sphere_1"]
    dist = np.linalg.norm(sphere.vertices - centres[0], axis=1)
    np.testing.assert_allclose(dist, 5 * MM, atol=1e-9)
    # Touch vertices in the plane of the sphere centres, outside the square.
    np.testing.assert_allclose(vertices[:, 2], centres[0, 2])
    assert np.all(np.linalg.norm(vertices[:, :2], axis=1) > 25 * MM * np.sqrt(2))
    # Every part is a closed convex solid (MuJoCo collides convex hulls).
    assert all(part.mesh.is_watertight and part.mesh.is_convex for part in p.parts)
    # The cone tips are the vertex landmarks.
    for j, v in enumerate(vertices, start=1):
        cone = {part.name: part.mesh for part in p.parts}[f"vertex_cone_{j}"]
        top = cone.vertices[np.argmax(cone.vertices[:, 2])]
        np.testing.assert_allclose(top, v, atol=GEOM_TOL)


def test_cone_dimensions():
    mesh = build_phantom(PhantomConfig(kind="cone")).mesh()
    lo, hi = mesh.bounds
    np.testing.assert_allclose(hi - lo, [60 * MM, 60 * MM, 44.64 * MM], atol=GEOM_TOL)
    assert mesh.is_watertight and mesh.is_convex
    # Volume of a cone: π r² h / 3 (faceted: slightly less).
    assert mesh.volume == pytest.approx(np.pi * (30 * MM) ** 2 * 44.64 * MM / 3, rel=2e-3)


def test_prism_dimensions():
    p = build_phantom(PhantomConfig(kind="prism"))
    mesh = p.mesh()
    lo, hi = mesh.bounds
    np.testing.assert_allclose(hi - lo, [120 * MM, 60 * MM, 44.64 * MM], atol=GEOM_TOL)
    assert mesh.volume == pytest.approx(0.5 * 60 * MM * 44.64 * MM * 120 * MM, rel=1e-9)
    ridge = p.landmarks["ridge_end"] - p.landmarks["ridge_start"]
    np.testing.assert_allclose(ridge, [120 * MM, 0, 0])
    np.testing.assert_allclose(p.landmarks["ridge_start"][2], 44.64 * MM)


def test_tolerance_perturbs_truth_not_cad(rng):
    cfg = PhantomConfig(tolerance_radius_mm=0.1, tolerance_position_mm=0.2)
    cad, true = phantom_pair(cfg, rng)
    assert cad.landmarks["sphere_1"] == pytest.approx(build_phantom(cfg).landmarks["sphere_1"])
    moved = [np.linalg.norm(true.landmarks[k] - cad.landmarks[k]) for k in cad.landmarks]
    assert 0 < np.mean(moved) < 1 * MM
    radii = np.array(list(true.sphere_radii.values()))
    assert np.all(radii != 5 * MM) and np.all(np.abs(radii - 5 * MM) < 0.6 * MM)
    # Zero tolerance: the printed phantom is the CAD.
    cad0, true0 = phantom_pair(PhantomConfig(tolerance_radius_mm=0, tolerance_position_mm=0), rng)
    for k in cad0.landmarks:
        np.testing.assert_array_equal(cad0.landmarks[k], true0.landmarks[k])


def test_tank_encloses_water():
    cfg = PhantomConfig()
    tank = build_tank(cfg)
    lo, hi = tank.mesh().bounds
    inner = np.array(cfg.tank_inner_mm) * MM
    t = cfg.tank_wall_mm * MM
    np.testing.assert_allclose(hi - lo, inner + np.array([2 * t, 2 * t, t]), atol=GEOM_TOL)
    assert tank.landmarks["water_surface"][2] == pytest.approx(cfg.water_level_mm * MM)
