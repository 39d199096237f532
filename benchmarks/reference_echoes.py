"""sim_us's echoes against an independent acoustic model: pymust (MUST/SIMUS), issue 35.

``benchmarks/physics_reference.py`` checks the beam (lateral, axial and elevation widths,
side lobes). This checks what the image is made of, for the same probes (the paper's and
``linear75``, defined there and imported from there):

1. **Speckle** of a tissue-mimicking gel (random point scatterers, ≥ 10 per resolution
   cell, 0.5 dB/cm/MHz, c = 1540 m/s) in windows of 25 λ × 17 λ (lateral × axial; 3 × 2
   mm for the paper probe) centred at 10, 20 and 30 mm: the grain size, the full width at
   half maximum of the envelope's normalised autocovariance laterally and axially; the
   envelope SNR, mean / std (1.91 for fully developed speckle, a Rayleigh envelope); and
   the mean level against depth, in dB relative to the 10 mm window, each depth's level
   taken relative to the echo of a perfect flat reflector at that depth imaged the same
   way (sim_us's ``backscatter_db`` is defined so: relative to a perfect reflector).
   The level change holds the attenuation of the broadband pulse (its spectrum shifts
   down: it loses less than at the centre frequency; sim_us: ``transducer.band_loss``)
   and the resolution cell: speckle ∝ cell volume × peak², a flat reflector ∝ cell area ×
   peak, so the ratio goes as 1 / (lateral × elevation width) (sim_us:
   ``beam.speckle_cell_gain``, its FWHMs).
2. **A flat specular plane** (a mirror in water for the twin) at 20 mm, tilted in the image
   plane by 0, 5, 10, 15, 20, 30°: the echo level (mean over the line of each scanline's
   envelope peak, dB relative to the same surface at 0°) and the granularity along the
   line (std / mean of those peaks), for a smooth plane and a rough one. The rough one is
   the printed-PLA roughness the twin models (``twin/printing.py``, docs/paper-comparison:
   FDM, Ra 10 µm): a Gaussian height field along the normal, σ = Ra √(π/2) = 12.5 µm,
   Gaussian covariance exp(−d² / 2ℓ²), ℓ = 0.4 mm (the extrusion width). The twin renders
   a 3 mm box of ``steel`` (diffuse share 0: the reference's sheets return nothing but
   their own scattering), smooth = untextured (the mirror's lobe through the apertures),
   rough = the same box textured with ``texture_rms_m`` = σ and ``texture_length_m`` = ℓ
   (sim_us's Kirchhoff coherent factor χ = exp(−2 (k σ cos θ)²) and facets of rms slope
   σ/ℓ, ``rough_surface_shape``), each with ``surface_speckle`` off and on. A printed
   material's diffuse share (PLA's 0.1: layer corners and fine roughness, which the
   reference's surfaces do not have) is not part of this comparison.
3. **The partial volume of a sphere**: a 5 mm sphere (steel, smooth) in water, centre at
   20 and 35 mm, moved in elevation by −4 … +4 mm: the cap's peak brightness (dB relative
   to offset 0) and the depth of that peak (true mm) against the offset.
4. **A flat reflector against depth**: a perfect flat reflector facing the probe in water
   at 5 … 40 mm, its echo's peak on the scanline focused at its depth, dB re 20 mm: the
   lateral aperture grows with depth (``depth / F#``, up to the active elements) and the
   elevation lens's wavefront is flat across the plane only near its focus (the paper
   probe's sheet at 5 mm: −21 dB). The twin's level of every echo against depth is this
   (``sim_us.transducer.flat_echo``); its speckle level of part 1 is taken against it at
   each depth, as the reference's is against its own sheet.

How, reference side (pymust 0.1.9, ``simus`` + ``rf2iq`` + ``dasmtx``):

- Focused transmit, dynamic receive, as in physics_reference.py: the elements within
  depth / (2 F#) of the scanline (at most the active ones) fire, focused at the window's
  depth (the plane's, the cap top's), and receive with the same f-number (``dasmtx``'s
  ``fnumber``). A scanline at x_l over a field of scatterers is the scanline at x = 0
  over the field moved by −x_l (the aperture moves with the line): one ``simus`` per
  scanline, always on the line x = 0, with the scatterers within a lateral margin of it
  (3 lateral FWHM: beyond it the two-way PSF is below −45 dB). Envelope = |I/Q| after
  ``rf2iq`` (low-pass at fc) and ``dasmtx``. 3-D (``param.height``, ``param.focus``: the
  elevation lens), soft baffle, pymust's default element splitting. pymust counts a
  scatterer's elevation offset twice in its path (``physics_reference.pymust_depth``):
  each scatterer is handed to it at the depth that cancels the second count (before,
  the sphere's cap 2 mm beside the plane was drawn 0.10 mm too deep at 20 mm).
- A short frequency grid (cost). ``simus`` samples the spectrum finely enough for the whole
  RF from t = 0 (≈ 400-1100 frequencies at 10-30 mm); a window's echoes last a few µs.
  Its public ``FrequencyStep`` scaling is set so that the grid has period P = K / fc
  (``simus`` returns the first half-period), and a uniform receive delay
  ``param.RXdelay`` = −t0 (a phase per frequency: exact) moves the window's echoes,
  [t_lo, t_hi] from its geometry with the pulse either side, into that half-period;
  ``dasmtx`` is told the start time (``param.t0`` = t0). A band-limited spectrum sampled
  every 1 / P is the sum of the RF's copies P apart; none reaches the window's interval,
  so the RF there is the true RF. ``simus``'s RF amplitude scales as 1 / K: envelopes
  are multiplied by K so different windows compare. One approximation remains: pymust
  re-evaluates its elevation (multi-Gaussian beam) term only every 20th frequency
  sample, so the grid's step is that term's resolution; K is kept ≥ 20 fc / 1 MHz (a
  re-evaluation at least every 1 MHz: K = 260 at 13 MHz, ≥ 150 at 7.5 MHz). The stored
  ``aliasing_check`` compares, for the paper probe, one speckle line at 30 mm with
  pymust's own grid (≈ 5 % rms on the envelope, +0.3 dB on its mean intensity, the same
  sign at every depth: less in a level relative to 10 mm), and the sphere's cap at 20
  mm, 1 and 2 mm off the plane, where the points far off the plane test pymust's
  elevation term hardest (≈ 0.5 dB).
- Speckle: uniform random positions, reflection coefficients N(0, 1), density 10 per
  resolution cell (lateral × axial × elevation FWHM at the window's depth, from
  ``sim_us.beam``, which follows the transducer as pymust does; the densities are
  stored) over the window plus margins (laterally 3 lateral FWHM, axially 3 axial FWHM,
  in elevation ±1.25 slice thicknesses: the two-way elevation amplitude there is
  −38 dB). Scanlines every λ F# / 4, samples every λ / 8. Attenuation:
  ``param.attenuation`` = 0.5 dB/cm/MHz (pymust's is linear in frequency, applied at
  every frequency: the spectrum shifts down and narrows with depth). Before the grain
  and SNR, both sides' windows are detrended (a TGC: divided by the root of an
  exponential fitted to the rows' mean intensity). Level: mean envelope intensity per
  unit scatterer density, relative to the peak² of the echo of a flat sheet of
  scatterers (as for the planes, no attenuation) at that depth, normalised to the 10 mm
  window. Also printed: the attenuation alone, at fc (what sim_us applies) and over
  pymust's two-way pulse spectrum (pulse × probe²); and the SNR of the three windows
  pooled (one window holds ≈ 150 grains: its SNR scatters by ≈ 7 %).
- Planes: a sheet of equal scatterers on a λ / 4 grid (no grating echo: its first Bragg
  order would need sin θ = 2), laterally ±3 lateral FWHM about the line, ±1.5 slice
  thicknesses in elevation, the outer third each side tapered (Tukey; the two-way beam
  is below −24 dB there) so its edges do not diffract; the rough sheet's points moved
  along the normal by the height field (one field per angle, drawn along the whole
  line). Each scanline sits at a different place along the plane: the scatterers are
  moved along the plane instead, so every line meets the plane at 20 mm, the transmit
  focus (as sim_us, whose beam is focused at every depth). Smooth: 3 lines (translation
  invariant); rough: 30 lines 0.2 mm apart (6 mm of line, ≈ 15 roughness lengths).
  Water: c = 1482 m/s (20 °C, sim_us's water), no attenuation (levels are relative at
  one depth).
- Flat: the planes' sheet facing the probe (λ / 4 grid, ± 3 lateral FWHM) reaching
  ± max(1.5 slice thicknesses, H) in elevation (H the elevation aperture: the image
  method's specular points lie within ± H / 2, and in front of the lens focus the beam
  is wider than its slice), tapered; one line, transmit focus at the depth. Water as for
  the planes.
- Sphere: the probe-facing hemisphere's surface (outward normal not pointing away from
  the probe: below the equator the sphere shadows itself) within ±1.5 × max(slice
  thickness, H / 2) of the image plane in elevation (a raised-cosine taper over the
  outer 0.5 mm), a Fibonacci lattice at λ / 2, equal reflectivity; one scanline over the
  sphere's centre (the brightest: the cap is symmetric about it), transmit focused at the
  cap's top at offset 0; the envelope's peak and its depth along the line. Water as for
  the planes.

How, twin side (always live): ``BmodeSimulator.envelope`` (noise-free) of the probe as
``ProbeConfig`` gives it, with the frame's sampling changed for measuring (pixels 0.02 ×
0.01 mm for speckle, 0.05 × 0.01 mm otherwise; the probe's own scanline rule), the
pixel-scale error and image offsets off. Speckle: gel, empty scene, rendered once to
31+ mm; the same window size, three adjacent windows per depth (autocovariances
averaged, SNR pooled). Note: the twin's gel picks one scatterer per lattice cell (a third of the
finest resolution) per pixel, so at pixels finer than the cell its level rises (+8.4 dB
at these pixels for the paper probe); the level is compared relative to 10 mm, where
that cancels, and the absolute level is printed at the probe's own pixels too. Planes:
a 3 mm steel box in water (20 °C), its top face through (0, 20 mm) rotated about the
elevation axis; each column's peak within ±0.5 mm of the line over the central 8 mm.
Flat: the planes' steel box facing the probe at each depth, the mean over the central
8 mm of each column's peak, the water's two-way loss (``band_attenuation_db``) taken off.
Sphere: ``trimesh.creation.icosphere`` (5 subdivisions) of steel in water, the probe moved
in elevation, a scanline over its centre, ``surface_speckle`` off and on; the frame's
peak (no depth is shown for an echo below the −60 dB floor).
The twin displays depths at 1540 m/s: its depths are converted to true depths (× c_water
/ 1540) before comparing.

Figures: levels compared in dB (twin − reference; both clipped at −60 dB below their
reference, the display's dynamic range, where a difference between two echoes below
it means nothing); grain FWHMs as ratios twin / reference. The second-to-last line is
``worst_db=<largest |Δ dB|>``, the last ``worst_ratio=<grain FWHM ratio farthest from 1,
as max(r, 1/r)>``.

``--write`` stores the reference figures, the probe definitions, the method and the
pymust version in ``benchmarks/reference/echoes.json`` (the tests read it without
pymust); ``--stored`` prints from it (the default when pymust is absent). The twin's
side is always computed live. ``--write`` takes ≈ 10-15 min on one core (the figures
per part and probe are stored with their seconds), ``--stored`` ≈ 20 s.

Run: python benchmarks/reference_echoes.py [--probe paper|linear75|all] [--write | --stored]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import importlib.metadata  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import asdict, dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from types import ModuleType  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from scipy.ndimage import gaussian_filter  # noqa: E402
from scipy.signal.windows import tukey  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from bench.files import write_text_atomic  # noqa: E402
from sim_us import MediumConfig, ProbeConfig  # noqa: E402
from sim_us.beam import (  # noqa: E402
    axial_fwhm_m,
    band_attenuation_db,
    flat_echo_gain,
    lateral_fwhm_m,
    scanline_step,
    slice_thickness,
    speckle_cell_gain,
)
from sim_us.materials import MATERIALS, water_speed_m_s  # noqa: E402
from sim_us.raycast import AcousticScene, ScenePart  # noqa: E402
from sim_us.simulator import BmodeSimulator  # noqa: E402

ROOT = Path(_HERE).parent
STORED = Path(_HERE) / "reference" / "echoes.json"
COMMAND = "python benchmarks/reference_echoes.py --write"

Array = NDArray[np.float64]


def _physics_reference() -> ModuleType:
    """benchmarks/physics_reference.py (not a package): the probes, pymust's PARAM, the
    receive f-number and aperture, the FWHM of a profile; one definition for both."""
    name = "physics_reference"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, Path(_HERE) / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


PR = _physics_reference()
PROBES: dict[str, Callable[[], Any]] = PR.PROBES

# ------------------------------------------------------------------ settings

# Speckle: window centres, size (in wavelengths: 3 × 2 mm for the paper probe), density.
SPECKLE_DEPTHS_MM = (10.0, 20.0, 30.0)
WINDOW_WAVELENGTHS = (25.0, 17.0)  # lateral, axial
SCATTERERS_PER_CELL = 10.0
GEL = MATERIALS["gel"]
# Scatterers within this many lateral (axial) FWHM of a window: the two-way lateral PSF
# is below -45 dB past 3 FWHM (its first side lobe, ≈ -33 dB, sits at 1.6 FWHM).
LATERAL_MARGIN_FWHM = 3.0
AXIAL_MARGIN_FWHM = 3.0
# ... and within this many slice thicknesses of the image plane in elevation (the two-way
# elevation amplitude there: -38 dB; the intensity a speckle sums: -75 dB); a sheet
# (coherent: the amplitude counts) reaches further, its outer third tapered.
ELEVATION_REACH_ST = 1.25
SHEET_REACH_ST = 1.5
# Scanline spacing (in λ F#) and axial sampling (in λ) of the reference's windows.
LINE_SPACING_LAMBDA_F = 0.25
SAMPLE_SPACING_LAMBDA = 0.125
# The twin's measuring pixels (lateral, axial mm) for speckle, and for surfaces; the
# twin's speckle windows per depth (side by side).
TWIN_SPECKLE_PIXELS_MM = (0.02, 0.01)
TWIN_SURFACE_PIXELS_MM = (0.05, 0.01)
TWIN_WINDOWS = 3

# Planes: depth, tilts, sheet grid, roughness, lines.
PLANE_DEPTH_MM = 20.0
PLANE_ANGLES_DEG = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0)
SHEET_SPACING_LAMBDA = 0.25
ROUGH_RA_UM = 10.0  # FDM PLA (docs/paper-comparison.md); σ = Ra √(π/2)
ROUGH_SIGMA_M = ROUGH_RA_UM * 1e-6 * np.sqrt(np.pi / 2.0)
ROUGH_LENGTH_M = 0.4e-3  # covariance exp(-d² / 2ℓ²), as twin/printing.py
ROUGH_LINES = 30
ROUGH_LINE_SPACING_M = 0.2e-3
SMOOTH_LINES = 3
# Tukey taper of a sheet: its outer third each side, where the two-way beam is below
# -24 dB (elevation, past 1 slice thickness) or -30 dB (lateral, past 2 FWHM).
TAPER = 2.0 / 3.0
BOX_THICKNESS_M = 3e-3
TWIN_LINE_HALF_SPAN_M = 4e-3  # the twin's line: the central 8 mm
TWIN_PEAK_BAND_M = 0.5e-3

# A flat reflector facing the probe against depth (its level re FLAT_REFERENCE_MM).
FLAT_DEPTHS_MM = (5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0)
FLAT_REFERENCE_MM = 20.0

# The sphere's cap in the image plane against depth (its centre's), re the flat sheet at
# FLAT_REFERENCE_MM (per unit of surface: the same reflector, curved).
CAP_DEPTHS_MM = (10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0)

# Sphere: radius, centre depths, elevation offsets, surface sampling.
SPHERE_RADIUS_M = 2.5e-3
SPHERE_DEPTHS_MM = (20.0, 35.0)
SPHERE_OFFSETS_MM = (-4.0, -3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0)
CAP_SPACING_LAMBDA = 0.5
CAP_TAPER_M = 0.5e-3

# pymust re-evaluates its elevation (MGBM) term every this many frequency samples; its
# frequency step is kept so that this happens at least every MGBM_STEP_HZ.
MGBM_SAMPLES = 20
MGBM_STEP_HZ = 1e6
# Levels below this (dB under their reference) are taken at it: a 60 dB display.
LEVEL_FLOOR_DB = -60.0
WATER_C = water_speed_m_s(20.0)


# ------------------------------------------------------------------ measurements


def acf(env: Array) -> Array:
    """Normalised autocovariance of an image (rows = depth, columns = lateral), lags
    ≥ 0 in both axes: (rows, cols); each lag's sum divided by its number of pairs."""
    e = np.asarray(env, float) - np.mean(env)
    h, w = e.shape
    f = np.fft.rfft2(e, s=(2 * h, 2 * w))
    ones = np.fft.rfft2(np.ones_like(e), s=(2 * h, 2 * w))
    cov = np.fft.irfft2(np.abs(f) ** 2, s=(2 * h, 2 * w))[:h, :w]
    pairs = np.fft.irfft2(np.abs(ones) ** 2, s=(2 * h, 2 * w))[:h, :w]
    cov = cov / np.maximum(np.rint(pairs), 1.0)
    return cov / cov[0, 0]


