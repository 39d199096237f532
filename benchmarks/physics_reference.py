"""sim_us's beam against an independent acoustic model: pymust (MUST/SIMUS), issue 35.

What it measures. For two linear probes, the paper's (``scenarios/paper.yaml``'s imaging
section, with the transducer the issue describes: 13 MHz, 64 active elements at 0.2 mm
pitch, 65 % bandwidth, 4 mm elevation aperture, 18 mm lens) and a 7.5 MHz, 38 mm linear
array with a 25 mm lens (``linear75``: 128 elements at 0.3 mm pitch, 64 of them active,
kerf 0.03 mm, 75 % bandwidth, 5 mm elevation aperture: a Verasonics L11-5v-like array
with a longer lens), at depths 5, 10, 15, 18, 22, 26, 30, 35, 40 and 50 mm:

- two-way lateral FWHM, axial FWHM, elevation FWHM (the slice thickness), and the first
  lateral side lobe (level, dB below the main lobe, and position, mm off the axis),
  computed with pymust, next to what ``sim_us`` draws for the same probe, with the ratios
  twin / reference (side-lobe levels: the difference twin − reference, dB);
- the point-target PSF as the display shows it at 10, 18 and 30 mm: one scatterer through
  ``simus`` (RF of the 64 elements, the focused transmit above), ``rf2iq`` and
  delay-and-sum with ``dasmtx`` (dynamic receive, the same f-number), its envelope |I/Q|;
  lateral and axial FWHM and the first side lobe, next to the field figures and sim_us.

- plane-wave imaging (``ProbeConfig.plane_waves_deg``): the point-target PSF of three
  plane waves at -8°, 0°, +8° from all active elements, coherently compounded (per wave
  ``simus``, ``rf2iq``, ``dasmtx`` at the f-number on a 0.01 mm pixel grid about the
  point; the I/Q summed), each column's brightest pixel (the compounding's tails are
  tilted copies of the echo at other depths), at 10, 18 and 30 mm: lateral FWHM and
  the levels at offsets out to 2 mm, next to sim_us's lateral kernel for the same
  imaging (``beam_of(probe).lateral_profile``).

How, reference side (pymust 0.1.9, ``pfield`` with ``param.height`` / ``param.focus``:
its multi-Gaussian elevation beam model, Fresnel in elevation, far field per sub-element
laterally, 3-D, soft baffle, the element directivity at the centre frequency):

- The scanner focuses its transmit at each depth and beamforms in receive with dynamic
  focus. Both use the same aperture, centred on the scanline: the elements within
  ``depth / (2 F#)`` of it, at most the 64 active ones. F# is the receive f-number MUST's
  ``dasmtx`` derives from the element directivity (Perrot et al. 2021, "So you think you
  can DAS?"): the angle where the element's response ``cos θ · sinc(w sin θ / λ_min)``
  falls to 0.71, F# = 1 / (2 tan θ) (2.31 for the paper probe, 2.08 for linear75;
  dasmtx's own bounded search lands on a wrong local minimum for 0.18 mm elements at
  13 MHz, so the first crossing is taken here). Elements further out see the point at
  angles where their directivity has fallen below -3 dB: a scanner leaves them out.
- Two-way = transmit × receive pressure. With the same aperture and focus this is the
  square of pfield's one-way RMS pressure (reciprocity); each profile is that square,
  normalised to its peak, and a FWHM is the width at half of it (linear interpolation
  between samples) through the focus: along x at y = 0 (lateral) and along y at x = 0
  (elevation). Near the face the elevation beam is a near-field pattern whose maximum
  lies off the axis (±0.9 mm at 5 mm for the paper probe, with a dip to 0.7-0.8 on it):
  its FWHM is the width between the outer half-maximum crossings.
- The first side lobe is the first local maximum of the lateral two-way profile past its
  first minimum, its level 20 log10 of the profile there. A broad band fills the nulls:
  where the profile falls without a minimum (linear75 from 15 mm on), the side lobe is
  the shoulder it leaves, the flattest point of the dB profile past the -20 dB point
  (marked "s" in the tables; stored as ``side_lobe_kind``).
- The axial FWHM is that of the envelope (Hilbert) of the two-way pulse, pymust's
  ``getpulse(param, 2)`` (a one-cycle excitation through the probe's pulse-echo
  response of the stated -6 dB bandwidth), times c / 2: the same at every depth.
- pfield sums the spectrum on a frequency grid and re-evaluates its elevation (MGBM)
  term every 20th frequency; at its default step the elevation FWHMs are off by up to
  8 % (at 10 mm). ``FrequencyStep = 0.1`` is converged to 0.5 % (0.05 gives the same).
- c = 1540 m/s (the medium a datasheet's lens focus is stated in), no attenuation.
- The issue's elevation figures for the paper probe (2.21, 1.13, 0.46, 0.53, 0.65, 0.82,
  1.08, 1.71, 2.86, 4.81 mm) were taken with all 64 elements at every depth. The paper
  table's last rows repeat that setting (converged frequency step): within 4 % of the
  issue's, the size of what pfield's frequency step moves them by (the issue's sampling
  is not stated). The F#-limited aperture thickens the slice near the face (2.31 instead
  of 2.21 mm at 5 mm, 1.23 instead of 1.18 at 10 mm): the elements far off the scanline
  see the point at long range, where their elevation beam is wide.
- The PSF: a scanline at x_l images a scatterer at 0 as the line at 0 images one at -x_l
  (the aperture moves with the line), so the lateral profile is the envelope on the line
  x = 0, at the depth of its peak, of scatterers placed across it, one simus each (81
  per half profile); the axial profile is the line through the scatterer on the axis.
  I/Q demodulation low-passes at fc (``rf2iq`` without a bandwidth), which keeps the
  whole echo band; a cut at the -6 dB band (rf2iq given ``param``) widens the axial
  FWHM by ≈ 15 %. fs = 4 fc. The PSF's lateral FWHM is the field's within 3 %.

How, twin side: ``sim_us`` as the simulator uses it. Lateral and axial FWHM and the side
lobe are measured on a rendered frame: a 0.02 mm wire along the elevation axis at each
depth, drawn as sim_us draws wires (a line target, ``sim_us.wires``: a point in the image
plane; a mesh cylinder that thin is a solid whose back wall, 0.02 mm below its front,
echoed through the PLA and widened the axial profile up to 1.57 × at 26-50 mm), in water
at 20 °C (sim_us's default medium) with the scanner set to water's speed, as the
reference's delays are to its medium's (at its own 1540 m/s the beam in water is out of
focus: lateral widths up to 1.41 × and side lobes 24 dB off at 22-30 mm),
``BmodeSimulator.envelope`` through
the probe's PSF kernels with its side lobes and ring-down, sampled at 0.01 mm pixels and
scanlines (the sampling, the pixel-scale error and the image offsets changed from the
probe's, nothing else). The elevation FWHM is ``sim_us.beam.slice_thickness``: the
elevation weights are Gaussians of exactly that two-way FWHM (sampled by the
sub-planes). The paper probe's image ends at 40 mm; its 50 mm row extends the same
formulas. ``linear75`` has no stated widths: the paper probe's are scaled as the physics
scales them (lateral with λ, axial with 1 / (f · bandwidth), the focal slice with
λ F / H), what a user without a datasheet figure would enter, and the paper probe's side
lobe (-40 dB) and ring-down (2 cycles); the rest of its settings are sim_us's defaults.

``--write`` stores the reference figures, the probe definitions and the pymust version
in ``benchmarks/reference/beam.json`` (tests read it without pymust); ``--stored`` prints
the tables from that file without pymust. Needs pymust (``pip install -e '.[reference]'``)
unless ``--stored``. Takes ≈ 45 s on a quiet host (pfield ≈ 2-5 s per depth and probe,
simus + DAS ≈ 2-5 s per PSF depth, the twin's renders ≈ 1 s in all), up to ≈ 4 min when
others load the two cores; ``--stored`` ≈ 3 s.

The second-to-last line is ``worst_level_db=<largest |Δ| of the side-lobe levels and of
the plane waves' main-lobe levels>`` (the plane waves' tails past -20 dB are printed, not
counted: the separable PSF draws them 0-7 dB above the reference's brightest pixel), the
last ``worst_ratio=<the ratio farthest from 1 over all rows and width/position columns,
the plane waves' FWHMs included, as max(r, 1/r)>``.

Run: python benchmarks/physics_reference.py [--probe paper|linear75|all] [--write | --stored]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import importlib.metadata  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from scipy.signal import hilbert  # noqa: E402

from bench.config.scenario import load_scenario  # noqa: E402
from bench.files import write_text_atomic  # noqa: E402
from calib.sound import water_speed_m_s  # noqa: E402
from sim_us import MediumConfig, ProbeConfig  # noqa: E402
from sim_us.beam import (  # noqa: E402
    SIDE_LOBE_OFFSET_PER_FWHM,
    axial_fwhm_m,
    beam_of,
    lateral_fwhm_m,
    slice_thickness,
)
from sim_us.raycast import AcousticScene  # noqa: E402
from sim_us.simulator import BmodeSimulator  # noqa: E402
from sim_us.wires import Wire  # noqa: E402

ROOT = Path(_HERE).parent
PAPER_SCENARIO = ROOT / "scenarios" / "paper.yaml"
STORED = Path(_HERE) / "reference" / "beam.json"
COMMAND = "python benchmarks/physics_reference.py --write"

DEPTHS_MM = (5.0, 10.0, 15.0, 18.0, 22.0, 26.0, 30.0, 35.0, 40.0, 50.0)
# The issue's pymust elevation FWHMs for the paper probe (64 elements at every depth).
ISSUE_ELEVATION_FWHM_MM = (2.21, 1.13, 0.46, 0.53, 0.65, 0.82, 1.08, 1.71, 2.86, 4.81)

SPEED_M_S = 1540.0
# pfield's frequency step (a scaling of its automatic one): converged to 0.5 % (above).
FREQUENCY_STEP = 0.1
# The element's directivity (amplitude) at the edge of the receive aperture.
DIRECTIVITY_AT_EDGE = 0.71
# Samples of each half profile (the profiles are symmetric about the scanline).
PROFILE_SAMPLES = 160

# Point-target PSFs (simus + DAS): depths, lateral positions per half profile.
PSF_DEPTHS_MM = (10.0, 18.0, 30.0)
PSF_POSITIONS = 81

# Plane-wave imaging (ProbeConfig.plane_waves_deg): the steering angles compounded, the
# offsets (mm) its lateral PSF is compared at, the pixel grid about the point (mm).
PLANE_WAVES_DEG = (-8.0, 0.0, 8.0)
PLANE_WAVE_OFFSETS_MM = (0.1, 0.15, 0.2, 0.3, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0)
PLANE_WAVE_HALF_WIDTH_MM = 2.5
PLANE_WAVE_HALF_DEPTH_MM = 1.0

# The twin's wire: radius, pixel and scanline spacing of the measuring render.
WIRE_RADIUS_M = 0.01e-3
FINE_MM = 0.01


@dataclass(frozen=True)
class ArraySpec:
    """A linear array as a datasheet gives it (what pymust needs), units in the names."""

    f_mhz: float
    elements: int  # on the face
    active_elements: int  # at most this many fire and receive for one scanline
    pitch_mm: float
    kerf_mm: float
    bandwidth_pct: float  # pulse-echo, -6 dB, fractional
    elevation_aperture_mm: float  # element height
    elevation_focus_mm: float  # lens focus
    speed_m_s: float = SPEED_M_S
    tx_cycles: float = 1.0  # cycles of the excitation (pymust's TXnow)


@dataclass(frozen=True)
class ProbeCase:
    """One probe: how sim_us is configured for it and the transducer pymust models."""

    name: str
    description: str
    imaging: ProbeConfig
    array: ArraySpec


def array_of(imaging: ProbeConfig) -> ArraySpec:
    """The transducer pymust models: exactly the datasheet figures sim_us is given."""
    return ArraySpec(
        f_mhz=imaging.f_mhz,
        elements=round(imaging.width_mm / imaging.pitch_mm),
        active_elements=imaging.active_elements,
        pitch_mm=imaging.pitch_mm,
        kerf_mm=imaging.kerf_mm,
        bandwidth_pct=imaging.bandwidth_pct,
        elevation_aperture_mm=imaging.elevation_aperture_mm,
        elevation_focus_mm=imaging.elevation_focus_mm,
        speed_m_s=imaging.assumed_speed_m_s,
        tx_cycles=imaging.pulse_cycles,
    )


def paper_probe() -> ProbeCase:
    """The paper probe exactly as ``scenarios/paper.yaml`` configures it."""
    imaging = load_scenario(PAPER_SCENARIO, check_reach=False).imaging
    return ProbeCase(
        "paper", "scenarios/paper.yaml's imaging (L8-18i-D)", imaging, array_of(imaging)
    )


def linear75_probe() -> ProbeCase:
    """A 7.5 MHz, 38 mm linear array with a 25 mm lens, as sim_us is given it."""
    imaging = replace(
        ProbeConfig(),
        width_mm=38.4,
        depth_mm=50.0,
        f_mhz=7.5,
        bandwidth_pct=75.0,
        pitch_mm=0.3,
        kerf_mm=0.03,
        active_elements=64,
        elevation_aperture_mm=5.0,
        elevation_focus_mm=25.0,
    )
    return ProbeCase(
        "linear75", "7.5 MHz, 38 mm linear array, 25 mm lens", imaging, array_of(imaging)
    )


PROBES = {"paper": paper_probe, "linear75": linear75_probe}


# ------------------------------------------------------------------ profiles


def fwhm(x: NDArray[np.float64], p: NDArray[np.float64]) -> float:
    """Full width at half maximum of profile ``p`` sampled at ``x`` around its peak
    (linear interpolation of the two half-maximum crossings); NaN if one is missing."""
    p = np.asarray(p, float) / np.max(p)
    k = int(np.argmax(p))
    below = np.flatnonzero(p[k:] < 0.5)
    above = np.flatnonzero(p[: k + 1] < 0.5)
    if not len(below) or not len(above):
        return float("nan")
    j = k + int(below[0])  # first sample under half past the peak
    i = int(above[-1])  # last sample under half before it
    xr = x[j - 1] + (0.5 - p[j - 1]) * (x[j] - x[j - 1]) / (p[j] - p[j - 1])
    xl = x[i] + (0.5 - p[i]) * (x[i + 1] - x[i]) / (p[i + 1] - p[i])
    return float(xr - xl)


def first_side_lobe(x: NDArray[np.float64], p: NDArray[np.float64]) -> tuple[float, float, str]:
    """(level dB, offset, kind) of the first lateral side lobe of amplitude profile ``p``,
    on the side of increasing ``x`` from the peak: the first local maximum past the first
    minimum ("peak"); where the bandwidth has filled the null and the profile falls
    monotonically, the shoulder instead: the flattest point of its dB profile past the
    main lobe's -20 dB point ("shoulder"). NaNs and "none" if neither is found."""
    p = np.asarray(p, float) / np.max(p)
    k = int(np.argmax(p))
    q, xq = p[k:], x[k:] - x[k]
    d = np.diff(q)
    rising = np.flatnonzero(d > 0)
    if len(rising):
        m = int(rising[0])  # the first minimum
        falling = np.flatnonzero(d[m:] < 0)
        if len(falling):
            s = m + int(falling[0])
            return float(20.0 * np.log10(q[s])), float(xq[s]), "peak"
    db = 20.0 * np.log10(np.maximum(q, 1e-12))
    slope = np.gradient(db, xq)
    start = np.flatnonzero(db < -20.0)
    if len(start):
        i = int(start[0])
        flat = np.flatnonzero(
            (slope[i:-2] < slope[i + 1 : -1]) & (slope[i + 1 : -1] >= slope[i + 2 :])
        )
        if len(flat):
            s = i + 1 + int(flat[0])
            return float(db[s]), float(xq[s]), "shoulder"
    return float("nan"), float("nan"), "none"


