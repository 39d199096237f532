"""The printed phantom (twin/printing.py): layer lines, roughness, shape error and
out-of-roundness, checked against their models on the printed meshes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from twin import printing
from twin.phantoms import PhantomConfig, build_phantom, phantom_pair
from twin.printing import layer_offset

MM = 1e-3
UM = 1e-6
EXACT = dict(tolerance_radius_mm=0.0, tolerance_position_mm=0.0)  # no print tolerance
LAYER_MM = 0.2


def _rng(seed: int = 7) -> np.random.Generator:
    return np.random.default_rng(seed)


def _sphere_mesh(phantom, i: int = 1):
    return {p.name: p.mesh for p in phantom.parts}[f"sphere_{i}"]


@pytest.mark.parametrize("kind", ["spheres", "cone", "prism"])
def test_off_the_printed_phantom_is_todays(kind):
    """Every printing key at 0: the true phantom is the CAD with the print tolerance
    only, and the phantom generator draws exactly the tolerance draws (nothing more)."""
    cfg = PhantomConfig(kind=kind)
    rng = _rng()
    cad, true = phantom_pair(cfg, rng)
    after = rng.random()
    n_draws = {"spheres": 4 + 12 + 12, "cone": 2, "prism": 3}[kind]
    ref = _rng()
    ref.normal(size=n_draws)
    assert after == ref.random()
    assert [p.name for p in true.parts] == [p.name for p in cad.parts]
    for p, q in zip(true.parts, cad.parts, strict=True):
        assert len(p.mesh.faces) == len(q.mesh.faces)
    if kind == "spheres":
        for i in range(1, 5):
            v = _sphere_mesh(true, i).vertices - true.landmarks[f"sphere_{i}"]
            r = np.linalg.norm(v, axis=1)
            assert np.ptp(r) < 1e-12 and r[0] == pytest.approx(true.sphere_radii[f"sphere_{i}"])
    # Printing draws only from its own streams: the landmarks of what it does not touch,
    # and the generator's own state afterwards, are the same with printing on.
    on = PhantomConfig(kind=kind, print_layer_mm=0.2, print_warp_mm=0.2, sphere_roundness_mm=0.1)
    rng_on = _rng()
    _, printed = phantom_pair(on, rng_on)
    assert rng_on.random() == after
    if kind == "spheres":
        for j in range(1, 5):
            assert np.array_equal(printed.landmarks[f"vertex_{j}"], true.landmarks[f"vertex_{j}"])


def test_keys_of_other_phantoms_leave_a_phantom_unchanged():
    """Shape error is the cone's and prism's; the four-sphere phantom stays today's."""
    a = build_phantom(PhantomConfig(), _rng())
    b = build_phantom(PhantomConfig(print_shrinkage_pct=0.4, print_warp_mm=0.3), _rng())
    for p, q in zip(a.parts, b.parts, strict=True):
        assert np.array_equal(p.mesh.vertices, q.mesh.vertices)
    assert all(np.array_equal(a.landmarks[k], b.landmarks[k]) for k in a.landmarks)