def acf_fwhm(cov: Array, dx_mm: float, dz_mm: float) -> tuple[float, float]:
    """(lateral, axial) FWHM (mm) of an autocovariance from :func:`acf`, through lag 0."""
    lat = cov[0, : cov.shape[1] // 2]
    ax = cov[: cov.shape[0] // 2, 0]
    lx, lp = PR.mirrored(np.arange(len(lat)) * dx_mm, lat)
    zx, zp = PR.mirrored(np.arange(len(ax)) * dz_mm, ax)
    return float(PR.fwhm(lx, lp)), float(PR.fwhm(zx, zp))


def detrend(env: Array) -> Array:
    """The envelope (rows = depth) with its attenuation compensated (a TGC): divided by
    the root of an exponential fitted to the rows' mean intensity. Across a 2 mm window
    the gel's two-way loss changes the level by 2.6 dB at 13 MHz; left in, it would
    add to the envelope's spread (lower the SNR) and widen the autocovariance."""
    rows = np.arange(env.shape[0])
    fit = np.polyfit(rows, np.log(np.mean(env**2, axis=1)), 1)
    return env / np.exp(np.polyval(fit, rows) / 2)[:, None]


def snr(env: Array) -> float:
    """Envelope SNR, mean / std: 1.91 for fully developed speckle (Rayleigh)."""
    return float(np.mean(env) / np.std(env))


def db(v: float) -> float:
    """20 log10 of an amplitude ratio, floored at ``LEVEL_FLOOR_DB``."""
    return float(max(20.0 * np.log10(max(v, 1e-30)), LEVEL_FLOOR_DB))


def broadband_attenuation_db(case: Any, depth_m: float) -> tuple[float, float]:
    """Two-way loss (dB) of the echo energy at ``depth_m`` in gel: (at fc, as sim_us
    applies it; over pymust's pulse-echo spectrum, pulse × probe², whose higher
    frequencies attenuate more)."""
    param = PR.pymust_param(case.array, np.ones(case.array.active_elements, np.float32))
    f = np.linspace(1e3, 2.0 * param.fc, 4001)
    w = 2 * np.pi * f
    s = np.abs(param.getPulseSpectrumFunction()(w) * param.getProbeFunction()(w) ** 2) ** 2
    alpha = GEL.attenuation_db_cm_mhz * 1e2 * depth_m * 2.0  # dB per MHz, two-way
    loss = 10.0 ** (-alpha * f / 1e6 / 10.0)  # intensity
    broadband = 10.0 * np.log10(np.sum(s * loss) / np.sum(s))
    return -alpha * param.fc / 1e6, float(broadband)


# ------------------------------------------------------------------ reference (pymust)


@dataclass
class Scanline:
    """One focused transmit and its dynamic-receive scanline on x = 0 (module docstring):
    pymust's PARAM of the active aperture, the frequency grid's period K / fc and the
    shift t0 that hold the window's echoes, and the delay-and-sum matrix for that grid."""

    param: Any
    delays: Array  # (1, elements) s
    z_m: Array  # depths of the line's samples
    k: int
    t0_s: float  # true time of the RF's first sample (the echoes are shifted by it)
    pulse_s: float  # duration of pymust's two-way pulse
    das: Any


def scanline(
    a: Any,
    focus_m: float,
    z_m: Array,
    box: tuple[float, float, float, float],
    attenuation: float = 0.0,
) -> Scanline:
    """The scanline at x = 0 of array ``a`` (an ArraySpec, its speed the medium's),
    focused at ``focus_m``, sampled at ``z_m``, for scatterers within ``box`` = (lateral
    half width, shallowest, deepest, elevation half width), metres."""
    import pymust  # optional: only the reference needs pymust

    fnum = PR.receive_fnumber(a)
    n_on = int(PR.aperture(a, focus_m, fnum).sum())
    # The active aperture alone (an even count, symmetric about the line: the same
    # element positions as the full array's), so no time is spent on silent elements.
    sub = replace(a, active_elements=n_on)
    param = PR.pymust_param(sub, np.ones(n_on, np.float32))
    delays = np.asarray(pymust.txdelay(0.0, focus_m, param), float).reshape(1, -1)
    delays -= delays.min()
    param.fs = 4 * param.fc
    param.attenuation = attenuation
    param.fnumber = fnum
    _, tp = pymust.getpulse(param, 2)
    pulse = float(tp[-1])
    # The window's echoes: earliest and latest arrival over a grid of the box (transmit
    # wavefront at the point, then the nearest/farthest element), the pulse either side.
    xh, z0, z1, yh = box
    g = np.stack(
        np.meshgrid(np.linspace(-xh, xh, 9), np.linspace(-yh, yh, 9), np.linspace(z0, z1, 9)),
        axis=-1,
    ).reshape(-1, 3)
    xe = param.getElementPositions()[0].ravel()
    r = np.sqrt((g[:, :1] - xe) ** 2 + g[:, 1:2] ** 2 + g[:, 2:3] ** 2)
    tx = delays + r / a.speed_m_s
    t_lo = float(np.min(tx.min(axis=1) + r.min(axis=1) / a.speed_m_s)) - pulse
    t_hi = float(np.max(tx.max(axis=1) + r.max(axis=1) / a.speed_m_s)) + pulse
    fc = param.fc
    # The shortest period holding the echoes with room either side (and pymust's elevation
    # term re-evaluated often enough); the echoes are then shifted to its first half.
    span = t_hi - t_lo
    k = max(int(np.ceil(2.2 * span * fc)), int(np.ceil(MGBM_SAMPLES * fc / MGBM_STEP_HZ)))
    period = k / fc
    t0 = t_lo - (period / 2 - span) / 2
    p = param.copy()
    p.TXdelay = delays.copy()
    p.t0 = np.array([t0])
    das = pymust.dasmtx(1j * np.array([2 * k, n_on]), np.zeros_like(z_m), z_m, p)
    return Scanline(param, delays, np.asarray(z_m, float), k, t0, pulse, das)


def envelope(line: Scanline, pts: Array, rc: Array) -> Array:
    """|I/Q| along ``line`` of scatterers ``pts`` (n, 3: x lateral, y elevation, z depth,
    metres) of reflection coefficients ``rc``, times K (module docstring)."""
    import pymust  # optional: only the reference needs pymust
    from pymust import utils

    param = line.param
    c, fc = param.c, param.fc
    x, y, z = (np.ascontiguousarray(pts[:, i]) for i in range(3))
    z = PR.pymust_depth(y, z)  # its elevation counted once (pymust_depth)
    # simus's own frequency step (it spans the RF from t = 0, scatterers' in-plane range
    # plus the pulse); FrequencyStep scales it to fc / (K - 1/2), so that its grid,
    # fc / ceil(fc / step), has exactly the period K / fc.
    xe = param.getElementPositions()[0].ravel()
    max_d = np.sqrt(np.max((x[:, None] - xe) ** 2 + z[:, None] ** 2)) + line.pulse_s * c
    step = 1.0 / 2.0 / (2.0 * max_d / c + max(float(np.max(line.delays)), 0.0))
    opt = utils.Options()
    opt.WaitBar = False
    opt.FrequencyStep = fc / (step * (line.k - 0.5))
    # The RF shifted earlier by t0 (a uniform receive delay of -t0: exact, a phase
    # per frequency), so the window's echoes fall in the first half-period.
    param.RXdelay = np.full((1, len(xe)), -line.t0_s)
    # simus warns (through a malformed logging call) whenever FrequencyStep > 1.
    logging.disable(logging.WARNING)
    try:
        rf, _ = pymust.simus(
            x[None],
            y[None],
            z[None],
            rc[None].astype(float),
            line.delays.copy(),
            param,
            opt,
        )
    finally:
        logging.disable(logging.NOTSET)
    if rf.shape[0] != 2 * line.k:
        raise RuntimeError(
            f"pymust's frequency grid is not the one asked for ({rf.shape[0]} RF samples, "
            f"expected {2 * line.k}): its simus changed, see the module docstring"
        )
    iq = pymust.rf2iq(rf, param.fs, fc)
    return np.abs(line.das @ iq.flatten(order="F")) * line.k


def _beam_widths(case: Any, depth_m: float) -> tuple[float, float, float]:
    """(lateral, axial, elevation) FWHM (m) of the probe's beam at ``depth_m``."""
    im = case.imaging
    return (
        float(lateral_fwhm_m(im, depth_m)),
        float(axial_fwhm_m(im)),
        float(slice_thickness(im, depth_m)),
    )


def _in_medium(case: Any, c: float) -> Any:
    """The probe's array in a medium of speed ``c``."""
    return replace(case.array, speed_m_s=c)


def _sheet(u_half: float, v_half: float, spacing: float) -> tuple[Array, Array, Array]:
    """A regular grid (u, v) of a sheet ±u_half × ±v_half at ``spacing``, and its Tukey
    taper weights (the outer third each side: ``TAPER``)."""
    u = np.arange(-u_half, u_half + 1e-12, spacing)
    v = np.arange(-v_half, v_half + 1e-12, spacing)
    w = np.outer(tukey(len(u), TAPER), tukey(len(v), TAPER))
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return uu.ravel(), vv.ravel(), w.ravel()


def reference_speckle(case: Any, log: bool = True) -> dict[str, Any]:
    """Speckle figures of the gel at each depth (module docstring)."""
    a = case.array
    lam = a.speed_m_s / (a.f_mhz * 1e6)
    fnum = PR.receive_fnumber(a)
    rng = np.random.default_rng(35)
    out: dict[str, list[Any]] = {
        k: []
        for k in (
            "lateral_acf_fwhm_mm",
            "axial_acf_fwhm_mm",
            "snr",
            "level_db",
            "scatterers_per_mm3",
            "lines",
            "frequency_samples",
        )
    }
    raw: list[float] = []
    flats: list[Array] = []
    for depth_mm in SPECKLE_DEPTHS_MM:
        t0 = time.perf_counter()
        d = depth_mm * 1e-3
        lat, ax, st = _beam_widths(case, d)
        width, height = WINDOW_WAVELENGTHS[0] * lam, WINDOW_WAVELENGTHS[1] * lam
        m, mz, yh = LATERAL_MARGIN_FWHM * lat, AXIAL_MARGIN_FWHM * ax, ELEVATION_REACH_ST * st
        dx = LINE_SPACING_LAMBDA_F * lam * fnum
        xl = np.arange(-width / 2, width / 2 + 1e-12, dx)
        z = np.arange(d - height / 2, d + height / 2 + 1e-12, SAMPLE_SPACING_LAMBDA * lam)
        density = SCATTERERS_PER_CELL / (lat * ax * st)
        lo = np.array([xl[0] - m, -yh, d - height / 2 - mz])
        hi = np.array([xl[-1] + m, yh, d + height / 2 + mz])
        n = int(rng.poisson(density * np.prod(hi - lo)))
        pts = lo + (hi - lo) * rng.random((n, 3))
        rc = rng.standard_normal(n)
        line = scanline(a, d, z, (m, lo[2], hi[2], yh), GEL.attenuation_db_cm_mhz)
        env = np.empty((len(z), len(xl)))
        for j, x0 in enumerate(xl):
            near = np.abs(pts[:, 0] - x0) <= m
            env[:, j] = envelope(line, pts[near] - [x0, 0.0, 0.0], rc[near])
        # The perfect flat reflector at this depth, the same transmit and receive, no
        # attenuation: a sheet of equal scatterers on a λ/4 grid.
        ys = SHEET_REACH_ST * st
        u, v, w = _sheet(m, ys, SHEET_SPACING_LAMBDA * lam)
        zp = np.arange(d - 4 * ax, d + 4 * ax, SAMPLE_SPACING_LAMBDA * lam / 4)
        mirror = scanline(a, d, zp, (m, d, d, ys))
        sheet = np.column_stack([u, v, np.full_like(u, d)])
        peak = float(np.max(envelope(mirror, sheet, w)))
        # Mean intensity per unit density (per mm³) over the reflector's peak².
        raw.append(float(np.mean(env**2)) / (density * 1e-9) / peak**2)
        flat = detrend(env)
        flats.append(flat)
        lat_fwhm, ax_fwhm = acf_fwhm(acf(flat), dx * 1e3, SAMPLE_SPACING_LAMBDA * lam * 1e3)
        out["lateral_acf_fwhm_mm"].append(lat_fwhm)
        out["axial_acf_fwhm_mm"].append(ax_fwhm)
        out["snr"].append(snr(flat))
        out["scatterers_per_mm3"].append(density * 1e-9)
        out["lines"].append(len(xl))
        out["frequency_samples"].append(line.k)
        if log:
            print(
                f"  pymust {case.name} speckle {depth_mm:g} mm: {len(xl)} lines, "
                f"{n} scatterers, {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
            )
    out["level_db"] = [10.0 * np.log10(v / raw[0]) for v in raw]
    out["snr_pooled"] = snr(np.concatenate([f.ravel() for f in flats]))
    out["attenuation_fc_db"] = []
    out["attenuation_broadband_db"] = []
    for depth_mm in SPECKLE_DEPTHS_MM:
        at_fc, band = broadband_attenuation_db(case, depth_mm * 1e-3)
        base_fc, base_band = broadband_attenuation_db(case, SPECKLE_DEPTHS_MM[0] * 1e-3)
        out["attenuation_fc_db"].append(at_fc - base_fc)
        out["attenuation_broadband_db"].append(band - base_band)
    return out


def reference_flat(case: Any, log: bool = True) -> dict[str, Any]:
    """A perfect flat reflector facing the probe at each of ``FLAT_DEPTHS_MM`` in water:
    its echo's peak on the scanline focused at its depth, dB re FLAT_REFERENCE_MM."""
    peaks = []
    for depth_mm in FLAT_DEPTHS_MM:
        t0 = time.perf_counter()
        peaks.append(_sheet_peak(case, depth_mm * 1e-3)[0])
        if log:
            print(
                f"  pymust {case.name} flat {depth_mm:g} mm: {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
            )
    ref = peaks[FLAT_DEPTHS_MM.index(FLAT_REFERENCE_MM)]
    return {"level_db": [db(p / ref) for p in peaks], "peak": peaks}


def height_field(shape: tuple[int, int], spacing: float, rng: np.random.Generator) -> Array:
    """A Gaussian height field on a grid (σ = ``ROUGH_SIGMA_M``, covariance
    exp(−d² / 2ℓ²), ℓ = ``ROUGH_LENGTH_M``): white noise through a Gaussian of σ ℓ / √2
    (whose autocorrelation is that covariance), scaled to σ."""
    h = gaussian_filter(rng.standard_normal(shape), ROUGH_LENGTH_M / np.sqrt(2) / spacing)
    return h * (ROUGH_SIGMA_M / np.std(h))


def reference_planes(case: Any, log: bool = True) -> dict[str, Any]:
    """Echo level and granularity of a smooth and a rough plane at each tilt."""
    a = _in_medium(case, WATER_C)
    lam = a.speed_m_s / (a.f_mhz * 1e6)
    d = PLANE_DEPTH_MM * 1e-3
    lat, ax, st = _beam_widths(case, d)
    m, yh, spacing = LATERAL_MARGIN_FWHM * lat, SHEET_REACH_ST * st, SHEET_SPACING_LAMBDA * lam
    z = np.arange(d - 6 * ax, d + 6 * ax, SAMPLE_SPACING_LAMBDA * lam / 2)
    rng = np.random.default_rng(36)
    out: dict[str, Any] = {}
    for rough in (False, True):
        key = "rough" if rough else "smooth"
        peaks: list[list[float]] = []
        t0 = time.perf_counter()
        for angle in PLANE_ANGLES_DEG:
            th = np.radians(angle)
            # Along the plane: each line's footprint (±m laterally is ±m / cos θ along it).
            half = m / np.cos(th)
            n_lines = ROUGH_LINES if rough else SMOOTH_LINES
            step = ROUGH_LINE_SPACING_M if rough else spacing / SMOOTH_LINES
            ul = (np.arange(n_lines) - (n_lines - 1) / 2) * step
            u = np.arange(ul[0] - half, ul[-1] + half + 1e-12, spacing)
            v = np.arange(-yh, yh + 1e-12, spacing)
            h = (
                height_field((len(u), len(v)), spacing, rng)
                if rough
                else np.zeros((len(u), len(v)))
            )
            uu, vv = np.meshgrid(u, v, indexing="ij")
            reach = half * np.sin(th) + 3 * ROUGH_SIGMA_M
            line = scanline(a, d, z, (m + 3 * ROUGH_SIGMA_M, d - reach, d + reach, yh))
            row: list[float] = []
            for u0 in ul:
                on = np.abs(u - u0) <= half
                s, vs, hs = (uu[on] - u0).ravel(), vv[on].ravel(), h[on].ravel()
                w = np.outer(tukey(int(on.sum()), TAPER), tukey(len(v), TAPER)).ravel()
                # The plane through (0, d) tilted by θ in the image plane; its normal
                # (−sin θ, cos θ) in (x, z); heights along it.
                pts = np.column_stack(
                    [s * np.cos(th) - hs * np.sin(th), vs, d + s * np.sin(th) + hs * np.cos(th)]
                )
                row.append(float(np.max(envelope(line, pts, w))))
            peaks.append(row)
        mean0 = float(np.mean(peaks[0]))
        out[key] = {
            "level_db": [db(float(np.mean(p)) / mean0) for p in peaks],
            "granularity": [float(np.std(p) / np.mean(p)) for p in peaks],
            "mean_peak": [float(np.mean(p)) for p in peaks],
            "lines": len(peaks[0]),
        }
        if log:
            print(
                f"  pymust {case.name} {key} plane: {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
            )
    out["rough_at_0_re_smooth_db"] = db(
        out["rough"]["mean_peak"][0] / out["smooth"]["mean_peak"][0]
    )
    return out


def fibonacci_sphere(radius: float, spacing: float) -> tuple[Array, Array]:
    """Points (n, 3) quasi-uniformly on a sphere about 0 about ``spacing`` apart (a
    Fibonacci lattice: equal area per point) and their outward unit normals."""
    n = int(np.ceil(4 * np.pi * radius**2 / spacing**2))
    i = np.arange(n) + 0.5
    cos_t = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    sin_t = np.sqrt(1.0 - cos_t**2)
    normal = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    return radius * normal, normal


def _sphere_setup(
    case: Any, depth_mm: float
) -> tuple[Scanline, Callable[[float], tuple[Array, Array]]]:
    """The scanline over a sphere centred at ``depth_mm`` (transmit focus at its cap top)
    and its scatterers at an elevation offset (mm): (points, weights)."""
    a = _in_medium(case, WATER_C)
    lam = a.speed_m_s / (a.f_mhz * 1e6)
    R = SPHERE_RADIUS_M
    surface, normal = fibonacci_sphere(R, CAP_SPACING_LAMBDA * lam)
    # Probe-facing: the outward normal not pointing away from the probe (z is depth).
    surface = surface[normal[:, 2] <= 0.0]
    d = depth_mm * 1e-3
    _, ax, st = _beam_widths(case, d - R)
    y_max = SHEET_REACH_ST * max(st, a.elevation_aperture_mm * 1e-3 / 2)
    z = np.arange(d - R - 4 * ax, d + 4 * ax, SAMPLE_SPACING_LAMBDA * lam / 2)
    line = scanline(a, d - R, z, (R, d - R, d, y_max))

    def cap(off_mm: float) -> tuple[Array, Array]:
        pts = surface + np.array([0.0, off_mm * 1e-3, d])
        keep = np.abs(pts[:, 1]) <= y_max
        # A raised-cosine taper to the elevation cut (its edge would diffract).
        w = np.clip((y_max - np.abs(pts[keep, 1])) / CAP_TAPER_M, 0.0, 1.0)
        return pts[keep], 0.5 - 0.5 * np.cos(np.pi * w)

    return line, cap


def reference_sphere(case: Any, log: bool = True) -> dict[str, Any]:
    """The cap's peak (dB re offset 0) and its depth (mm) against elevation offset."""
    out: dict[str, Any] = {}
    for depth_mm in SPHERE_DEPTHS_MM:
        t0 = time.perf_counter()
        line, cap = _sphere_setup(case, depth_mm)
        peaks, depths = [], []
        for off_mm in SPHERE_OFFSETS_MM:
            env = envelope(line, *cap(off_mm))
            k = int(np.argmax(env))
            peaks.append(float(env[k]))
            depths.append(float(line.z_m[k]) * 1e3)
        p0 = peaks[SPHERE_OFFSETS_MM.index(0.0)]
        out[f"{depth_mm:g}"] = {
            "level_db": [db(p / p0) for p in peaks],
            "depth_mm": depths,
            "surface_points": len(cap(0.0)[0]),
        }
        if log:
            print(
                f"  pymust {case.name} sphere {depth_mm:g} mm: {time.perf_counter() - t0:.0f} s",
                file=sys.stderr,
            )
    return out


def _sheet_peak(case: Any, depth_m: float) -> tuple[float, float]:
    """A flat sheet facing the probe at ``depth_m`` in water: its echo's peak on the
    scanline focused there, and its scatterers' spacing (m)."""
    a = _in_medium(case, WATER_C)
    lam = WATER_C / (a.f_mhz * 1e6)
    lat, ax, st = _beam_widths(case, depth_m)
    # Laterally the focus's spot; in elevation the lens's wavefront, flat only near its
    # focus: at least the aperture's height each side (the image method's specular points
    # lie within ± H / 2), tapered.
    m, ys = LATERAL_MARGIN_FWHM * lat, max(SHEET_REACH_ST * st, a.elevation_aperture_mm * 1e-3)
    spacing = SHEET_SPACING_LAMBDA * lam
    u, v, w = _sheet(m, ys, spacing)
    zp = np.arange(depth_m - 4 * ax, depth_m + 4 * ax, SAMPLE_SPACING_LAMBDA * lam / 4)
    line = scanline(a, depth_m, zp, (m, depth_m, depth_m, ys))
    sheet = np.column_stack([u, v, np.full_like(u, depth_m)])
    return float(np.max(envelope(line, sheet, w))), spacing


def reference_cap_depth(case: Any, log: bool = True) -> dict[str, Any]:
    """The sphere's cap in the image plane, its centre at each of ``CAP_DEPTHS_MM``: the
    echo's peak per unit of surface, dB re a flat sheet's at FLAT_REFERENCE_MM."""
    t0 = time.perf_counter()
    lam = WATER_C / (case.array.f_mhz * 1e6)
    sheet, sheet_spacing = _sheet_peak(case, FLAT_REFERENCE_MM * 1e-3)
    levels = []
    for depth_mm in CAP_DEPTHS_MM:
        line, cap = _sphere_setup(case, depth_mm)
        peak = float(np.max(envelope(line, *cap(0.0))))
        # Per unit of surface: each point stands for its spacing² of it.
        levels.append(db(peak * (CAP_SPACING_LAMBDA * lam) ** 2 / (sheet * sheet_spacing**2)))
    if log:
        print(
            f"  pymust {case.name} cap against depth: {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
        )
    return {"level_db": levels}


def default_grid_envelope(line: Scanline, pts: Array, rc: Array) -> Array:
    """As :func:`envelope`, with pymust's own frequency grid (no shift): the check."""
    import pymust  # optional: only the reference needs pymust
    from pymust import utils

    p = line.param.copy()
    p.RXdelay = np.zeros((1, line.delays.shape[1]))
    opt = utils.Options()
    opt.WaitBar = False
    depth = PR.pymust_depth(pts[:, 1], pts[:, 2])  # its elevation counted once
    rf, _ = pymust.simus(
        pts[:, 0][None], pts[:, 1][None], depth[None], rc[None], line.delays.copy(), p, opt
    )
    iq = pymust.rf2iq(rf, p.fs, p.fc)
    q = p.copy()
    q.TXdelay = line.delays.copy()
    q.t0 = np.array([0.0])
    das = pymust.dasmtx(1j * np.array(iq.shape), np.zeros_like(line.z_m), line.z_m, q)
    return np.abs(das @ iq.flatten(order="F")) * (rf.shape[0] // 2)


def aliasing_check(case: Any) -> dict[str, Any]:
    """The short, shifted frequency grid against pymust's own (module docstring): one
    speckle line of 1000 scatterers at 30 mm in gel (the rms difference of the envelopes,
    relative, and the bias of their mean intensity, dB), and the sphere's cap at 20 mm,
    1 and 2 mm off the plane (its level re offset 0 both ways: the far off-plane points
    are where pymust's elevation term is least resolved)."""
    a = case.array
    lam = a.speed_m_s / (a.f_mhz * 1e6)
    d = 30e-3
    lat, ax, st = _beam_widths(case, d)
    m, mz, yh = LATERAL_MARGIN_FWHM * lat, AXIAL_MARGIN_FWHM * ax, ELEVATION_REACH_ST * st
    height = WINDOW_WAVELENGTHS[1] * lam
    z = np.arange(d - height / 2, d + height / 2 + 1e-12, SAMPLE_SPACING_LAMBDA * lam)
    lo = np.array([-m, -yh, d - height / 2 - mz])
    hi = np.array([m, yh, d + height / 2 + mz])
    rng = np.random.default_rng(37)
    pts = lo + (hi - lo) * rng.random((1000, 3))
    rc = rng.standard_normal(1000)
    line = scanline(a, d, z, (m, lo[2], hi[2], yh), GEL.attenuation_db_cm_mhz)
    fast = envelope(line, pts, rc)
    full = default_grid_envelope(line, pts, rc)
    speckle = {
        "depth_mm": d * 1e3,
        "scatterers": len(pts),
        "frequency_samples": line.k,
        "envelope_rms_difference": float(np.linalg.norm(fast - full) / np.linalg.norm(full)),
        "intensity_bias_db": float(10.0 * np.log10(np.mean(fast**2) / np.mean(full**2))),
    }
    cap_line, cap = _sphere_setup(case, 20.0)
    offsets = (0.0, 1.0, 2.0)
    peaks = {k: [] for k in ("short", "default")}
    for off in offsets:
        pts, w = cap(off)
        peaks["short"].append(float(np.max(envelope(cap_line, pts, w))))
        peaks["default"].append(float(np.max(default_grid_envelope(cap_line, pts, w))))
    sphere = {
        "centre_mm": 20.0,
        "offsets_mm": list(offsets[1:]),
        "level_db": [db(v / peaks["short"][0]) for v in peaks["short"][1:]],
        "level_db_default_grid": [db(v / peaks["default"][0]) for v in peaks["default"][1:]],
    }
    return {"speckle": speckle, "sphere": sphere}


def reference_figures(case: Any, parts: tuple[str, ...], log: bool = True) -> dict[str, Any]:
    """Every reference figure of one probe, with the seconds each part took."""
    out: dict[str, Any] = {"receive_fnumber": round(PR.receive_fnumber(case.array), 4)}
    seconds: dict[str, float] = {}
    with threadpool_limits(1):  # one core (the budget stated in the docstring)
        for part, fn in (
            ("speckle", reference_speckle),
            ("planes", reference_planes),
            ("sphere", reference_sphere),
            ("flat", reference_flat),
            ("cap_depth", reference_cap_depth),
        ):
            if part not in parts:
                continue
            t0 = time.perf_counter()
            out[part] = fn(case, log)
            seconds[part] = round(time.perf_counter() - t0, 1)
        if case.name == "paper" and "speckle" in parts and "sphere" in parts:
            t0 = time.perf_counter()
            out["aliasing_check"] = aliasing_check(case)
            seconds["aliasing_check"] = round(time.perf_counter() - t0, 1)
    out["seconds"] = seconds
    return out


# ------------------------------------------------------------------ twin (sim_us)


def _in_water(case: Any) -> ProbeConfig:
    """The probe imaging water as the reference's does: its scanner's delays and depths at
    the water's speed (pymust's array is given the water's speed for its delays and its
    propagation alike, so its beam is in focus). At its own 1540 m/s the twin's beam in
    water is out of focus (README, "The beam in water"), which the reference's is not: the
    plane 5° off read −0.3 dB against pymust's −4.1."""
    return replace(case.imaging, assumed_speed_m_s=WATER_C)


def _measuring(probe: ProbeConfig, width_mm: float, depth_mm: float, pixels: tuple) -> ProbeConfig:
    """The probe with a frame for measuring: its size and pixels changed, the pixel-scale
    error and image offsets off; everything else (beam, scanlines, elevation) as given."""
    return replace(
        probe,
        width_mm=width_mm,
        depth_mm=depth_mm,
        pixel_spacing_mm=pixels,
        pixel_scale_error_pct=(0.0, 0.0),
        image_origin_offset_mm=0.0,
        lateral_offset_mm=0.0,
    )


def _pose(rotation_deg: float = 0.0, about_m: float = 0.0, elevation_m: float = 0.0) -> Array:
    """A probe pose (4, 4) in the scene: turned by ``rotation_deg`` about the elevation
    axis through (0, about_m, 0) and moved by ``elevation_m`` along it, so that the scene
    appears turned by −rotation and moved by −elevation in the image."""
    th = np.radians(rotation_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]
    pivot = np.array([0.0, about_m, 0.0])
    T[:3, 3] = pivot - T[:3, :3] @ pivot + [0.0, 0.0, elevation_m]
    return T


def twin_speckle(case: Any, depths_mm: tuple[float, ...] = SPECKLE_DEPTHS_MM) -> dict[str, Any]:
    """The twin's gel at ``depths_mm``: grain FWHMs, SNR and level (module docstring)."""
    im = case.imaging
    lam_mm = GEL.speed_m_s / (im.f_mhz * 1e6) * 1e3
    width, height = WINDOW_WAVELENGTHS[0] * lam_mm, WINDOW_WAVELENGTHS[1] * lam_mm
    sx, sz = TWIN_SPECKLE_PIXELS_MM
    n_cols = round(width / sx)
    frame_w = 2.0 * round((TWIN_WINDOWS * width / 2 + 1.0) / sx) * sx  # 1 mm spare each side
    depth = max(depths_mm) + height / 2 + 1.0
    out: dict[str, Any] = {k: [] for k in ("lateral_acf_fwhm_mm", "axial_acf_fwhm_mm", "snr")}
    raw: list[float] = []
    native: list[float] = []
    pooled: list[Array] = []
    for pixels, levels in (((sx, sz), raw), (im.pixel_spacing_mm, native)):
        probe = _measuring(im, frame_w, depth, pixels)
        sim = BmodeSimulator(AcousticScene(()), probe, MediumConfig(kind="gel"))
        env = sim.envelope(np.eye(4)[None])[0].astype(float)
        H, W = env.shape
        y = np.arange(H) * pixels[1]
        x = (np.arange(W) - (W - 1) / 2) * pixels[0]
        for d in depths_mm:
            rows = np.abs(y - d) <= height / 2
            cols = np.abs(x) <= TWIN_WINDOWS * width / 2
            levels.append(float(np.mean(env[np.ix_(rows, cols)] ** 2)))
            if pixels != (sx, sz):
                continue
            first = int(np.flatnonzero(cols)[0])
            wins = [
                detrend(env[rows, first + i * n_cols : first + (i + 1) * n_cols])
                for i in range(TWIN_WINDOWS)
            ]
            pooled += [w.ravel() for w in wins]
            lat, ax = acf_fwhm(np.mean([acf(w) for w in wins], axis=0), sx, sz)
            out["lateral_acf_fwhm_mm"].append(lat)
            out["axial_acf_fwhm_mm"].append(ax)
            out["snr"].append(snr(np.concatenate([w.ravel() for w in wins])))
    # The level is taken against a flat reflector at each depth, as the reference's: the
    # twin's flat reflector's echo there (checked against pymust's, the "flat" part).
    flat = flat_echo_gain(im, np.array(depths_mm) * 1e-3, GEL.speed_m_s)
    per_flat = list(np.array(raw) / flat**2)
    out["level_db"] = [10.0 * np.log10(v / per_flat[0]) for v in per_flat]
    out["snr_pooled"] = snr(np.concatenate(pooled))
    out["absolute_db"] = [10.0 * np.log10(v) for v in raw]
    out["absolute_native_db"] = [10.0 * np.log10(v) for v in native]
    return out


def _plate(depth_m: float) -> trimesh.Trimesh:
    """A steel plate (lateral 40 mm, thick ``BOX_THICKNESS_M``, 30 mm in elevation), its
    top face (facing the probe) at ``depth_m``."""
    box = trimesh.creation.box(extents=[40e-3, BOX_THICKNESS_M, 30e-3])
    box.apply_translation([0.0, depth_m + BOX_THICKNESS_M / 2, 0.0])
    return box


def twin_planes(case: Any) -> dict[str, Any]:
    """The twin's plane at each tilt: smooth (untextured steel) and rough (textured with
    σ and ℓ), surface speckle off and on; level (dB re 0°) and granularity (std/mean)."""
    im = _in_water(case)
    d = PLANE_DEPTH_MM * 1e-3
    to_display = im.assumed_speed_m_s / WATER_C  # displayed / true depth in water
    sx, sy = TWIN_SURFACE_PIXELS_MM
    reach = d + TWIN_LINE_HALF_SPAN_M * np.tan(np.radians(max(PLANE_ANGLES_DEG)))
    depth_mm = (reach * to_display + 2e-3) * 1e3
    poses = np.array([_pose(-a, d) for a in PLANE_ANGLES_DEG])  # the plane turned by +a
    mesh = _plate(d)
    out: dict[str, Any] = {}
    for rough in (False, True):
        part = ScenePart("plate", mesh, "steel")
        if rough:
            n_v = len(mesh.vertices)
            part = ScenePart(
                "plate",
                mesh,
                "steel",
                np.asarray(mesh.vertices, float).copy(),
                np.full(n_v, ROUGH_SIGMA_M),
                ROUGH_LENGTH_M,
            )
        mean0 = None
        for speckle in (False, True):
            probe = replace(_measuring(im, 12.0, depth_mm, (sx, sy)), surface_speckle=speckle)
            sim = BmodeSimulator(AcousticScene((part,)), probe, MediumConfig())
            env = sim.envelope(poses).astype(float)
            H, W = env.shape[1:]
            x = (np.arange(W) - (W - 1) / 2) * sx * 1e-3
            cols = np.flatnonzero(np.abs(x) <= TWIN_LINE_HALF_SPAN_M)
            y = np.arange(H) * sy * 1e-3
            peaks = []
            for f, a in enumerate(PLANE_ANGLES_DEG):
                line = (d + x[cols] * np.tan(np.radians(a))) * to_display
                band = np.abs(y[:, None] - line[None, :]) <= TWIN_PEAK_BAND_M
                peaks.append(np.max(np.where(band, env[f][:, cols], 0.0), axis=0))
            key = ("rough" if rough else "smooth") + ("_speckle" if speckle else "")
            mean0 = float(np.mean(peaks[0]))
            out[key] = {
                "level_db": [db(float(np.mean(p)) / mean0) for p in peaks],
                "granularity": [float(np.std(p) / np.mean(p)) for p in peaks],
                "mean_peak": [float(np.mean(p)) for p in peaks],
            }
    for suffix in ("", "_speckle"):
        out["rough_at_0_re_smooth_db" + suffix] = db(
            out["rough" + suffix]["mean_peak"][0] / out["smooth" + suffix]["mean_peak"][0]
        )
    return out


def _twin_plate_peak(case: Any, depth_mm: float) -> float:
    """The twin's steel plate facing the probe in water at ``depth_mm``: the mean over the
    central 8 mm of each column's peak, the water's two-way loss taken off (the
    reference's water does not attenuate)."""
    im = _in_water(case)
    sx, sy = TWIN_SURFACE_PIXELS_MM
    d = depth_mm * 1e-3
    probe = _measuring(im, 12.0, depth_mm + 2.0, (sx, sy))
    sim = BmodeSimulator(
        AcousticScene((ScenePart("plate", _plate(d), "steel"),)), probe, MediumConfig()
    )
    env = sim.envelope(np.eye(4)[None])[0].astype(float)
    H, W = env.shape
    x = (np.arange(W) - (W - 1) / 2) * sx * 1e-3
    y = np.arange(H) * sy * 1e-3  # displayed at the water's speed: true depth
    band = np.abs(y - d) <= TWIN_PEAK_BAND_M
    peak = float(np.mean(env[band][:, np.abs(x) <= TWIN_LINE_HALF_SPAN_M].max(axis=0)))
    return peak * 10.0 ** (float(band_attenuation_db(probe, sim.medium, d)) / 20.0)


def twin_flat(case: Any) -> dict[str, Any]:
    """The twin's plate (:func:`_twin_plate_peak`) at each of ``FLAT_DEPTHS_MM``, dB re
    FLAT_REFERENCE_MM."""
    peaks = [_twin_plate_peak(case, depth_mm) for depth_mm in FLAT_DEPTHS_MM]
    ref = peaks[FLAT_DEPTHS_MM.index(FLAT_REFERENCE_MM)]
    return {"level_db": [db(p / ref) for p in peaks]}


def _twin_sphere_setup(im: ProbeConfig, depth_m: float) -> tuple[AcousticScene, ProbeConfig]:
    """A smooth steel sphere (radius SPHERE_RADIUS_M) centred at ``depth_m`` in water, and
    the measuring probe whose scanline runs over its centre."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_M)
    mesh.apply_translation([0.0, depth_m, 0.0])
    sx, sy = TWIN_SURFACE_PIXELS_MM
    to_display = im.assumed_speed_m_s / WATER_C
    probe = _measuring(im, 8.0, (depth_m + 1e-3) * to_display * 1e3, (sx, sy))
    # A whole number of scanline steps each side of the centre column: a scanline runs
    # over the sphere's centre (the simulator's lines start at column 0).
    step = scanline_step(probe, sx * 1e-3)
    half = step * np.ceil(4.0 / (step * sx))
    probe = replace(probe, width_mm=round(2.0 * half * sx, 6))
    return AcousticScene((ScenePart("sphere", mesh, "steel"),)), probe


def twin_cap_depth(case: Any) -> dict[str, Any]:
    """The twin's smooth steel sphere in the image plane at each of ``CAP_DEPTHS_MM``, its
    peak dB re the steel plate's at FLAT_REFERENCE_MM (:func:`_twin_plate_peak`), the
    water's loss taken off both."""
    im = _in_water(case)
    flat = _twin_plate_peak(case, FLAT_REFERENCE_MM)
    levels = []
    for depth_mm in CAP_DEPTHS_MM:
        d = depth_mm * 1e-3
        scene, probe = _twin_sphere_setup(im, d)
        sim = BmodeSimulator(scene, probe, MediumConfig())
        peak = float(sim.envelope(np.eye(4)[None])[0].max())
        loss = float(band_attenuation_db(probe, sim.medium, d - SPHERE_RADIUS_M))
        levels.append(db(peak * 10.0 ** (loss / 20.0) / flat))
    return {"level_db": levels}


def twin_sphere(case: Any) -> dict[str, Any]:
    """The twin's sphere cap against elevation offset, surface speckle off and on: peak
    (dB re offset 0) and its true depth (mm); keys "<depth>" and "<depth>_speckle"."""
    im = _in_water(case)
    to_display = im.assumed_speed_m_s / WATER_C
    sy = TWIN_SURFACE_PIXELS_MM[1]
    out: dict[str, Any] = {}
    for depth_mm in SPHERE_DEPTHS_MM:
        scene, probe = _twin_sphere_setup(im, depth_mm * 1e-3)
        # The probe moved by −e in elevation: the sphere at +e in the image.
        poses = np.array([_pose(elevation_m=-e * 1e-3) for e in SPHERE_OFFSETS_MM])
        for speckle in (False, True):
            sim = BmodeSimulator(scene, replace(probe, surface_speckle=speckle), MediumConfig())
            env = sim.envelope(poses).astype(float)
            peaks = env.reshape(len(poses), -1).max(axis=1)
            rows = np.array([np.unravel_index(int(np.argmax(e)), e.shape)[0] for e in env])
            p0 = float(peaks[SPHERE_OFFSETS_MM.index(0.0)])
            out[f"{depth_mm:g}" + ("_speckle" if speckle else "")] = {
                "level_db": [db(float(p) / p0) for p in peaks],
                "depth_mm": [float(r) * sy / to_display for r in rows],
            }
    return out


def twin_figures(case: Any, parts: tuple[str, ...]) -> dict[str, Any]:
    """Every twin figure of one probe (live), with the seconds each part took."""
    out: dict[str, Any] = {}
    seconds: dict[str, float] = {}
    for part, fn in (
        ("speckle", twin_speckle),
        ("planes", twin_planes),
        ("sphere", twin_sphere),
        ("flat", twin_flat),
        ("cap_depth", twin_cap_depth),
    ):
        if part in parts:
            t0 = time.perf_counter()
            out[part] = fn(case)
            seconds[part] = round(time.perf_counter() - t0, 1)
    out["seconds"] = seconds
    return out


# ------------------------------------------------------------------ stored reference

# The parts computed per probe (linear75: the cheap ones, see the module docstring).
PARTS: dict[str, tuple[str, ...]] = {
    "paper": ("speckle", "planes", "sphere", "flat", "cap_depth"),
    "linear75": ("speckle", "sphere", "flat", "cap_depth"),
}

METHOD: dict[str, str] = {
    "common": "pymust simus (3-D: param.height/focus, soft baffle, default element "
    "splitting) + rf2iq (low-pass at fc) + dasmtx; focused transmit at the window's depth "
    "(the plane's, the cap top's) with the elements within depth/(2 F#) of the line (F# "
    "from the element directivity, 0.71 at the edge: physics_reference.py's "
    "receive_fnumber and aperture), only those elements simulated, the same f-number in "
    "receive (dasmtx fnumber); one simus per scanline on x = 0, the scatterers moved by "
    "-x_l instead of the line, those within 3 lateral FWHM of it; envelope |I/Q|; each "
    "scatterer at elevation y, depth z handed to simus at depth sqrt(z^2 - y^2): pymust's "
    "pfield takes r = sqrt(d^2 + y^2) and its MGBM term adds y^2/2r again, so its r is made "
    "the in-plane distance (physics_reference.pymust_depth)",
    "frequency_grid": "options.FrequencyStep set so simus's grid has period P = K/fc "
    "(simus returns [0, P/2)); param.RXdelay = -t0 for every element (a uniform receive "
    "delay: a phase per frequency) shifts the window's echoes [t_lo, t_hi] (geometry, the "
    "two-way pulse's duration either side) to the middle of that half-period; dasmtx "
    "param.t0 = t0; envelopes x K (simus's RF scales as 1/K); K = max(2.2 (t_hi - t_lo) fc, "
    "20 fc / 1 MHz): pymust re-evaluates its elevation (MGBM) term every 20th frequency "
    "sample, at least every 1 MHz here; aliasing_check: against pymust's own grid",
    "speckle": "gel: uniform random scatterers (Poisson count), RC ~ N(0,1), 10 per "
    "lateral x axial x elevation FWHM cell at the window's depth (sim_us.beam's widths; "
    "densities stored) over the window (25 x 17 wavelengths) plus 3 lateral / 3 axial FWHM "
    "and +-1.25 slice thicknesses; attenuation 0.5 dB/cm/MHz (param.attenuation), c 1540; "
    "lines every lambda F#/4, samples every lambda/8; each window detrended (divided by the "
    "root of an exponential fitted to its rows' mean intensity) before: grain = FWHM of "
    "the envelope's normalised autocovariance (each lag's sum over its pair count) through "
    "lag 0, SNR = mean/std (snr_pooled: the three windows together); level = mean "
    "intensity (not detrended) per scatterer/mm^3 over the peak^2 of a flat sheet's echo "
    "(as the planes', no attenuation) at the same depth, dB re the first depth; "
    "attenuation_* = the loss alone re the first depth, at fc and over pymust's pulse-echo "
    "spectrum (pulse x probe^2)",
    "planes": "sheet of equal scatterers on a lambda/4 grid, +-3 lateral FWHM (along the "
    "plane: /cos) x +-1.5 slice thicknesses, Tukey-tapered (the outer third each side), "
    "tilted in the image plane through (0, depth); each line meets it at the depth "
    "(scatterers moved along the plane), transmit focus there; rough: heights along the "
    "normal, Gaussian field sigma = Ra sqrt(pi/2), Ra 10 um, covariance exp(-d^2/2l^2), l "
    "0.4 mm (white noise through a Gaussian of l/sqrt2, scaled to sigma), one field per "
    "angle; smooth: 3 lines, rough: 30 lines 0.2 mm apart; level = mean over lines of the "
    "envelope peak, dB re 0 deg of the same surface (floored at -60); granularity = "
    "std/mean of the peaks; water: c 1482.4 (20 C), no attenuation",
    "flat": "a sheet of equal scatterers on a lambda/4 grid facing the probe, +-3 lateral "
    "FWHM x +-max(1.5 slice thicknesses, the elevation aperture H), Tukey-tapered (the "
    "outer third each side), at each depth; one line, transmit focus at the depth; "
    "level = the envelope's peak, dB re 20 mm; water as for the planes",
    "cap_depth": "the sphere part's scatterers (radius 2.5 mm, offset 0) centred at each "
    "depth, one line over the centre, transmit focus at the cap top; level = the "
    "envelope's peak per unit of surface (x the lattice spacing^2), dB re the flat part's "
    "sheet at 20 mm (x its spacing^2): one reflector, curved against flat",
    "sphere": "radius 2.5 mm, centre at the depth, moved in elevation; scatterers: "
    "Fibonacci lattice at lambda/2 on the hemisphere facing the probe, within +-1.5 max("
    "slice thickness, H/2) of the image plane (raised-cosine taper over 0.5 mm), equal RC; "
    "one line over the centre, transmit focus at the cap top; peak of the envelope along "
    "the line and its depth (true mm); level dB re offset 0 (floored at -60); water as "
    "for the planes",
}


def probe_record(case: Any, ref: dict[str, Any]) -> dict[str, Any]:
    """The stored definition and figures of one probe."""
    rec: dict[str, Any] = {
        "description": case.description,
        "array": asdict(case.array),
        "imaging": {
            k: getattr(case.imaging, k)
            for k in (
                "f_mhz",
                "bandwidth_pct",
                "pitch_mm",
                "kerf_mm",
                "active_elements",
                "elevation_aperture_mm",
                "elevation_focus_mm",
                "width_mm",
            )
        },
        "parts": list(PARTS[case.name]),
    }
    rec.update(ref)
    return rec


def _rounded(v: Any) -> Any:
    """Figures as stored: floats to 4 significant decimals, NaN as null."""
    if isinstance(v, dict):
        return {k: _rounded(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_rounded(x) for x in v]
    if isinstance(v, bool | int | str) or v is None:
        return v
    f = float(v)
    return round(f, 4) if np.isfinite(f) else None


def write_stored(records: dict[str, dict[str, Any]]) -> None:
    """Write (or update, probe by probe) ``benchmarks/reference/echoes.json``."""
    data: dict[str, Any] = {
        "what": "pymust echo figures: speckle, specular plane vs angle, sphere partial "
        "volume (benchmarks/reference_echoes.py's docstring)",
        "command": COMMAND,
        "pymust_version": importlib.metadata.version("pymust"),
        "settings": {
            "speckle_depths_mm": list(SPECKLE_DEPTHS_MM),
            "window_wavelengths": list(WINDOW_WAVELENGTHS),
            "scatterers_per_cell": SCATTERERS_PER_CELL,
            "gel_attenuation_db_cm_mhz": GEL.attenuation_db_cm_mhz,
            "plane_depth_mm": PLANE_DEPTH_MM,
            "plane_angles_deg": list(PLANE_ANGLES_DEG),
            "rough_ra_um": ROUGH_RA_UM,
            "rough_sigma_um": ROUGH_SIGMA_M * 1e6,
            "rough_length_mm": ROUGH_LENGTH_M * 1e3,
            "flat_depths_mm": list(FLAT_DEPTHS_MM),
            "flat_reference_mm": FLAT_REFERENCE_MM,
            "cap_depths_mm": list(CAP_DEPTHS_MM),
            "sphere_radius_mm": SPHERE_RADIUS_M * 1e3,
            "sphere_depths_mm": list(SPHERE_DEPTHS_MM),
            "sphere_offsets_mm": list(SPHERE_OFFSETS_MM),
            "water_speed_m_s": WATER_C,
            "level_floor_db": LEVEL_FLOOR_DB,
        },
        "method": METHOD,
        "probes": records,
    }
    if STORED.exists():
        old = json.loads(STORED.read_text())
        old["probes"].update(records)
        data["probes"] = {k: old["probes"][k] for k in PROBES if k in old["probes"]}
    STORED.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(_rounded(data), indent=1, ensure_ascii=False)
    # Lists of numbers on one line each.
    text = re.sub(
        r"\[\s*([-0-9.e,\s]*?|null)\s*\]",
        lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]",
        text,
    )
    write_text_atomic(STORED, text + "\n")


# ------------------------------------------------------------------ printing


def _num(v: Any) -> float:
    return float("nan") if v is None else float(v)


class Tally:
    """The comparisons made: grain FWHM ratios and level differences (dB)."""

    def __init__(self) -> None:
        self.ratios: list[float] = []
        self.levels: list[float] = []

    def ratio(self, twin: float, ref: float) -> float:
        q = twin / ref if np.isfinite(twin) and np.isfinite(ref) and ref > 0 else float("nan")
        self.ratios.append(q)
        return q

    def level(self, twin: float, ref: float) -> float:
        d = twin - ref
        self.levels.append(d)
        return d


def print_speckle(case: Any, ref: dict[str, Any], twin: dict[str, Any], tally: Tally) -> None:
    im = case.imaging
    print(
        f"\n{case.name} speckle (gel, {GEL.attenuation_db_cm_mhz:g} dB/cm/MHz, windows "
        f"{WINDOW_WAVELENGTHS[0]:g} × {WINDOW_WAVELENGTHS[1]:g} λ): grain = envelope "
        "autocovariance FWHM; level dB re the 10 mm window (reference: re a flat "
        "reflector at each depth)"
    )
    print(
        f"{'depth':>5} | {'lateral grain mm':^17} | {'axial grain mm':^17} | "
        f"{'SNR (1.91)':^11} | {'level dB re 10 mm':^17} | {'atten. alone':^11}"
    )
    print(
        f"{'mm':>5} |"
        + f" {'ref':>5} {'twin':>5} {'ratio':>5} |" * 2
        + f" {'ref':>5} {'twin':>5} |"
        + f" {'ref':>5} {'twin':>5} {'Δ dB':>5} |"
        + f" {'fc':>5} {'band':>5}"
    )
    for i, depth in enumerate(SPECKLE_DEPTHS_MM):
        cells = []
        for key in ("lateral_acf_fwhm_mm", "axial_acf_fwhm_mm"):
            r, t = _num(ref[key][i]), twin[key][i]
            cells.append(f" {r:5.3f} {t:5.3f} {tally.ratio(t, r):5.2f} |")
        cells.append(f" {_num(ref['snr'][i]):5.2f} {twin['snr'][i]:5.2f} |")
        r, t = _num(ref["level_db"][i]), twin["level_db"][i]
        d = tally.level(t, r) if i else t - r
        cells.append(f" {r:5.1f} {t:5.1f} {d:+5.1f} |")
        cells.append(
            f" {_num(ref['attenuation_fc_db'][i]):5.1f}"
            f" {_num(ref['attenuation_broadband_db'][i]):5.1f}"
        )
        print(f"{depth:5g} |" + "".join(cells))
    print(
        f"  SNR of the {len(SPECKLE_DEPTHS_MM)} windows pooled: ref {_num(ref['snr_pooled']):.2f}, "
        f"twin {twin['snr_pooled']:.2f} (one window holds ≈ 150 grains: ±7 % for one)"
    )
    # The twin's model: the gel's level at the elevation focus, the broadband two-way
    # loss, the resolution cell's gain against the focus's.
    depths_m = np.array(SPECKLE_DEPTHS_MM) * 1e-3
    nominal = (
        GEL.backscatter_db
        - band_attenuation_db(im, GEL, depths_m)
        + 10 * np.log10(speckle_cell_gain(im, depths_m))
        + 20 * np.log10(flat_echo_gain(im, depths_m))
    )
    print(
        "  twin absolute level dB (re a perfect reflector) at "
        + ", ".join(f"{d:g}" for d in SPECKLE_DEPTHS_MM)
        + " mm: nominal "
        + " ".join(f"{v:.1f}" for v in nominal)
        + f"; at the probe's {im.pixel_spacing_mm[0]:g} × {im.pixel_spacing_mm[1]:g} mm pixels "
        + " ".join(f"{v:.1f}" for v in twin["absolute_native_db"])
        + f"; at the measuring {TWIN_SPECKLE_PIXELS_MM[0]:g} × {TWIN_SPECKLE_PIXELS_MM[1]:g} mm "
        + " ".join(f"{v:.1f}" for v in twin["absolute_db"])
    )


def print_planes(case: Any, ref: dict[str, Any], twin: dict[str, Any], tally: Tally) -> None:
    print(
        f"\n{case.name} plane at {PLANE_DEPTH_MM:g} mm, tilted: echo level (mean of the "
        "line's peaks, dB re the same surface at 0°); twin off/on = surface_speckle"
    )
    print(
        f"{'angle':>5} | {'smooth: ref':>11} {'twin off':>8} {'Δ':>5} {'twin on':>8} {'Δ':>5} | "
        f"{'rough: ref':>10} {'twin off':>8} {'Δ':>5} {'twin on':>8} {'Δ':>5}"
    )
    for i, angle in enumerate(PLANE_ANGLES_DEG):
        cells = []
        for surface in ("smooth", "rough"):
            r = _num(ref[surface]["level_db"][i])
            cells.append(f" {r:{11 if surface == 'smooth' else 10}.1f}")
            for variant in (surface, surface + "_speckle"):
                t = twin[variant]["level_db"][i]
                d = tally.level(t, r) if i else t - r
                cells.append(f" {t:8.1f} {d:+5.1f}")
            cells.append(" |")
        print(f"{angle:5g} |" + "".join(cells).rstrip(" |"))
    r = _num(ref["rough_at_0_re_smooth_db"])
    off, on = twin["rough_at_0_re_smooth_db"], twin["rough_at_0_re_smooth_db_speckle"]
    print(
        f"  rough re smooth at 0°: ref {r:.1f} dB, "
        f"twin off {off:.1f} ({tally.level(off, r):+.1f}), "
        f"on {on:.1f} ({tally.level(on, r):+.1f})"
    )
    print("  granularity (std/mean of the peaks along the line):")
    print(
        f"{'angle':>5} | {'smooth: ref':>11} {'twin off':>8} {'twin on':>8} | "
        f"{'rough: ref':>10} {'twin off':>8} {'twin on':>8}"
    )
    for i, angle in enumerate(PLANE_ANGLES_DEG):
        s, ro = ref["smooth"]["granularity"][i], ref["rough"]["granularity"][i]
        print(
            f"{angle:5g} | {_num(s):11.3f} {twin['smooth']['granularity'][i]:8.3f} "
            f"{twin['smooth_speckle']['granularity'][i]:8.3f} | {_num(ro):10.3f} "
            f"{twin['rough']['granularity'][i]:8.3f} {twin['rough_speckle']['granularity'][i]:8.3f}"
        )


def print_flat(case: Any, ref: dict[str, Any], twin: dict[str, Any], tally: Tally) -> None:
    print(
        f"\n{case.name} flat reflector facing the probe (water, its loss taken off): echo "
        f"level dB re {FLAT_REFERENCE_MM:g} mm (the lateral aperture growing with depth, "
        "the elevation lens's wavefront flat across the plane only near its focus)"
    )
    print(f"{'depth mm':>8} | {'ref':>6} {'twin':>6} {'Δ dB':>6}")
    for i, depth in enumerate(FLAT_DEPTHS_MM):
        r, t = _num(ref["level_db"][i]), twin["level_db"][i]
        d = tally.level(t, r) if depth != FLAT_REFERENCE_MM else t - r
        print(f"{depth:8g} | {r:6.1f} {t:6.1f} {d:+6.1f}")


def print_cap_depth(case: Any, ref: dict[str, Any], twin: dict[str, Any], tally: Tally) -> None:
    print(
        f"\n{case.name} sphere's cap in the image plane (radius "
        f"{SPHERE_RADIUS_M * 1e3:g} mm, water, its loss taken off): echo level dB re a flat "
        f"reflector at {FLAT_REFERENCE_MM:g} mm, against the centre's depth"
    )
    print(f"{'depth mm':>8} | {'ref':>6} {'twin':>6} {'Δ dB':>6}")
    for i, depth in enumerate(CAP_DEPTHS_MM):
        r, t = _num(ref["level_db"][i]), twin["level_db"][i]
        print(f"{depth:8g} | {r:6.1f} {t:6.1f} {tally.level(t, r):+6.1f}")


def print_sphere(case: Any, ref: dict[str, Any], twin: dict[str, Any], tally: Tally) -> None:
    print(
        f"\n{case.name} sphere (radius {SPHERE_RADIUS_M * 1e3:g} mm, smooth steel in water) "
        "moved in elevation: the cap's peak (dB re offset 0) and its true depth (mm); "
        "twin off/on = surface_speckle"
    )
    for k in (f"{d:g}" for d in SPHERE_DEPTHS_MM):
        print(f"  centre at {k} mm (cap top at {float(k) - SPHERE_RADIUS_M * 1e3:g} mm)")
        cols = f"{'twin off':>8} {'Δ':>5} {'twin on':>8} {'Δ':>5}"
        print(f"{'offset':>6} | {'level: ref':>10} {cols} | {'depth: ref':>10} {cols}")
        for i, off in enumerate(SPHERE_OFFSETS_MM):
            r, rz = _num(ref[k]["level_db"][i]), _num(ref[k]["depth_mm"][i])
            cells = [f" {r:10.1f}"]
            for variant in (k, k + "_speckle"):
                t = twin[variant]["level_db"][i]
                d = tally.level(t, r) if off != 0.0 else t - r
                cells.append(f" {t:8.1f} {d:+5.1f}")
            # No depth for an echo below the display's floor (its peak is noise).
            shown = r > LEVEL_FLOOR_DB
            cells.append(f" | {rz:10.2f}" if shown else f" | {'—':>10}")
            for variant in (k, k + "_speckle"):
                tz = twin[variant]["depth_mm"][i]
                if twin[variant]["level_db"][i] <= LEVEL_FLOOR_DB:
                    cells.append(f" {'—':>8} {'':5}")
                else:
                    delta = f"{tz - rz:+5.2f}" if shown else ""
                    cells.append(f" {tz:8.2f} {delta:>5}")
            print(f"{off:6g} |" + "".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(
        description="sim_us's echoes against pymust (issue 35)",
        epilog="Details: the module docstring.",
    )
    parser.add_argument("--probe", choices=["paper", "linear75", "all"], default="all")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--write", action="store_true", help=f"store the reference in {STORED}")
    mode.add_argument("--stored", action="store_true", help="print from the stored reference")
    parser.add_argument(
        "--part",
        choices=sorted({p for ps in PARTS.values() for p in ps}),
        action="append",
        help="with --write: compute only these parts (repeatable), the others kept as stored",
    )
    args = parser.parse_args()
    if args.part and not args.write:
        parser.error("--part goes with --write")
    have_pymust = importlib.util.find_spec("pymust") is not None
    if args.write and not have_pymust:
        parser.error("--write needs pymust (pip install -e '.[reference]')")
    use_stored = args.stored or not have_pymust
    names = list(PROBES) if args.probe == "all" else [args.probe]
    t_start = time.perf_counter()
    stored = json.loads(STORED.read_text()) if use_stored else None
    records: dict[str, dict[str, Any]] = {}
    tally = Tally()
    for name in names:
        case = PROBES[name]()
        parts = PARTS[name]
        if stored is not None:
            rec = stored["probes"][name]
        elif args.part:
            # Only the parts asked for; the probe's other figures as stored.
            rec = json.loads(STORED.read_text())["probes"][name]
            fresh = reference_figures(case, tuple(p for p in parts if p in args.part))
            seconds = {**rec.get("seconds", {}), **fresh.pop("seconds")}
            rec.update(json.loads(json.dumps(_rounded(probe_record(case, fresh)))))
            rec["seconds"] = seconds
        else:
            rec = json.loads(
                json.dumps(_rounded(probe_record(case, reference_figures(case, parts))))
            )
        records[name] = rec
        twin = twin_figures(case, parts)
        print(f"  sim_us {name}: {twin['seconds']}", file=sys.stderr)
        a = case.array
        print(
            f"\n{name}: {case.description}. {a.f_mhz:g} MHz, {a.active_elements} active "
            f"elements at {a.pitch_mm:g} mm, {a.bandwidth_pct:g} % bandwidth, elevation "
            f"{a.elevation_aperture_mm:g} mm focused at {a.elevation_focus_mm:g} mm; "
            f"F# {rec['receive_fnumber']:.2f}. pymust seconds: {rec.get('seconds')}"
        )
        if "speckle" in parts:
            print_speckle(case, rec["speckle"], twin["speckle"], tally)
        if "planes" in parts:
            print_planes(case, rec["planes"], twin["planes"], tally)
        if "sphere" in parts:
            print_sphere(case, rec["sphere"], twin["sphere"], tally)
        if "flat" in parts:
            print_flat(case, rec["flat"], twin["flat"], tally)
        if "cap_depth" in parts:
            print_cap_depth(case, rec["cap_depth"], twin["cap_depth"], tally)
    if args.write:
        write_stored(records)
        print(f"\nwrote {STORED.relative_to(ROOT)}")
    if stored is None:
        source = f"computed with pymust {importlib.metadata.version('pymust')}"
    else:
        source = f"read from {STORED.relative_to(ROOT)} (pymust {stored['pymust_version']})"
    print(f"\nreference {source}; time {time.perf_counter() - t_start:.0f} s")
    lv = [abs(v) for v in tally.levels if np.isfinite(v)]
    finite = [max(q, 1 / q) for q in tally.ratios if np.isfinite(q) and q > 0]
    print(f"worst_db={max(lv):.1f}" if lv else "worst_db=nan")
    print(f"worst_ratio={max(finite):.2f}" if finite else "worst_ratio=nan")


if __name__ == "__main__":
    main()