def mirrored(x: NDArray[np.float64], p: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """A profile sampled on x ≥ 0 (x[0] = 0), made whole by its symmetry."""
    return np.concatenate([-x[:0:-1], x]), np.concatenate([p[:0:-1], p])


# ------------------------------------------------------------------ reference (pymust)


def receive_fnumber(a: ArraySpec) -> float:
    """MUST's directivity f-number: the first angle where the element's response
    cos θ · sinc(w sin θ / λ_min) falls to 0.71 (λ_min at the band's upper edge)."""
    lam_min = a.speed_m_s / (a.f_mhz * 1e6 * (1 + a.bandwidth_pct / 200))
    w = (a.pitch_mm - a.kerf_mm) * 1e-3
    th = np.linspace(0.0, np.pi / 2, 200001)
    g = np.cos(th) * np.sinc(w / lam_min * np.sin(th))
    alpha = th[int(np.argmax(g < DIRECTIVITY_AT_EDGE))]
    return float(1.0 / (2.0 * np.tan(alpha)))


def aperture(a: ArraySpec, depth_m: float, fnumber: float | None) -> NDArray[np.float32]:
    """Apodization (active_elements,) of the aperture a scanline at x = 0 uses at
    ``depth_m``: the elements within depth / (2 F#) of it; all of them if F# is None."""
    xe = (np.arange(a.active_elements) - (a.active_elements - 1) / 2) * a.pitch_mm * 1e-3
    if fnumber is None:
        return np.ones(a.active_elements, np.float32)
    on = np.abs(xe) <= depth_m / (2.0 * fnumber) + 1e-12
    if on.sum() < 2:  # at least the two elements beside the line
        on = np.abs(xe) <= np.sort(np.abs(xe))[1] + 1e-12
    return on.astype(np.float32)


def pymust_depth(y: NDArray[np.float64], z: NDArray[np.float64]) -> NDArray[np.float64]:
    """The depth (m) to hand pymust for scatterers at elevation ``y`` and depth ``z``.

    pymust 0.1.9's ``pfield`` counts a scatterer's elevation offset twice: its distance
    to each element is the 3-D one, ``r = √(d² + y²)`` (``d`` the in-plane distance), and
    its multi-Gaussian elevation beam adds the paraxial path ``y² / 2r`` again (its
    ``gamma`` term), which already holds it. A point beside the image plane is drawn late
    by ``y² / 2d`` each way: 2 mm off at 20 mm, 0.10 mm too deep (pymust 0.19 mm, the
    paraxial aperture integral 0.09 mm: a rectangular element with its lens, checked by a
    direct sum over the element's height, and pymust itself with ``r = d``). Handing it
    the depth ``√(z² − y²)`` makes its ``r`` the in-plane distance to every element
    exactly (``(x − u)² + z² − y² + y²``); the elevation is left to its beam model. The
    element's obliquity, taken in plane, moves by < 0.5 %."""
    return np.sqrt(np.maximum(np.asarray(z, float) ** 2 - np.asarray(y, float) ** 2, 0.0))


def pymust_param(a: ArraySpec, apod: NDArray[np.float32]) -> Any:
    """pymust's PARAM for the active aperture (elements centred on the scanline)."""
    from pymust import utils  # optional: only the reference needs pymust

    p = utils.Param()
    p.fc = a.f_mhz * 1e6
    p.pitch = a.pitch_mm * 1e-3
    p.kerf = a.kerf_mm * 1e-3
    p.Nelements = a.active_elements
    p.bandwidth = a.bandwidth_pct
    p.height = a.elevation_aperture_mm * 1e-3
    p.focus = a.elevation_focus_mm * 1e-3
    p.c = a.speed_m_s
    p.TXnow = a.tx_cycles
    p.TXapodization = apod.reshape(1, -1).copy()
    return p


def two_way_profiles(
    a: ArraySpec, depth_m: float, apod: NDArray[np.float32], lateral: bool = True
) -> dict[str, tuple[NDArray, NDArray]]:
    """Two-way amplitude profiles through the focus at ``depth_m``, transmit focused
    there with aperture ``apod`` and the same aperture in receive: {"lateral": (x, p),
    "elevation": (y, p)}, positions in mm, each whole (mirrored)."""
    import pymust  # optional: only the reference needs pymust
    from pymust import utils

    lam = a.speed_m_s / (a.f_mhz * 1e6)
    D = apod.sum() * a.pitch_mm * 1e-3
    # Laterally: out to ≈ 2.8 times the first side lobe (at 1.43 λ z / D).
    x = np.linspace(0.0, 4.0 * lam * depth_m / D, PROFILE_SAMPLES) if lateral else np.zeros(0)
    # In elevation: out past the geometric beam's half width.
    H, F = a.elevation_aperture_mm * 1e-3, a.elevation_focus_mm * 1e-3
    y = np.linspace(0.0, 0.75 * max(H, H * abs(depth_m - F) / F) + 0.5e-3, PROFILE_SAMPLES)
    px = np.concatenate([x, np.zeros_like(y)])
    py = np.concatenate([np.zeros_like(x), y])
    param = pymust_param(a, apod)
    delays = pymust.txdelay(0.0, depth_m, param)
    opt = utils.Options()
    opt.FrequencyStep = FREQUENCY_STEP
    rp, _, _ = pymust.pfield(px, py, np.full_like(px, depth_m), delays, param, options=opt)
    two_way = np.asarray(rp, float).ravel() ** 2  # transmit × receive (reciprocity)
    out = {"elevation": mirrored(y * 1e3, two_way[len(x) :])}
    if lateral:
        out["lateral"] = mirrored(x * 1e3, two_way[: len(x)])
    return out


def axial_fwhm_mm(a: ArraySpec) -> float:
    """FWHM (mm of depth) of the envelope of pymust's two-way pulse."""
    import pymust  # optional: only the reference needs pymust

    param = pymust_param(a, np.ones(a.active_elements, np.float32))
    pulse, t = pymust.getpulse(param, 2)
    env = np.abs(hilbert(pulse))
    return fwhm(t, env) * a.speed_m_s / 2.0 * 1e3


def point_target_psf(a: ArraySpec, depth_m: float, fnumber: float) -> dict[str, Any]:
    """The displayed PSF of one point scatterer at ``depth_m`` (module docstring): RF by
    ``simus``, I/Q by ``rf2iq``, delay-and-sum by ``dasmtx`` along the scanline, |I/Q|.

    A scanline at x_l images a scatterer at 0 as the scanline at 0 images one at -x_l
    (the aperture moves with the line): the lateral profile is the envelope on the line
    x = 0, at the depth of its peak, of scatterers placed across it, one simus each."""
    import pymust  # optional: only the reference needs pymust

    apod = aperture(a, depth_m, fnumber)
    param = pymust_param(a, np.ones(a.active_elements, np.float32))
    del param["TXapodization"]
    delays = np.asarray(pymust.txdelay(0.0, depth_m, param), float)
    del param["TXdelay"]
    delays[0, apod == 0] = np.nan  # elements off: no transmit, and dasmtx's sub-aperture
    delays[0] -= np.nanmin(delays)
    param.fs = 4 * param.fc
    param.fnumber = fnumber  # dasmtx's receive aperture: the same as the transmit one
    lam = a.speed_m_s / (a.f_mhz * 1e6)
    D = apod.sum() * a.pitch_mm * 1e-3
    offsets = np.linspace(0.0, 4.0 * lam * depth_m / D, PSF_POSITIONS)
    z = depth_m + np.arange(-0.6e-3, 0.6e-3 + 1e-9, lam / 40)
    x = np.zeros_like(z)
    envelopes = []
    das = None
    for xo in offsets:
        rf, _ = pymust.simus(
            np.array([[xo]]),
            np.array([[1e-8]]),  # y ≠ 0: the 3-D model with the elevation lens (at y = 0)
            np.array([[depth_m]]),
            np.array([[1.0]]),
            delays.copy(),
            param,
        )
        # Demodulation low-pass at fc (rf2iq without a bandwidth): it keeps the whole echo
        # band, so the envelope is the pulse's (a cut at the -6 dB band would widen it).
        iq = pymust.rf2iq(rf, param.fs, param.fc)
        if das is None or das.shape[1] != iq.size:
            param.TXdelay = delays.copy()
            das = pymust.dasmtx(1j * np.array(iq.shape), x, z, param)
        envelopes.append(np.abs(das @ iq.flatten(order="F")))
    env = np.array(envelopes)  # (offsets, depths)
    peak = int(np.argmax(env[0]))
    lx, lp = mirrored(offsets * 1e3, env[:, peak])
    level, offset, kind = first_side_lobe(lx, lp)
    return {
        "lateral_fwhm_mm": fwhm(lx, lp),
        "axial_fwhm_mm": fwhm(z * 1e3, env[0]),
        "side_lobe_db": level,
        "side_lobe_mm": offset,
        "side_lobe_kind": kind,
    }


def plane_wave_psf(a: ArraySpec, depth_m: float, fnumber: float) -> dict[str, Any]:
    """The displayed PSF of one point scatterer at ``(0, depth_m)`` imaged by coherently
    compounded plane waves (:data:`PLANE_WAVES_DEG`, every active element firing, no
    apodization), as ``ProbeConfig.plane_waves_deg`` asks sim_us for: per wave, ``simus``
    (pymust's own frequency grid), ``rf2iq``, ``dasmtx`` at the f-number (its hard-edged
    receive aperture) on a pixel grid about the point; the I/Q summed over the waves, its
    modulus. The lateral profile is each column's brightest pixel (the compounding's tails
    are tilted copies of the echo, at other depths than its peak: the display shows them
    beside the point all the same), its FWHM and its levels (dB) at
    :data:`PLANE_WAVE_OFFSETS_MM`."""
    import pymust  # optional: only the reference needs pymust
    from pymust import utils

    param = pymust_param(a, np.ones(a.active_elements, np.float32))
    del param["TXapodization"]
    param.fs = 4 * param.fc
    param.radius = np.inf
    x = np.arange(-PLANE_WAVE_HALF_WIDTH_MM, PLANE_WAVE_HALF_WIDTH_MM + 1e-9, 0.01) * 1e-3
    z = depth_m + np.arange(-PLANE_WAVE_HALF_DEPTH_MM, PLANE_WAVE_HALF_DEPTH_MM + 1e-9, 0.01) * 1e-3
    X, Z = np.meshgrid(x, z)
    opt = utils.Options()
    opt.WaitBar = False
    iq_sum = np.zeros(X.size, complex)
    for angle in PLANE_WAVES_DEG:
        p = param.copy()
        p.TXdelay = pymust.txdelay(p, np.radians(angle))
        rf, _ = pymust.simus(
            np.array([[0.0]]),
            np.array([[1e-8]]),  # y ≠ 0: the 3-D model with the elevation lens (at y = 0)
            np.array([[depth_m]]),
            np.array([[1.0]]),
            p.TXdelay,
            p,
            opt,
        )
        iq = pymust.rf2iq(rf, p.fs, p.fc)
        p.fnumber = fnumber
        iq_sum += pymust.dasmtx(iq, X, Z, p) @ iq.flatten(order="F")
    env = np.abs(iq_sum).reshape(X.shape, order="F")
    profile = env.max(axis=0) / env.max()
    xm = x * 1e3

    def level(o: float) -> float:  # both sides' mean amplitude, dB
        both = np.interp(o, xm, profile) + np.interp(-o, xm, profile)
        return float(20.0 * np.log10(both / 2.0))

    return {
        "lateral_fwhm_mm": fwhm(xm, profile),
        "levels_db": [level(o) for o in PLANE_WAVE_OFFSETS_MM],
    }


def reference_figures(case: ProbeCase, log: bool = True) -> dict[str, Any]:
    """The pymust figures of one probe at every depth (see the module docstring)."""
    a = case.array
    fnum = receive_fnumber(a)
    axial = axial_fwhm_mm(a)
    fig: dict[str, list[float]] = {
        k: []
        for k in (
            "aperture_elements",
            "lateral_fwhm_mm",
            "axial_fwhm_mm",
            "elevation_fwhm_mm",
            "side_lobe_db",
            "side_lobe_mm",
            "side_lobe_kind",
        )
    }
    full: list[float] = []
    for depth_mm in DEPTHS_MM:
        t0 = time.perf_counter()
        d = depth_mm * 1e-3
        apod = aperture(a, d, fnum)
        prof = two_way_profiles(a, d, apod)
        level, offset, kind = first_side_lobe(*prof["lateral"])
        fig["aperture_elements"].append(int(apod.sum()))
        fig["lateral_fwhm_mm"].append(fwhm(*prof["lateral"]))
        fig["axial_fwhm_mm"].append(axial)
        fig["elevation_fwhm_mm"].append(fwhm(*prof["elevation"]))
        fig["side_lobe_db"].append(level)
        fig["side_lobe_mm"].append(offset)
        fig["side_lobe_kind"].append(kind)
        if case.name == "paper":
            # The issue's setting: all 64 elements at every depth (elevation only).
            ful = two_way_profiles(a, d, aperture(a, d, None), lateral=False)
            full.append(fwhm(*ful["elevation"]))
        if log:
            print(
                f"  pymust {case.name} {depth_mm:g} mm: {time.perf_counter() - t0:.1f} s",
                file=sys.stderr,
            )
    psf: dict[str, list[Any]] = {}
    for depth_mm in PSF_DEPTHS_MM:
        t0 = time.perf_counter()
        for k, v in point_target_psf(a, depth_mm * 1e-3, fnum).items():
            psf.setdefault(k, []).append(_r(v))
        if log:
            print(
                f"  simus {case.name} {depth_mm:g} mm: {time.perf_counter() - t0:.1f} s",
                file=sys.stderr,
            )
    pw: dict[str, list[Any]] = {}
    for depth_mm in PSF_DEPTHS_MM:
        t0 = time.perf_counter()
        for k, v in plane_wave_psf(a, depth_mm * 1e-3, fnum).items():
            pw.setdefault(k, []).append([_r(x) for x in v] if isinstance(v, list) else _r(v))
        if log:
            print(
                f"  simus {case.name} plane waves {depth_mm:g} mm: "
                f"{time.perf_counter() - t0:.1f} s",
                file=sys.stderr,
            )
    out: dict[str, Any] = {
        "receive_fnumber": round(fnum, 4),
        "figures": {k: [_r(v) for v in vals] for k, vals in fig.items()},
        "psf": {"depths_mm": list(PSF_DEPTHS_MM), **psf},
        "plane_wave_psf": {
            "depths_mm": list(PSF_DEPTHS_MM),
            "steer_deg": list(PLANE_WAVES_DEG),
            "offsets_mm": list(PLANE_WAVE_OFFSETS_MM),
            **pw,
        },
    }
    if full:
        out["elevation_fwhm_full_aperture_mm"] = [_r(v) for v in full]
        out["issue_elevation_fwhm_mm"] = list(ISSUE_ELEVATION_FWHM_MM)
    return out


def _r(v: float | int | str) -> float | int | str | None:
    """A figure as stored: 4 decimals; None (JSON null) for a missing one."""
    if isinstance(v, int | str):
        return v
    return round(float(v), 4) if np.isfinite(v) else None


# ------------------------------------------------------------------ twin (sim_us)


def twin_figures(probe: ProbeConfig) -> dict[str, list[float]]:
    """What sim_us draws for ``probe`` at every depth: lateral/axial FWHM and the side
    lobe measured on a rendered wire, the elevation FWHM of its elevation weights."""
    widest = float(np.max(lateral_fwhm_m(probe, np.array(DEPTHS_MM) * 1e-3))) * 1e3
    half_width = (SIDE_LOBE_OFFSET_PER_FWHM + 4.0) * widest
    fig: dict[str, list[float]] = {
        k: []
        for k in (
            "lateral_fwhm_mm",
            "axial_fwhm_mm",
            "elevation_fwhm_mm",
            "side_lobe_db",
            "side_lobe_mm",
        )
    }
    for depth_mm in DEPTHS_MM:
        # A line target across the image plane (sim_us.wires): a point in the plane.
        y = depth_mm * 1e-3
        wire = Wire(
            "wire", np.array([0.0, y, -10e-3]), np.array([0.0, y, 10e-3]), 2 * WIRE_RADIUS_M
        )
        fine = replace(
            probe,
            width_mm=2.0 * round(half_width, 1),
            depth_mm=1.06 * depth_mm + 2.0 * axial_fwhm_m(probe) * 1e3 + 1.0,
            pixel_spacing_mm=(FINE_MM, FINE_MM),
            scanline_spacing_mm=FINE_MM,
            pixel_scale_error_pct=(0.0, 0.0),
            image_origin_offset_mm=0.0,
            lateral_offset_mm=0.0,
            # The reference's delays are for its medium's speed: the twin's scanner too.
            assumed_speed_m_s=water_speed_m_s(MediumConfig().temperature_c),
        )
        sim = BmodeSimulator(AcousticScene((), (wire,)), fine, MediumConfig())
        env = sim.envelope(np.eye(4)[None])[0].astype(float)
        r, c = np.unravel_index(int(np.argmax(env)), env.shape)
        pos = np.arange(env.shape[1]) * FINE_MM
        row = env[r]
        level, offset, _ = first_side_lobe(pos, row)
        fig["lateral_fwhm_mm"].append(fwhm(pos, row))
        fig["axial_fwhm_mm"].append(fwhm(np.arange(env.shape[0]) * FINE_MM, env[:, c]))
        fig["elevation_fwhm_mm"].append(float(slice_thickness(probe, depth_mm * 1e-3)) * 1e3)
        fig["side_lobe_db"].append(level)
        fig["side_lobe_mm"].append(offset)
    return fig


def twin_plane_wave_psf(probe: ProbeConfig) -> dict[str, list]:
    """sim_us's lateral PSF for ``probe`` imaging with :data:`PLANE_WAVES_DEG` (receive
    aperture unapodized, as dasmtx's): the lateral kernel the simulator blurs echoes with
    (``beam_of(probe).lateral_profile``) at each PSF depth, its FWHM and its levels at
    :data:`PLANE_WAVE_OFFSETS_MM`."""
    pw = replace(probe, plane_waves_deg=PLANE_WAVES_DEG, apodization="rect")
    tables = beam_of(pw)
    x = np.arange(-PLANE_WAVE_HALF_WIDTH_MM, PLANE_WAVE_HALF_WIDTH_MM + 1e-9, 0.005)
    out: dict[str, list] = {"lateral_fwhm_mm": [], "levels_db": []}
    for depth_mm in PSF_DEPTHS_MM:
        prof = tables.lateral_profile(depth_mm * 1e-3, x * 1e-3)[0]
        out["lateral_fwhm_mm"].append(fwhm(x, prof / prof.max()))
        levels = np.interp(PLANE_WAVE_OFFSETS_MM, x, prof / prof.max())
        out["levels_db"].append([float(v) for v in 20.0 * np.log10(np.maximum(levels, 1e-6))])
    return out


# ------------------------------------------------------------------ stored reference


def probe_record(case: ProbeCase, ref: dict[str, Any]) -> dict[str, Any]:
    """The stored definition and figures of one probe."""
    rec: dict[str, Any] = {
        "description": case.description,
        "array": asdict(case.array),
        "imaging": {
            k: getattr(case.imaging, k)
            for k in ("f_mhz", "elevation_aperture_mm", "elevation_focus_mm", "width_mm")
        },
    }
    if case.name == "paper":
        rec["source"] = "scenarios/paper.yaml"
    rec.update(ref)
    return rec


def write_stored(records: dict[str, dict[str, Any]]) -> None:
    data: dict[str, Any] = {
        "what": "pymust two-way beam figures (benchmarks/physics_reference.py's docstring)",
        "command": COMMAND,
        "pymust_version": importlib.metadata.version("pymust"),
        "depths_mm": list(DEPTHS_MM),
        "method": {
            "two_way": "square of pfield's one-way RMS pressure (same transmit and receive "
            "aperture, transmit focused at the depth), FWHM through the focus",
            "aperture": "elements within depth / (2 F#) of the scanline, at most "
            "active_elements; F# from the element directivity (0.71 at the edge)",
            "axial": "envelope FWHM of getpulse(param, 2) times c / 2",
            "psf": "one scatterer through simus, rf2iq (low-pass at fc), dasmtx along the "
            "scanline (the same f-number); FWHMs of |I/Q|",
            "frequency_step": FREQUENCY_STEP,
            "speed_m_s": SPEED_M_S,
        },
        "probes": records,
    }
    if STORED.exists():
        old = json.loads(STORED.read_text())
        old["probes"].update(records)
        data["probes"] = {k: old["probes"][k] for k in PROBES if k in old["probes"]}
    STORED.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(data, indent=1, ensure_ascii=False)
    # Lists of figures on one line each (they hold no brackets, braces or commas in strings).
    text = re.sub(
        r"\[\s*([^\[\]{}]*?)\s*\]",
        lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]",
        text,
    )
    write_text_atomic(STORED, text + "\n")


