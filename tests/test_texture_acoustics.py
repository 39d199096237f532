"""A printed surface's texture in the ultrasound simulator (Kirchhoff approximation): the
specular lobe follows the un-textured surface, the texture's rms height σ scales the
coherent reflection by exp(−2 (k σ cos θ)²) and gives the lost energy to the diffuse
share; untextured parts render as before."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from sim_us.beam import mirror_of
from sim_us.materials import MATERIALS, water
from sim_us.propagation import coherent_factor, rough_surface_shape
from sim_us.raycast import AcousticScene, RayCaster, ScenePart
from twin import printing
from twin.phantoms import PhantomConfig, build_phantom

from .sim_us_scenes import MM, SMALL_PROBE, T_IDENTITY, simulator, slab, sphere, trace_along_y

UM = 1e-6
F_MHZ = 13.0


def _textured(part: ScenePart, rms_m: float) -> ScenePart:
    """The part with its own mesh as the un-textured surface and a uniform texture."""
    v = np.asarray(part.mesh.vertices)
    return ScenePart(part.name, part.mesh, part.material, v.copy(), np.full(len(v), rms_m))


def _first_and_reverberation(e) -> tuple[float, float]:
    """Amplitudes of a single ray's first echo and of its reverberation (twice as deep)."""
    i = np.argmin(e.depth)
    j = np.argmin(np.abs(e.depth - 2 * e.depth[i]))
    assert abs(e.depth[j] - 2 * e.depth[i]) < 1e-12
    return e.amplitude[i], e.amplitude[j]


def _trace(parts, origins, dirs, reverberation=True):
    caster = RayCaster(AcousticScene(tuple(parts)))
    mats = [MATERIALS[p.material] for p in parts]
    return trace_along_y(caster, mats, water(20.0), origins, dirs, reverberation=reverberation)


# (a) ------------------------------------------------------------------ off = as before
def test_untextured_parts_carry_nothing_and_trace_as_before():
    # Printing keys off or shape error only: no acoustic texture data on any part.
    rng = np.random.default_rng(np.random.SeedSequence(5))
    for cfg in (PhantomConfig(), PhantomConfig(sphere_roundness_mm=0.05)):
        ph = build_phantom(cfg, rng)
        assert all(p.acoustic_vertices is None and p.texture_rms_m is None for p in ph.parts)
    printed = build_phantom(PhantomConfig(print_layer_mm=0.3), rng)
    spheres = [p for p in printed.parts if p.name.startswith("sphere_")]
    assert spheres and all(p.acoustic_vertices.shape == p.mesh.vertices.shape for p in spheres)
    assert (
        RayCaster(AcousticScene((sphere([0, 20, 0]),)))
        .first_hits(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), np.array([1.0]))
        .texture_rms
        is None
    )

    # A scene with a textured sphere (σ = 0) over a plate: the plate's echoes are
    # bit-identical to the untextured scene's, the sphere's equal to rounding.
    x = np.linspace(-9, 9, 181) * MM
    origins = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    dirs = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    plain = [sphere([0.0, 12.0, 0.0]), slab(25.0)]
    a = _trace(plain, origins, dirs)
    b = _trace([_textured(plain[0], 0.0), plain[1]], origins, dirs)
    np.testing.assert_array_equal(a.ray, b.ray)
    np.testing.assert_array_equal(a.depth, b.depth)
    beside = np.abs(x[a.ray]) > 5.5 * MM
    np.testing.assert_array_equal(a.amplitude[beside], b.amplitude[beside])
    # The sphere's vertex normals are area-weighted here, angle-weighted by trimesh: a
    # fraction of a degree apart, felt only by the steep flanks' weak echoes.
    strong = a.amplitude > 0.5 * a.amplitude.max()
    np.testing.assert_allclose(a.amplitude[strong], b.amplitude[strong], rtol=3e-2)
    # Far down the mirror's lobe (below -40 dB) a fraction of a degree moves the echo by
    # tens of per cent; above it, by less than a tenth.
    shown = a.amplitude > 1e-2 * a.amplitude.max()
    np.testing.assert_allclose(a.amplitude[shown], b.amplitude[shown], rtol=0.1)


