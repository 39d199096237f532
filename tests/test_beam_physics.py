"""Beam and scanner error sources of the B-mode simulator: continuous elevation
integration, side lobes, ring-down, scanner geometry, a drifting water temperature.

Each source: off ⇒ identical frames, on ⇒ the modelled position and size, deterministic.
The probe frame is the scene frame (see sim_us_scenes).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bench.config.scenario import scenario_from_mapping
from calib.errors import ScenarioError
from sim_us import MediumConfig
from sim_us.beam import SIDE_LOBE_OFFSET_PER_FWHM
from sim_us.materials import water_speed_m_s
from twin.imager import SimImager

from .sim_us_scenes import (
    MM,
    SMALL_PROBE,
    T_IDENTITY,
    elevation_shift,
    simulator,
    slab,
    sphere,
    wire,
)

DATA = Path(__file__).parent / "data"
# A wire seen at 0.05 mm pixels (the PSF spans ≈ 14 × 7 pixels).
FINE = replace(
    SMALL_PROBE,
    pixel_spacing_mm=(0.05, 0.05),
    scanline_spacing_mm=0.05,
    width_mm=8.0,
    depth_mm=20.0,
)
# Sub-pixel position of a peak: parabola through the maximum and its neighbours.


def peak_position(profile: np.ndarray) -> float:
    k = int(np.argmax(profile))
    y0, y1, y2 = np.log(profile[k - 1 : k + 2])
    return k + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)


def wire_envelope(**changes) -> tuple[np.ndarray, int, int]:
    """Envelope of a wire at 15 mm, its peak (row, col)."""
    env = simulator([wire(0.0, 15.0)], probe=replace(FINE, **changes)).envelope(T_IDENTITY)[0]
    r, c = np.unravel_index(np.argmax(env), env.shape)
    return env, int(r), int(c)


def cap_depth_mm(sim, pose=T_IDENTITY, temperature_c=None, col=None) -> float:
    """Apparent depth (mm, by the reported spacing) of the brightest echo in a column."""
    env = sim.envelope(pose, temperature_c)[0]
    col = (env.shape[1] - 1) // 2 if col is None else col
    return peak_position(env[:, col].astype(float)) * sim.spacing[1] / MM


# 0 ------------------------------------------------------------------ off ⇒ identical
def golden_scene(probe):
    return simulator(
        [sphere([1.0, 12.0, 0.5]), slab(20.0, tilt_deg=5.0)],
        probe=replace(probe, width_mm=10.0, depth_mm=25.0, pixel_spacing_mm=(0.2, 0.2)),
        medium=MediumConfig(kind="gel"),
    )


def test_discrete_elevation_reproduces_the_frame_from_before():
    """With continuous elevation off (and every new source at its default) the golden
    frame stored before these sources existed comes out again (stored anew twice since:
    when the gel's speckle started summing a thinned lattice past the elevation focus, and
    when the speckle's lateral PSF became one per row, cut at −40 dB instead of 3 σ: ≤ 5
    grey levels on 17 % of the pixels; and when a surface's echo became the mirror lobe of
    the probe's apertures instead of a stated specular width; and when the gel's speckle
    level came to follow the broadband loss and the resolution cell; and when a surface's
    diffuse return came to grow with the area a ray's tube meets; and when an echo beside
    the image plane came to be drawn as much deeper as the lens's longer paths delay it;
    and when every echo came to carry a flat reflector's level against depth)."""
    frame = golden_scene(replace(SMALL_PROBE, continuous_elevation=False)).render(
        T_IDENTITY, np.random.default_rng(2026)
    )[0]
    stored = np.load(DATA / "golden_frame_discrete.npy", allow_pickle=False)
    diff = np.abs(frame.astype(int) - stored.astype(int))
    assert diff.max() <= 2 and (diff > 0).mean() < 0.01  # Embree float32, as the golden test


def test_off_values_give_identical_frames():
    off = replace(
        SMALL_PROBE,
        side_lobe_db=None,
        ring_down_cycles=0.0,
        pixel_scale_error_pct=(0.0, 0.0),
        image_origin_offset_mm=0.0,
        lateral_offset_mm=0.0,
    )
    a = golden_scene(SMALL_PROBE)
    b = golden_scene(off)
    np.testing.assert_array_equal(
        a.render(T_IDENTITY, np.random.default_rng(5)),
        b.render(T_IDENTITY, np.random.default_rng(5), temperature_c=20.0),
    )
    on = golden_scene(replace(off, side_lobe_db=-20.0))
    assert not np.array_equal(
        a.render(T_IDENTITY, np.random.default_rng(5)),
        on.render(T_IDENTITY, np.random.default_rng(5)),
    )


# 1 ------------------------------------------------------------------ continuous elevation
def _bump_db(profile_db: np.ndarray) -> float:
    """Largest rise (dB) of a profile on either side of its maximum: 0 for a unimodal one."""
    k = int(np.argmax(profile_db))
    rises = []
    for side in (profile_db[k:], profile_db[: k + 1][::-1]):
        rises.append(float(np.max(side - np.minimum.accumulate(side))))
    return max(rises)


@pytest.fixture(scope="module")
def thick_slice_caps():
    """A sphere 3 mm off the image plane, 35 mm deep: 2× the elevation focus, where the
    slice is ≈ 4 mm thick. Intensity (before noise) with discrete and continuous elevation."""
    probe = replace(SMALL_PROBE, width_mm=20.0, depth_mm=50.0)
    out = {}
    for continuous in (False, True):
        sim = simulator(
            [sphere([0.0, 40.0, 0.0], 5.0)], probe=replace(probe, continuous_elevation=continuous)
        )
        out[continuous] = sim.intensity(elevation_shift(3.0))[0].astype(float)
    return out


def test_thick_slice_gives_one_thickened_echo(thick_slice_caps):
    def bumps(image):
        result = []
        for x_mm in (0.0, 1.0, 2.0, 3.0, 4.0):
            p = image[300:420, 100 + round(x_mm / 0.1)]
            p = p[p > p.max() * 1e-3]  # the echo, 30 dB down
            result.append(_bump_db(10 * np.log10(p)))
        return np.array(result)

    # The discrete sub-planes draw separate arcs: dips of more than 6 dB between peaks.
    assert bumps(thick_slice_caps[False]).max() > 6.0
    # Integrated continuously: one echo in every column. Not quite unimodal: the mirror's
    # echo of each slab comes from near its specular point, so the slabs' echoes stack
    # near the cap's top with a ripple of ≈ 3 dB, not as separate arcs.
    assert bumps(thick_slice_caps[True]).max() < 4.0
    # Thickened: it spans more depth than the point-like PSF (FWHM ≈ 0.35 mm).
    p = thick_slice_caps[True][:, 100]
    above = np.flatnonzero(p > p.max() / 100)  # 20 dB down
    assert (above[-1] - above[0]) * 0.1 > 1.0


def test_continuous_elevation_keeps_the_echo_energy(thick_slice_caps):
    discrete, continuous = (thick_slice_caps[k].sum() for k in (False, True))
    assert continuous == pytest.approx(discrete, rel=0.01)


def test_elevation_flat_reflector_is_unchanged():
    """A plate square to the beam has no depth slope across the slice: same echo."""
    frames = [
        simulator([slab(20.0)], continuous_elevation=c).intensity(T_IDENTITY)[0] for c in (0, 1)
    ]
    np.testing.assert_array_equal(*frames)


# 2 ------------------------------------------------------------------ side lobes
@pytest.mark.parametrize("level_db", [-26.5, -40.0])
def test_side_lobe_copies_at_first_side_lobe(level_db):
    env, r, c = wire_envelope(side_lobe_db=level_db)
    profile = env[r].astype(float)
    offset_px = SIDE_LOBE_OFFSET_PER_FWHM * FINE.lateral_fwhm_mm / 0.05  # 1.13 mm
    for side in (-1, 1):
        lo = c + side * int(offset_px) - 6
        window = profile[lo : lo + 14]
        pos = lo + peak_position(window) - c
        assert abs(abs(pos) - offset_px) <= 1.0  # within one pixel (0.05 mm)
        level = 20 * np.log10(window.max() / profile[c])
        assert level == pytest.approx(level_db, abs=1.0)
    off, _, _ = wire_envelope()
    assert off[r, c + round(offset_px)] < 1e-6 * off[r, c]  # nothing there without lobes


# 3 ------------------------------------------------------------------ ring-down
def test_ring_down_tail_length_and_decay():
    n_cycles = 2.0
    ell_mm = n_cycles * 1540.0 / (2 * 13e6) / MM  # 0.118 mm per e-fold of amplitude
    env, r, c = wire_envelope(ring_down_cycles=n_cycles)
    off, r0, c0 = wire_envelope()
    assert (r, c) == (r0, c0)
    a, b = env[:, c].astype(float) / env[r, c], off[:, c].astype(float) / off[r, c]
    # Above and at the echo nothing changes: leading edge, peak.
    np.testing.assert_allclose(a[: r + 1], b[: r + 1], rtol=1e-5)
    # Below it the tail decays by e per ℓ: fit the slope between −30 and −60 dB (above
    # −27 dB the Gaussian's trailing edge is still the larger).
    below = np.arange(r + 1, r + 60)
    tail = (a[below] < 10 ** (-30 / 20)) & (a[below] > 10 ** (-60 / 20))
    slope = np.polyfit(below[tail] * 0.05, np.log(a[below[tail]]), 1)[0]
    assert -1 / slope == pytest.approx(ell_mm, rel=0.05)

    # Its length: −40 dB is reached ℓ ln 100 below the peak (0.54 mm), not the PSF's
    # 0.37 mm (amplitude σ 0.149 mm × √(2 ln 100)).
    def length_mm(p):
        return (r + np.argmax(p[r:] < 0.01) - r) * 0.05

    assert length_mm(a) == pytest.approx(ell_mm * np.log(100.0), abs=0.06)
    assert length_mm(b) == pytest.approx(0.149 * np.sqrt(2 * np.log(100.0)), abs=0.06)


# 4 ------------------------------------------------------------------ scanner geometry
def test_axial_scale_error_makes_things_deeper():
    parts = [sphere([0.0, 20.0, 0.0])]
    base = cap_depth_mm(simulator(parts))
    scaled = cap_depth_mm(simulator(parts, pixel_scale_error_pct=(0.0, 2.0)))
    assert scaled / base == pytest.approx(1.02, abs=0.002)


def test_lateral_scale_error_and_offsets():
    parts = [sphere([4.0, 20.0, 0.0])]

    def cap_x_mm(**changes):
        env = simulator(parts, **changes).envelope(T_IDENTITY)[0]
        row = int(np.argmax(env.max(axis=1)))
        return (peak_position(env[row].astype(float)) - (env.shape[1] - 1) / 2) * 0.1

    x0 = cap_x_mm()
    assert x0 == pytest.approx(4.0, abs=0.05)
    assert cap_x_mm(pixel_scale_error_pct=(3.0, 0.0)) == pytest.approx(1.03 * x0, abs=0.02)
    assert cap_x_mm(lateral_offset_mm=1.0) == pytest.approx(x0 - 1.0, abs=0.02)
    sim = simulator(parts, image_origin_offset_mm=1.5)
    col = round(4.0 / 0.1) + (sim.shape[1] - 1) // 2
    shallower = cap_depth_mm(simulator(parts), col=col) - cap_depth_mm(sim, col=col)
    assert shallower == pytest.approx(1.5, abs=0.02)
    np.testing.assert_allclose(sim.T_face_image[:3, 3], [0.0, 1.5 * MM, 0.0])


def test_frames_report_the_nominal_spacing():
    sim = simulator([], pixel_scale_error_pct=(2.0, -3.0))
    assert sim.spacing == SMALL_PROBE.spacing_m
    assert sim.true_spacing == pytest.approx((1e-4 / 1.02, 1e-4 / 0.97))


# 5 ------------------------------------------------------------------ water temperature
@pytest.mark.parametrize("temperature_c", [15.0, 25.0])
def test_temperature_changes_apparent_depth_as_the_speed(temperature_c):
    sim = simulator([sphere([0.0, 30.0, 0.0])], depth_mm=30.0)
    d0 = cap_depth_mm(sim)
    d1 = cap_depth_mm(sim, temperature_c=temperature_c)
    expected = water_speed_m_s(20.0) / water_speed_m_s(temperature_c)
    assert d1 / d0 == pytest.approx(expected, abs=0.001)  # 25 mm: ±0.025 mm
    assert abs(d1 / d0 - 1) > 0.003  # a real shift (≈ ±0.4 mm at 25 mm)


def _stub_imager(medium: MediumConfig, clock_s: float) -> SimImager:
    """A SimImager on a stand-in robot: a sphere in front of a probe at the base origin."""
    part = sphere([0.0, 20.0, 0.0])
    scene = SimpleNamespace(
        phantom=SimpleNamespace(parts=[part]),
        T_base_phantom=np.eye(4),
        tank=SimpleNamespace(parts=[]),
        T_base_tank=np.eye(4),
    )
    robot = SimpleNamespace(
        scene=SimpleNamespace(scene=scene),
        truth=SimpleNamespace(T_base_ee=np.eye(4)),
        frame_pose=lambda: np.eye(4),
        clock_s=clock_s,
    )
    probe = replace(SMALL_PROBE, noise_db=-200.0)
    return SimImager(robot, np.eye(4), probe, medium, np.random.default_rng(3))


def test_imager_follows_the_session_clock():
    drifting = MediumConfig(temperature_c=22.0, temperature_drift_c_per_h=-1.5)
    assert drifting.temperature_at(7200.0) == pytest.approx(19.0)
    late = _stub_imager(drifting, clock_s=7200.0).grab()
    at_19 = _stub_imager(MediumConfig(temperature_c=19.0), clock_s=7200.0).grab()
    np.testing.assert_array_equal(late.image, at_19.image)
    assert late.spacing == SMALL_PROBE.spacing_m
    # No drift: the clock does not matter; at the start the drift has done nothing yet.
    steady = _stub_imager(MediumConfig(temperature_c=22.0), clock_s=7200.0).grab()
    start = _stub_imager(drifting, clock_s=0.0).grab()
    np.testing.assert_array_equal(steady.image, start.image)
    assert not np.array_equal(late.image, start.image)


# 6 ------------------------------------------------------------------ determinism, keys
def test_all_sources_on_are_deterministic():
    probe = replace(
        SMALL_PROBE,
        side_lobe_db=-30.0,
        ring_down_cycles=2.0,
        pixel_scale_error_pct=(1.0, -1.0),
        image_origin_offset_mm=0.5,
        lateral_offset_mm=-0.5,
    )
    frames = [
        golden_scene(probe).render(elevation_shift(1.0), np.random.default_rng(9), 23.0)
        for _ in range(2)
    ]
    np.testing.assert_array_equal(*frames)


def test_scenario_keys_and_their_off_values():
    s = scenario_from_mapping(
        {
            "imaging": {
                "side_lobe_db": None,
                "ring_down_cycles": 0,
                "pixel_scale_error_pct": [0, 0],
            },
            "medium": {"temperature_drift_c_per_h": 0.0},
        }
    )
    assert s.imaging.side_lobe_db is None and s.imaging.continuous_elevation
    with pytest.raises(ScenarioError, match="side_lobe_db"):
        scenario_from_mapping({"imaging": {"side_lobe_db": 0}})  # 0 dB is not "off"