# ------------------------------------------------------------------ printing


def _stated(v: float | None) -> str:
    return "from the transducer" if v is None else f"stated {v:g} mm"


def _num(v: float | None) -> float:
    return float("nan") if v is None else float(v)


def _ratio(t: float, r: float) -> float:
    return t / r if np.isfinite(t) and np.isfinite(r) and r > 0 else float("nan")


def print_plane_waves(rec: dict[str, Any], twin: dict[str, list]) -> tuple[list, list]:
    """The plane-wave PSF table of one probe; returns (FWHM ratios, level differences at
    the offsets up to the first null, where the main lobe is)."""
    ref = rec["plane_wave_psf"]
    offsets = ref["offsets_mm"]
    steer = ", ".join(f"{v:g}" for v in ref["steer_deg"])
    print(
        f"  plane waves at {steer}° compounded (simus + dasmtx per wave, each column's "
        "brightest pixel) vs sim_us's lateral kernel; levels dB at offsets (mm):"
    )
    print(
        f"  {'depth':>5} | {'FWHM mm ref twin ratio':^22} | "
        + " ".join(f"{o:>5g}" for o in offsets)
    )
    ratios, levels = [], []
    for j, depth in enumerate(ref["depths_mm"]):
        r, t = _num(ref["lateral_fwhm_mm"][j]), twin["lateral_fwhm_mm"][j]
        q = _ratio(t, r)
        ratios.append(q)
        print(
            f"  {depth:5g} | {r:6.3f} {t:6.3f} {q:6.2f}    | ref  "
            + " ".join(f"{v:5.1f}" for v in ref["levels_db"][j])
        )
        print(f"  {'':5} | {'':22} | twin " + " ".join(f"{v:5.1f}" for v in twin["levels_db"][j]))
        # The main lobe: offsets out to where the reference first falls below -20 dB.
        main = np.flatnonzero(np.asarray(ref["levels_db"][j]) < -20.0)
        stop = int(main[0]) if len(main) else len(offsets)
        levels += [
            t_ - r_
            for r_, t_ in zip(ref["levels_db"][j][:stop], twin["levels_db"][j][:stop], strict=True)
        ]
        tails = [
            t_ - r_
            for r_, t_ in zip(ref["levels_db"][j][stop:], twin["levels_db"][j][stop:], strict=True)
        ]
        if tails:
            print(
                f"  {'':5} | {'':22} | past -20 dB: twin − ref "
                f"{min(tails):+.1f} to {max(tails):+.1f} dB"
            )
    return ratios, levels


