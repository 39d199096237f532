"""Surface speckle (``imaging.surface_speckle``): the incoherent share of a surface echo
drawn as random-phase scatterers on the surface.

Checked: a mirror at normal incidence is untouched (its echo is all coherent); an oblique
plate (only the diffuse floor returns) keeps the smooth model's mean intensity but its
echo is granular with the statistics of fully developed speckle; the speckle belongs to
the scene (same pose, same frame; a small move keeps it; a move out of the slice renews it).
The probe frame is the scene frame (see sim_us_scenes).
"""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3

from .sim_us_scenes import MM, T_IDENTITY, elevation_shift, simulator, slab

WIDE = {"width_mm": 30.0, "depth_mm": 30.0}


def _echo_band(frame: np.ndarray, smooth: np.ndarray, half_rows: int = 6) -> np.ndarray:
    """The frame's pixels within ``half_rows`` of the smooth echo's peak, per column
    (columns with no echo dropped)."""
    peak = np.argmax(smooth, axis=0)
    cols = np.flatnonzero(smooth.max(axis=0) > 0.2 * smooth.max())
    rows = peak[cols][:, None] + np.arange(-half_rows, half_rows + 1)
    rows = np.clip(rows, 0, frame.shape[0] - 1)
    return frame[rows, cols[:, None]]


def test_a_mirror_at_normal_incidence_is_untouched():
    """A polished plate (steel: no diffuse share) facing the probe returns only its
    mirror echo: surface speckle changes nothing."""
    plate = [slab(15.0, material="steel")]
    smooth = simulator(plate, **WIDE).intensity(T_IDENTITY)[0]
    speckled = simulator(plate, surface_speckle=True, **WIDE).intensity(T_IDENTITY)[0]
    np.testing.assert_allclose(speckled, smooth, rtol=1e-4, atol=1e-9 * smooth.max())


@pytest.mark.parametrize("tilt_deg", [40.0, 60.0])
def test_oblique_plate_keeps_the_mean_and_is_speckled(tilt_deg):
    """Beyond the specular lobe only the incoherent diffuse floor returns: the echo's
    energy over many independent patches is the smooth model's (within the sampling
    error of ≈ 400 speckle grains), and its intensity along the echo is exponential-like
    (contrast std/mean ≈ 1) where the smooth echo is uniform."""
    plate = [slab(15.0, tilt_deg=tilt_deg)]
    poses = np.concatenate([elevation_shift(3.0 * k) for k in range(8)])  # beyond the slice
    smooth = simulator(plate, **WIDE).intensity(poses)
    speckled = simulator(plate, surface_speckle=True, **WIDE).intensity(poses)
    ratio = speckled.sum() / smooth.sum()
    assert ratio == pytest.approx(1.0, abs=0.12)
    # Along the smooth echo's ridge, the speckled over the smooth intensity: 1 without
    # speckle; exponential (contrast 1) with it.
    ratios = []
    for f, sm in zip(speckled, smooth, strict=True):
        cols = np.flatnonzero(sm.max(axis=0) > 0.2 * sm.max())
        rows = np.argmax(sm, axis=0)[cols]
        ratios.append(f[rows, cols] / sm[rows, cols])
    on_ridge = np.concatenate(ratios)
    contrast = on_ridge.std() / on_ridge.mean()
    assert 0.6 < contrast < 1.4  # exponential intensity: 1


def test_surface_speckle_belongs_to_the_scene():
    plate = [slab(15.0, tilt_deg=45.0)]
    sim = simulator(plate, surface_speckle=True, **WIDE)
    first = sim.intensity(T_IDENTITY)[0]
    np.testing.assert_array_equal(sim.intensity(T_IDENTITY)[0], first)
    smooth = simulator(plate, **WIDE).intensity(T_IDENTITY)[0]

    # The pattern, without the level a flat reflector has at each depth (the 45° plate
    # spans 12 mm of depth: a trend every frame shares, which is not the speckle).
    trend = sim._flat_rows[:, None]

    def correlation(T):
        a = _echo_band(first / trend, smooth).ravel()
        b = _echo_band(sim.intensity(T)[0] / trend, smooth).ravel()
        return np.corrcoef(a, b)[0, 1]

    # A twentieth of the lateral resolution along the plate's own surface keeps the
    # pattern; moving out of the slice (5 mm in elevation) renews it.
    t = np.radians(45.0)
    along = se3.make(np.eye(3), 0.035 * MM * np.array([np.cos(t), np.sin(t), 0.0]))[None]
    assert correlation(along) > 0.7
    assert abs(correlation(elevation_shift(5.0))) < 0.3