def test_layer_lines_are_a_staircase_of_the_layer_height():
    """Near the top of a sphere (a near-horizontal surface) the printed surface is flat
    treads at the layer boundaries, one layer height apart; everywhere it stays within
    h/2 of the CAD sphere, with the largest offsets where the surface is horizontal."""
    h = LAYER_MM * MM
    cfg = PhantomConfig(print_layer_mm=LAYER_MM, **EXACT)
    ph = build_phantom(cfg, _rng())
    cad_centre = build_phantom(cfg).landmarks["sphere_1"]
    r = cfg.sphere_radius_mm * MM
    v = _sphere_mesh(ph).vertices
    rel = v - cad_centre
    dev = np.linalg.norm(rel, axis=1) - r
    assert np.abs(dev).max() <= h / 2 + 1e-9
    n_z = rel[:, 2] / np.linalg.norm(rel, axis=1)
    top = n_z > 0.9
    frac = v[top, 2] / h - np.round(v[top, 2] / h)
    on_tread = np.abs(frac) < 1e-3
    assert on_tread.mean() > 0.7  # treads hold ≈ cos² α ≥ 81 % of the top's vertices
    levels = np.unique(np.round(v[top][on_tread, 2] / h))
    steps = np.diff(levels) * h
    assert len(levels) >= 3
    assert steps == pytest.approx(np.full(len(steps), h), abs=1e-9)
    # Amplitude ≈ (h/2)·cos α: near the equator the staircase nearly vanishes.
    flat, steep = np.abs(n_z) > 0.95, np.abs(n_z) < 0.2
    assert np.abs(dev[flat]).max() > 0.45 * h
    assert np.abs(dev[steep]).max() < 0.11 * h
    # MuJoCo collides a convex hull of the printed sphere, the same solid within h/2.
    hull = {p.name: p for p in ph.parts}["sphere_1"].collision_mesh
    assert hull.is_convex and len(hull.faces) < len(_sphere_mesh(ph).faces) / 4
    r_hull = np.linalg.norm(hull.vertices - cad_centre, axis=1) - r
    assert np.abs(r_hull).max() <= h / 2 + 1e-9


def test_layer_lines_on_the_prism_are_exact():
    """On a plane face the mesh follows the staircase's corners: the sloped faces'
    vertices lie on risers through the CAD at mid-layer and treads at layer boundaries,
    within (h/2)·cos α of the CAD plane."""
    h = LAYER_MM * MM
    cfg = PhantomConfig(kind="prism", print_layer_mm=LAYER_MM, **EXACT)
    mesh = build_phantom(cfg, _rng()).parts[0].mesh
    W, H = cfg.prism_width_mm * MM / 2, cfg.prism_height_mm * MM
    n = np.array([0.0, H, W]) / np.hypot(W, H)  # face y > 0
    v = mesh.vertices[mesh.vertices[:, 1] > 1e-9]
    d = (v - [0.0, W, 0.0]) @ n
    assert np.abs(d).max() == pytest.approx(h / 2 * n[2], rel=1e-6)
    # The ridge's row is the plane model's edge (the last, partial layer): left out.
    v = v[v[:, 2] < H - h]
    # Tread corners: vertices at a layer boundary; riser corners: on vertical lines
    # through the CAD at mid-layer. Every vertex is one or the other (or on an edge).
    boundary = np.abs(v[:, 2] / h - np.round(v[:, 2] / h)) < 1e-6
    mid = np.floor(v[:, 2] / h) + 0.5
    y_riser = W * (1 - mid * h / H)
    riser = np.abs(v[:, 1] - y_riser) < 1e-9
    assert np.all(boundary | riser)
    tread_levels = np.unique(np.round(v[boundary, 2] / h))
    assert np.all(np.diff(tread_levels) == 1)
    # A horizontal face prints at the nearest layer boundary; a vertical wall is unmoved.
    z = np.array([3.3, 3.7, 3.3]) * h
    assert layer_offset(z, np.array([1.0, 1.0, 0.0]), h) == pytest.approx([-0.3 * h, 0.3 * h, 0])


def test_roughness_has_the_set_ra_and_correlation_length():
    """On the prism's sloped face, the mean absolute height is Ra (within 20 %), and
    heights one correlation length apart correlate by e^(-1/2)."""
    ra_um, ell_mm = 15.0, 0.4
    cfg = PhantomConfig(
        kind="prism", print_roughness_ra_um=ra_um, print_roughness_length_mm=ell_mm, **EXACT
    )
    mesh = build_phantom(cfg, _rng()).parts[0].mesh
    W, H = cfg.prism_width_mm * MM / 2, cfg.prism_height_mm * MM
    n = np.array([0.0, H, W]) / np.hypot(W, H)
    v = mesh.vertices
    face = (v[:, 1] > 1e-9) & (v[:, 2] > 1e-3) & (v[:, 2] < H - 1e-3)
    d = (v[face] - [0.0, W, 0.0]) @ n
    assert np.mean(np.abs(d)) == pytest.approx(ra_um * UM, rel=0.2)
    assert np.abs(np.mean(d)) < 0.2 * ra_um * UM
    # Neighbours along the ridge (x) one correlation length apart, same row.
    foot = v[face] - d[:, None] * n  # back on the CAD plane: the grid's rows and columns
    x, z = foot[:, 0], np.round(foot[:, 2], 9)
    order = np.lexsort((x, z))
    xs, zs, ds = x[order], z[order], d[order]
    dx = np.median(np.diff(np.unique(np.round(xs, 9))))
    lag = round(float(ell_mm * MM / dx))
    same_row = zs[lag:] == zs[:-lag]
    rho = np.corrcoef(ds[lag:][same_row], ds[:-lag][same_row])[0, 1]
    assert rho == pytest.approx(np.exp(-0.5), abs=0.12)