def print_table(case: ProbeCase, rec: dict[str, Any], twin: dict[str, list[float]]) -> tuple:
    """Print one probe's table; returns (ratios, level differences)."""
    a, im = case.array, case.imaging
    ref = rec["figures"]
    print(
        f"\n{case.name}: {case.description}. Array: {a.f_mhz:g} MHz, {a.elements} elements "
        f"at {a.pitch_mm:g} mm pitch (kerf {a.kerf_mm:g} mm), {a.active_elements} active, "
        f"{a.bandwidth_pct:g} % bandwidth, elevation aperture {a.elevation_aperture_mm:g} mm, "
        f"lens focus {a.elevation_focus_mm:g} mm; transmit = receive aperture at "
        f"F# {rec['receive_fnumber']:.2f} (≤ {a.active_elements} elements), c {a.speed_m_s:g} m/s."
        f"\n  sim_us: lateral {_stated(im.lateral_fwhm_mm)}, axial "
        f"{_stated(im.axial_fwhm_mm)}, slice {_stated(im.slice_thickness_mm)}, side lobes "
        f"{im.side_lobe_db}, ring-down {im.ring_down_cycles:g} cycles."
    )
    head = (
        f"{'depth':>5} {'el':>3} | {'lateral FWHM mm':^19} | {'axial FWHM mm':^19} | "
        f"{'elevation FWHM mm':^19} | {'side lobe dB':^19} | {'side lobe at mm':^19}"
    )
    sub = f"{'mm':>5} {'':>3} |" + f" {'ref':>5} {'twin':>5} {'ratio':>5} |" * 3
    sub += f" {'ref':>5} {'twin':>5} {'Δ dB':>5} |" + f" {'ref':>5} {'twin':>5} {'ratio':>5}"
    print(head)
    print(sub)
    ratios: list[float] = []
    levels: list[float] = []
    for i, depth in enumerate(DEPTHS_MM):
        cells = []
        for key in ("lateral_fwhm_mm", "axial_fwhm_mm", "elevation_fwhm_mm"):
            r, t = _num(ref[key][i]), twin[key][i]
            q = _ratio(t, r)
            ratios.append(q)
            cells.append(f" {r:5.3f} {t:5.3f} {q:5.2f} |")
        shoulder = "s" if ref["side_lobe_kind"][i] == "shoulder" else " "
        r, t = _num(ref["side_lobe_db"][i]), twin["side_lobe_db"][i]
        levels.append(t - r)
        cells.append(f" {r:5.1f}{shoulder}{t:5.1f} {t - r:+5.1f} |")
        r, t = _num(ref["side_lobe_mm"][i]), twin["side_lobe_mm"][i]
        q = _ratio(t, r)
        ratios.append(q)
        cells.append(f" {r:5.3f} {t:5.3f} {q:5.2f}")
        ap = ref["aperture_elements"][i]
        print(f"{depth:5g} {ap:3d} |" + "".join(cells))
    print(
        "  (el = elements in the transmit/receive aperture; ratio = twin / reference; "
        "s = the reference's side lobe is a shoulder, the bandwidth filled its null)"
    )
    psf = rec["psf"]
    print(
        "  point-target PSF (simus + focused-transmit DAS, |I/Q|) vs the beam table's "
        "reference (field) and sim_us:"
    )
    print(
        f"  {'depth':>5} | {'lateral FWHM mm':^25} | {'axial FWHM mm':^25} | "
        f"{'side lobe dB / mm':^17}"
    )
    print(
        f"  {'mm':>5} |"
        + f" {'psf':>5} {'field':>5} {'twin':>5} {'ratio':>5} |" * 2
        + f" {'psf':>7} {'at':>5}"
    )
    for j, depth in enumerate(psf["depths_mm"]):
        i = DEPTHS_MM.index(depth)
        cells = []
        for key in ("lateral_fwhm_mm", "axial_fwhm_mm"):
            r, f, t = _num(psf[key][j]), _num(ref[key][i]), twin[key][i]
            q = _ratio(t, r)
            ratios.append(q)
            cells.append(f" {r:5.3f} {f:5.3f} {t:5.3f} {q:5.2f} |")
        shoulder = "s" if psf["side_lobe_kind"][j] == "shoulder" else " "
        level, at = _num(psf["side_lobe_db"][j]), _num(psf["side_lobe_mm"][j])
        cells.append(f" {level:6.1f}{shoulder} {at:5.3f}")
        print(f"  {depth:5g} |" + "".join(cells))
    if "elevation_fwhm_full_aperture_mm" in rec:
        full = rec["elevation_fwhm_full_aperture_mm"]
        issue = rec["issue_elevation_fwhm_mm"]
        print("  elevation FWHM with all 64 elements at every depth (the issue's setting):")
        print("    depth mm     " + " ".join(f"{d:5g}" for d in DEPTHS_MM))
        print("    pymust here  " + " ".join(f"{v:5.2f}" for v in full))
        print("    issue quotes " + " ".join(f"{v:5.2f}" for v in issue))
        print(
            "    here / issue "
            + " ".join(f"{f / q:5.2f}" for f, q in zip(full, issue, strict=True))
        )
    return ratios, levels


