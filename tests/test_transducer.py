"""The beam sim_us derives from the transducer, against the stored physics reference.

``benchmarks/reference/beam.json`` holds pymust's two-way lateral, axial and elevation
FWHM and first side lobe of two probes from 5 to 50 mm (``benchmarks/physics_reference.py
--write``). sim_us is given the same datasheet figures; its beam must be the reference's
within 12 % (widths) and 1.5 dB (side lobes), and so must what it draws.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from bench.config.scenario import ScenarioError, scenario_from_mapping
from sim_us import MediumConfig, ProbeConfig
from sim_us.beam import axial_fwhm_m, lateral_fwhm_m, slice_thickness
from sim_us.materials import water_speed_m_s
from sim_us.raycast import AcousticScene, ScenePart
from sim_us.simulator import BmodeSimulator
from sim_us.transducer import beam_tables, receive_fnumber, transducer

ROOT = Path(__file__).resolve().parents[1]
STORED = json.loads((ROOT / "benchmarks" / "reference" / "beam.json").read_text())
DEPTHS_M = np.array(STORED["depths_mm"]) * 1e-3
MM = 1e-3


def probe_of(array: dict) -> ProbeConfig:
    """sim_us's probe for a stored array: its datasheet figures, nothing stated."""
    return replace(
        ProbeConfig(),
        width_mm=array["elements"] * array["pitch_mm"],
        depth_mm=50.0,
        f_mhz=array["f_mhz"],
        bandwidth_pct=array["bandwidth_pct"],
        pulse_cycles=array["tx_cycles"],
        pitch_mm=array["pitch_mm"],
        kerf_mm=array["kerf_mm"],
        active_elements=array["active_elements"],
        elevation_aperture_mm=array["elevation_aperture_mm"],
        elevation_focus_mm=array["elevation_focus_mm"],
        assumed_speed_m_s=array["speed_m_s"],
    )


@pytest.mark.parametrize("name", sorted(STORED["probes"]))
@pytest.mark.slow
def test_the_derived_beam_is_the_reference_s(name):
    rec = STORED["probes"][name]
    probe, fig = probe_of(rec["array"]), rec["figures"]
    assert receive_fnumber(transducer(probe)) == pytest.approx(rec["receive_fnumber"], rel=0.01)
    for key, ours in (
        ("lateral_fwhm_mm", lateral_fwhm_m(probe, DEPTHS_M)),
        ("elevation_fwhm_mm", slice_thickness(probe, DEPTHS_M)),
        ("axial_fwhm_mm", np.full(len(DEPTHS_M), axial_fwhm_m(probe))),
    ):
        ratio = ours / MM / np.array(fig[key])
        assert np.all((ratio > 0.9) & (ratio < 1.12)), (key, np.round(ratio, 3))
    # The profile the simulator draws with (the table's, interpolated), at the reference's
    # first side lobe (its peak, or the shoulder a broad band leaves of it): the same level.
    tables = beam_tables(transducer(probe), 0.052)
    for depth, level, at_mm in zip(DEPTHS_M, fig["side_lobe_db"], fig["side_lobe_mm"], strict=True):
        ours = 20 * np.log10(tables.lateral_profile(depth, np.array([at_mm * MM]))[0, 0])
        assert ours == pytest.approx(level, abs=1.5), depth


def test_what_is_drawn_is_the_derived_beam():
    """A thin wire 18 mm deep, rendered at 0.01 mm: its lateral and axial FWHM are the
    reference's within 10 %, and its first side lobe within 1.5 dB. The reference images
    at the speed its scanner assumes; in water the scanner is set to water's speed (else
    its beam is out of focus: tests/test_reference_sweeps.py), its wavelength 4 % shorter."""
    rec = STORED["probes"]["paper"]
    i = STORED["depths_mm"].index(18.0)
    probe = replace(
        probe_of(rec["array"]),
        assumed_speed_m_s=water_speed_m_s(MediumConfig().temperature_c),
        width_mm=3.0,
        depth_mm=19.0,
        pixel_spacing_mm=(0.01, 0.01),
        scanline_spacing_mm=0.01,
    )
    wire = trimesh.creation.cylinder(radius=0.01 * MM, height=20 * MM, sections=16)
    wire.apply_translation([0.0, 18 * MM, 0.0])
    sim = BmodeSimulator(AcousticScene((ScenePart("wire", wire, "pla"),)), probe, MediumConfig())
    env = sim.envelope(np.eye(4)[None])[0].astype(float)
    r, c = np.unravel_index(int(np.argmax(env)), env.shape)

    def fwhm(p: np.ndarray, k: int) -> float:
        """mm, the half-maximum crossings interpolated linearly between samples."""
        p = p / p[k]
        hi = k + int(np.argmax(p[k:] < 0.5))
        lo = k - int(np.argmax(p[: k + 1][::-1] < 0.5))
        right = hi - 1 + (p[hi - 1] - 0.5) / (p[hi - 1] - p[hi])
        left = lo + 1 - (p[lo + 1] - 0.5) / (p[lo + 1] - p[lo])
        return (right - left) * 0.01

    assert fwhm(env[r], c) == pytest.approx(rec["figures"]["lateral_fwhm_mm"][i], rel=0.1)
    assert fwhm(env[:, c], r) == pytest.approx(rec["figures"]["axial_fwhm_mm"][i], rel=0.1)
    row = env[r, c:] / env[r, c]
    first_min = int(np.argmax(np.diff(row) > 0))
    level = 20 * np.log10(row[first_min:].max())
    assert level == pytest.approx(rec["figures"]["side_lobe_db"][i], abs=1.5)