def test_shrinkage_shrinks_the_cone_by_the_set_percent():
    """Height shrinks by the z percent, base diameter by the in-plane percent; the apex
    landmark moves with it."""
    cfg = PhantomConfig(kind="cone", print_shrinkage_pct=0.4, print_shrinkage_z_pct=0.25, **EXACT)
    ph = build_phantom(cfg, _rng())
    v = ph.parts[0].mesh.vertices
    H, R = cfg.cone_height_mm * MM, cfg.cone_base_diameter_mm * MM / 2
    assert v[:, 2].max() == pytest.approx(H * (1 - 0.0025), abs=1e-9)
    assert np.hypot(v[:, 0], v[:, 1]).max() == pytest.approx(R * (1 - 0.004), abs=1e-9)
    assert ph.landmarks["apex"] == pytest.approx([0, 0, H * (1 - 0.0025)], abs=1e-12)
    # The CAD stays exact.
    assert build_phantom(cfg).parts[0].mesh.vertices[:, 2].max() == pytest.approx(H)


def test_warp_lifts_the_base_edges_and_sag_bends_the_prism_faces():
    """Warp: the base's corners lift by 0.5-2.25× the key (drawn amplitude and x/y
    curvatures), the middle of its long sides by a quarter of that or less (lift ∝
    distance²), the ridge (well above the warped layers) barely moves. Sag: the sloped
    faces' centres move along the normal, their edges stay."""
    w_mm = 0.2
    cfg = PhantomConfig(kind="prism", print_warp_mm=w_mm, **EXACT)
    v = build_phantom(cfg, _rng()).parts[0].mesh.vertices
    L = cfg.prism_length_mm * MM
    bottom = v[:, 2] < 1e-3
    corners = v[bottom & (np.abs(np.abs(v[:, 0]) - L / 2) < 1e-9), 2]
    middle = v[bottom & (np.abs(v[:, 0]) < 1e-9), 2]
    assert len(corners) == 4 and len(middle) == 2
    assert 0.5 * w_mm * MM <= corners.min() and corners.max() <= 2.25 * w_mm * MM
    assert 0 < middle.max() <= 0.3 * corners.min()
    assert v[:, 2].max() - cfg.prism_height_mm * MM < 1e-6
    sag = PhantomConfig(kind="prism", print_sag_mm=0.1, **EXACT)
    cad = build_phantom(sag).parts[0].mesh
    s = build_phantom(sag, _rng()).parts[0].mesh.vertices
    W, H = sag.prism_width_mm * MM / 2, sag.prism_height_mm * MM
    n = np.array([0.0, H, W]) / np.hypot(W, H)
    d = (s[s[:, 1] > 1e-9] - [0.0, W, 0.0]) @ n
    assert 1e-6 < np.abs(d).max() < 0.5 * MM  # a drawn 1 σ = 0.1 mm pillow
    assert np.abs(cad.vertices[:, 0]).max() == pytest.approx(np.abs(s[:, 0]).max())