def main() -> None:
    parser = argparse.ArgumentParser(
        description="sim_us's beam against pymust (issue 35)",
        epilog="Details: the module docstring.",
    )
    parser.add_argument("--probe", choices=["paper", "linear75", "all"], default="all")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--write", action="store_true", help=f"store the reference in {STORED}")
    mode.add_argument("--stored", action="store_true", help="print from the stored reference")
    args = parser.parse_args()
    names = list(PROBES) if args.probe == "all" else [args.probe]
    t_start = time.perf_counter()
    stored = json.loads(STORED.read_text()) if args.stored else None
    records: dict[str, dict[str, Any]] = {}
    all_ratios: list[float] = []
    all_levels: list[float] = []
    for name in names:
        case = PROBES[name]()
        if stored is not None:
            rec = stored["probes"][name]
        else:
            rec = probe_record(case, reference_figures(case))
        records[name] = rec
        t0 = time.perf_counter()
        twin = twin_figures(case.imaging)
        print(f"  sim_us {name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        ratios, levels = print_table(case, rec, twin)
        all_ratios += ratios
        all_levels += levels
        if "plane_wave_psf" in rec:
            ratios, levels = print_plane_waves(rec, twin_plane_wave_psf(case.imaging))
            all_ratios += ratios
            all_levels += levels
    if args.write:
        write_stored(records)
        print(f"\nwrote {STORED.relative_to(ROOT)}")
    if stored is None:
        source = f"computed with pymust {importlib.metadata.version('pymust')}"
    else:
        source = f"read from {STORED.relative_to(ROOT)} (pymust {stored['pymust_version']})"
    print(f"\nreference {source}; time {time.perf_counter() - t_start:.0f} s")
    finite = [max(q, 1 / q) for q in all_ratios if np.isfinite(q) and q > 0]
    lv = [abs(v) for v in all_levels if np.isfinite(v)]
    print(f"worst_level_db={max(lv):.1f}" if lv else "worst_level_db=nan")
    print(f"worst_ratio={max(finite):.2f}" if finite else "worst_ratio=nan")


if __name__ == "__main__":
    main()