@pytest.mark.parametrize("name", sorted(STORED["probes"]))
def test_plane_wave_compounding_draws_the_reference_s_psf(name):
    """Three plane waves at -8°, 0°, +8° compounded (``imaging.plane_waves_deg``): the
    lateral kernel the simulator draws with is pymust's point-target PSF (simus + dasmtx
    per wave, each column's brightest pixel): FWHM within 10 % (as a drawn wire's), the
    main lobe's levels (down to -20 dB) within 1 dB; the compounding's tails past it drawn,
    never more than 1 dB below the reference's brightest pixel there nor 8 dB above it (0
    to 7.3 measured: the separable PSF draws the tails' energy at the echo's depth; module
    docstring of sim_us.transducer). A focused scanner's kernel has no such tails."""
    rec = STORED["probes"][name]
    ref = rec["plane_wave_psf"]
    assert ref["steer_deg"] == [-8.0, 0.0, 8.0]
    probe = replace(probe_of(rec["array"]), plane_waves_deg=(-8.0, 0.0, 8.0))
    pw = beam_tables(transducer(probe), 0.052)
    focused = beam_tables(transducer(probe_of(rec["array"])), 0.052)
    offsets = np.array(ref["offsets_mm"]) * MM
    for j, depth_mm in enumerate(ref["depths_mm"]):
        x = np.linspace(0.0, 1.0 * MM, 2001)
        prof = pw.lateral_profile(depth_mm * MM, x)[0]
        k = int(np.argmax(prof < 0.5))  # the first sample below half: interpolate to it
        fwhm = 2.0 * np.interp(0.5, prof[k - 1 : k + 1][::-1], x[k - 1 : k + 1][::-1]) / MM
        assert fwhm == pytest.approx(ref["lateral_fwhm_mm"][j], rel=0.1), depth_mm
        ours = 20 * np.log10(np.maximum(pw.lateral_profile(depth_mm * MM, offsets)[0], 1e-6))
        theirs = np.array(ref["levels_db"][j])
        main = theirs >= -20.0
        main &= np.cumprod(main).astype(bool)  # out to the first offset below -20 dB
        assert np.all(np.abs(ours[main] - theirs[main]) <= 1.0), (depth_mm, ours - theirs)
        tails = ~main & (theirs > -45.0)
        assert tails.any()
        assert np.all(
            (ours[tails] - theirs[tails] >= -1.0) & (ours[tails] - theirs[tails] <= 8.0)
        ), (
            depth_mm,
            ours - theirs,
        )
        scanner = 20 * np.log10(
            np.maximum(focused.lateral_profile(depth_mm * MM, offsets)[0], 1e-6)
        )
        # The tails' mean intensity: 6 dB and more above a focused scanner's side lobes.
        power = 10 * np.log10(
            np.mean(10 ** (ours[tails] / 10)) / np.mean(10 ** (scanner[tails] / 10))
        )
        assert power >= 6.0, (depth_mm, power)


def test_stated_widths_override_the_transducer():
    stated = replace(ProbeConfig(), lateral_fwhm_mm=0.7, axial_fwhm_mm=0.35, slice_thickness_mm=0.7)
    assert np.allclose(lateral_fwhm_m(stated, DEPTHS_M), 0.7 * MM)
    assert axial_fwhm_m(stated) == pytest.approx(0.35 * MM)
    # The geometric slice: the stated thickness at the lens focus, the aperture at the face.
    assert slice_thickness(stated, 18 * MM) == pytest.approx(0.7 * MM)
    assert slice_thickness(stated, 0.0) == pytest.approx(np.hypot(0.7, 4.0) * MM)


def test_side_lobes_are_the_array_s_a_level_or_none():
    for value in ("array", -40.0, None):
        s = scenario_from_mapping({"imaging": {"side_lobe_db": value}})
        assert s.imaging.side_lobe_db == value
    with pytest.raises(ScenarioError, match="did you mean 'array'"):
        scenario_from_mapping({"imaging": {"side_lobe_db": "arry"}})