def test_out_of_roundness_has_the_set_rms_and_the_centre_is_the_fitted_one():
    """Over 4 spheres × 5 seeds the mean squared radial deviation is the key² (within
    35 %: 240 degrees of freedom); the true centre is the least-squares sphere's of the
    printed surface (an independent fit agrees to 2 µm) and, the deviation having no
    degree-1 part, within 10 µm of the drawn centre."""
    key_mm = 0.1
    cfg = PhantomConfig(sphere_roundness_mm=key_mm, **EXACT)
    cad = build_phantom(cfg)
    ms = []
    for seed in range(5):
        ph = build_phantom(cfg, _rng(seed))
        for i in range(1, 5):
            v = _sphere_mesh(ph, i).vertices
            c = ph.landmarks[f"sphere_{i}"]
            dev = np.linalg.norm(v - c, axis=1) - ph.sphere_radii[f"sphere_{i}"]
            ms.append(np.mean(dev**2))
            if seed == 0:
                v_mm = v / MM  # an independent fit, over the vertices, in mm
                fit = least_squares(
                    lambda p, v_mm=v_mm: np.linalg.norm(v_mm - p[:3], axis=1) - p[3],
                    np.r_[cad.landmarks[f"sphere_{i}"] / MM, 5.0],
                    xtol=1e-12,
                ).x
                assert np.linalg.norm(fit[:3] * MM - c) < 2 * UM
                assert np.linalg.norm(c - cad.landmarks[f"sphere_{i}"]) < 10 * UM
                assert 0.5 * key_mm * MM < np.sqrt(ms[-1]) < 2 * key_mm * MM
    assert np.sqrt(np.mean(ms)) == pytest.approx(key_mm * MM, rel=0.35)


def test_printing_is_deterministic_for_a_seed():
    """The same seed prints the same sphere (built twice, past the per-process cache);
    another seed prints another."""
    s = PhantomConfig(print_layer_mm=0.3, print_roughness_ra_um=20, sphere_roundness_mm=0.05)
    build = printing.printed_sphere.__wrapped__
    centre, radius = np.array([0.0, 0.0, 20 * MM]), 5 * MM
    a, ca, _ = build(centre, radius, s.printing, 1, _rng(3))
    b, cb, _ = build(centre, radius, s.printing, 1, _rng(3))
    c, cc, _ = build(centre, radius, s.printing, 1, _rng(4))
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(ca, cb)
    assert not np.allclose(a.vertices, c.vertices, rtol=0, atol=1 * UM)
    assert not np.array_equal(ca, cc)


def test_the_disk_cache_shares_printed_parts_between_processes(tmp_path):
    """With a disk cache a part is built once and read back whole (mesh, its acoustic
    metadata, the fitted centre and radius) wherever the same inputs come again: what the
    run's worker processes share. Without one nothing is written."""
    s = PhantomConfig(print_layer_mm=0.3, print_roughness_ra_um=20, sphere_roundness_mm=0.05)
    calls = []

    def build(*args):
        calls.append(args)
        return printing.printed_sphere.__wrapped__(*args)

    build.__name__ = "printed_sphere"
    centre, radius = np.array([0.0, 0.0, 20 * MM]), 5 * MM
    args = (centre, radius, s.printing, 1, _rng(3))
    key = ("inputs", "seed")
    printing.use_disk_cache(None)
    printing._from_disk(build, key, args)
    assert len(calls) == 1 and not any(tmp_path.iterdir())
    try:
        printing.use_disk_cache(tmp_path)
        built = printing._from_disk(build, key, args)
        read = printing._from_disk(build, key, args)  # as another process would
    finally:
        printing.use_disk_cache(None)
    assert len(calls) == 2  # the second came from the file
    assert [p.suffix for p in tmp_path.iterdir()] == [".pkl"]
    (m0, c0, r0), (m1, c1, r1) = built, read
    np.testing.assert_array_equal(m0.vertices, m1.vertices)
    np.testing.assert_array_equal(m0.faces, m1.faces)
    np.testing.assert_array_equal(
        m0.metadata["acoustic_vertices"], m1.metadata["acoustic_vertices"]
    )
    np.testing.assert_array_equal(m0.metadata["texture_rms_m"], m1.metadata["texture_rms_m"])
    assert np.array_equal(c0, c1) and r0 == r1