# (b) ------------------------------------------------------------------ flat plate
@pytest.mark.parametrize("tilt_deg", [0.0, 6.0])
def test_coherent_factor_of_a_textured_plate(tilt_deg):
    """Echo of a plate with a texture of rms σ (facets of rms slope σ / ℓ): the
    reverberation (second, coherent-only bounce) over the first echo gives the coherent
    factor exp(−2 (k σ cos θ)²), the first echo the energy (1 − d²)(χ² S² + (1 − χ²) S_s²)
    + d² / cos θ (S the mirror's lobe, S_s the lobe widened by the facets; the diffuse
    share per unit of the plate's area)."""
    plate = slab(15.0, tilt_deg=tilt_deg)
    origin, direction = np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]])
    pla, medium = MATERIALS["pla"], water(20.0)
    k = 2 * np.pi * F_MHZ * 1e6 / medium.speed_m_s
    theta = np.radians(tilt_deg)
    depth = np.array([15.0 * MM * 1540.0 / medium.speed_m_s])
    ref = _trace([plate], origin, direction)
    first0, rev0 = _first_and_reverberation(ref)
    d = pla.diffuse
    chis = []
    for sigma_um in (2.0, 5.0, 10.0, 20.0, 40.0):
        part = _textured(plate, sigma_um * UM)
        e = _trace([part], origin, direction)
        np.testing.assert_array_equal(e.depth, ref.depth)  # the echo stays where it was
        first, rev = _first_and_reverberation(e)
        kσc = k * sigma_um * UM * np.cos(theta)
        chi = (rev / first) / (rev0 / first0)
        assert chi == pytest.approx(np.exp(-2 * kσc**2), rel=1e-6)
        assert chi == pytest.approx(coherent_factor(kσc), rel=1e-6)
        slope = np.array([sigma_um * UM / part.texture_length_m])
        lat, el, lat_w, el_w = mirror_of(SMALL_PROBE).lobes(depth, [theta], [0.0], slope)
        spec, wide = float(lat[0] * el[0]), float(lat_w[0] * el_w[0])
        area = 1.0 / np.cos(theta)
        energy = (1 - d**2) * (chi**2 * spec**2 + (1 - chi**2) * wide**2) + d**2 * area
        smooth = (1 - d**2) * spec**2 + d**2 * area
        assert first / first0 == pytest.approx(np.sqrt(energy / smooth), rel=1e-6)
        chis.append(chi)
    # Monotone in σ; at 40 µm (≈ λ/3) the coherent echo is gone.
    assert np.all(np.diff(chis) < 0) and chis[-1] < 0.05


def test_rough_shape_limits():
    spec = np.array([1.0, 0.3, 1e-4])
    wide = np.array([0.9, 0.5, 1e-2])
    s0, c0 = rough_surface_shape(spec, wide, 0.1, np.zeros(3))
    np.testing.assert_allclose(s0, np.sqrt(0.99 * spec**2 + 0.01), rtol=1e-12)
    np.testing.assert_allclose(c0, np.sqrt(0.99) * spec)
    s_inf, c_inf = rough_surface_shape(spec, wide, 0.1, np.full(3, 10.0))
    np.testing.assert_allclose(s_inf, np.sqrt(0.99 * wide**2 + 0.01))  # the facets' lobe
    assert np.all(c_inf < 1e-80)
    # Facing the probe: never above the smooth mirror, for any roughness.
    ks = np.linspace(0, 3, 301)
    one = np.ones_like(ks)
    assert np.all(rough_surface_shape(one, 0.8 * one, 0.1, ks)[0] <= 1 + 1e-12)


# (c) ------------------------------------------------------------------ printed sphere
# The printed sphere with its build axis z turned toward the probe (scene −y), centred
# 20 mm deep; the probe of ``sim_us_scenes`` looks along +y.
_R_BUILD = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 20 * MM], [0.0, 1.0, 0.0, 0.0], [0, 0, 0, 1]]
)


def _printed_sphere(layer_mm: float) -> ScenePart:
    s = printing.PrintSettings(layer=layer_mm * MM)
    rng = np.random.default_rng(np.random.SeedSequence(11))
    mesh, _, _ = printing.printed_sphere(np.zeros(3), 5 * MM, s, 0, rng)
    moved = mesh.copy()
    moved.apply_transform(_R_BUILD)
    smooth = mesh.metadata.get("acoustic_vertices")
    if smooth is not None:
        smooth = trimesh.transform_points(smooth, _R_BUILD)
    return ScenePart("sphere", moved, "pla", smooth, mesh.metadata.get("texture_rms_m"))


def _cap(layer_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Envelope of the sphere's cap (rows 110-200, the 6 mm around the centre) and each
    column's peak row."""
    env = simulator([_printed_sphere(layer_mm)]).envelope(T_IDENTITY)[0]
    mid = (env.shape[1] - 1) // 2
    cap = env[110:200, mid - 30 : mid + 31]
    return cap, np.argmax(cap, axis=0)


@pytest.fixture(scope="module")
def caps():
    return {h: _cap(h) for h in (0.0, 0.05, 0.1, 0.2)}


def test_fine_staircase_renders_like_the_smooth_sphere(caps):
    """0.05 mm layers (σ ≤ 14 µm ≈ λ/8 at 13 MHz): the cap's echo stays at the smooth
    sphere's depth within a pixel and keeps its brightness within 3 dB at the top."""
    smooth, rows0 = caps[0.0]
    fine, rows = caps[0.05]
    centre = slice(20, 41)  # ± 1 mm about the top
    assert np.abs(rows[centre] - rows0[centre]).max() <= 1
    top0, top = smooth[:, 30].max(), fine[:, 30].max()
    assert abs(20 * np.log10(top / top0)) < 3.0
    # The 0.2 mm staircase does not, at the top: its coherent echo is gone (≫ λ/8).
    assert caps[0.2][0][:, 30].max() < 0.98 * top0


def test_texture_effect_grows_with_layer_height(caps):
    smooth = caps[0.0][0]
    diff = [np.abs(caps[h][0] - smooth).sum() / smooth.sum() for h in (0.05, 0.1, 0.2)]
    assert diff[0] < diff[1] < diff[2]