def test_the_tables_kept_on_disk_are_the_tables_computed(tmp_path, monkeypatch):
    """sim_us.disk_cache: the beam tables a process computed are read back by the next
    one bit for bit; another transducer gets its own file, a damaged file is computed
    again, and `USCAL_CACHE_DIR=off` writes nothing."""
    import dataclasses

    cached = beam_tables.__wrapped__  # below the in-process cache: the disk's
    compute = cached.__wrapped__
    t = transducer(ProbeConfig())
    depth = 0.012
    monkeypatch.setenv("USCAL_CACHE_DIR", "off")
    cached(t, depth)
    assert not any(tmp_path.iterdir())
    monkeypatch.setenv("USCAL_CACHE_DIR", str(tmp_path / "cache"))
    fresh = compute(t, depth)
    first = cached(t, depth)
    (kept,) = (tmp_path / "cache").iterdir()
    again = cached(t, depth)  # read from the file
    for f in dataclasses.fields(fresh):
        a, b, c = (getattr(x, f.name) for x in (fresh, first, again))
        assert type(a) is type(c)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c), err_msg=f.name)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f.name)
    other = replace(t, elevation_focus_m=0.025)
    assert cached(other, depth).elevation_fwhm[-1] != again.elevation_fwhm[-1]
    assert len(list((tmp_path / "cache").iterdir())) == 2
    kept.write_bytes(b"not an npz")
    np.testing.assert_array_equal(cached(t, depth).lateral, fresh.lateral)
    assert kept.read_bytes()[:2] == b"PK"  # written again, whole


def _direct_delay(t, depth_m: float, z: float) -> float:
    """How much deeper (displayed m) a point at elevation ``z`` is drawn than one in the
    plane, summed directly: the element's height sampled every λ/8, each pair of
    transmitting and receiving points a path at the exact distances (no paraxial
    approximation) less the lens's delays (a thin lens focusing at F), the pulse's
    spectrum summed over the pairs at each frequency, the envelope's peak on a fine time
    grid. The elevation alone (one element's column): the test of the closed form."""
    H, F = t.elevation_aperture_m, t.elevation_focus_m
    c = t.c_medium
    zeta = np.arange(-H / 2, H / 2 + 1e-12, c / t.f_hz / 8)
    lens = np.sqrt(F**2 + (H / 2) ** 2) - np.sqrt(F**2 + zeta**2)  # thickest at the centre
    d = depth_m * t.true_per_displayed
    f = np.linspace(t.f_hz * (1 - t.bandwidth), t.f_hz * (1 + t.bandwidth), 257)
    from sim_us.transducer import _excitation, _pulse_echo_response

    pulse = _excitation(t, f) * _pulse_echo_response(t, f)
    tau = np.arange(-1.5e-6, 1.5e-6, 1e-10)

    def peak(zp: float) -> float:
        one_way = (np.hypot(d, zp - zeta) + lens) / c  # per point of the height
        # Σ over transmit × receive points of exp(2πi f (t_tx + t_rx)) = (Σ exp(..))².
        field = np.exp(2j * np.pi * np.outer(f, one_way - (d + lens[len(zeta) // 2]) / c))
        spectrum = pulse * field.sum(axis=1) ** 2
        env = np.abs(np.exp(-2j * np.pi * np.outer(tau, f)) @ spectrum)
        return float(tau[np.argmax(env)])

    return (peak(z) - peak(0.0)) * t.speed_m_s / 2.0


@pytest.mark.parametrize(("depth_mm", "offsets_mm"), [(20.0, (1.0, 2.0)), (35.0, (1.0, 2.0, 3.0))])
def test_a_point_beside_the_plane_is_drawn_as_deep_as_its_paths_say(depth_mm, offsets_mm):
    """The lens's longer paths to a point beside the image plane (paper probe in water):
    the closed-form delay the simulator draws with is the direct sum's within 0.02 mm,
    from 0.03 mm (1 mm off) to 0.25 mm (3 mm off at 35 mm); in the plane it is 0."""
    from sim_us.transducer import elevation_delay

    t = transducer(ProbeConfig(), water_speed_m_s(20.0))
    depth = depth_mm * MM / t.true_per_displayed
    z = np.array(offsets_mm) * MM
    ours = elevation_delay(t, depth, np.concatenate([[0.0], z]))
    assert ours[0] == pytest.approx(0.0, abs=1e-9)
    direct = np.array([_direct_delay(t, depth, zi) for zi in z])
    assert np.all(direct > 0.02 * MM)  # a real effect to check, not noise about 0
    np.testing.assert_allclose(ours[1:], direct, atol=0.02 * MM)
    # Farther off, later: the paths grow as z².
    assert np.all(np.diff(ours[1:]) > 0)
