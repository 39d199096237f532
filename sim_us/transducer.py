"""The beam a linear array forms, derived from what its datasheet gives.

A probe is described by its centre frequency, pulse-echo bandwidth, element pitch and
kerf, the number of elements that fire for one scanline, the transmit excitation, and the
elevation aperture (element height) with its lens focus. From these follow:

- **the pulse** (axial resolution): an excitation of ``pulse_cycles`` cycles of a sine at
  the centre frequency through the probe's pulse-echo response, a generalized normal
  window whose -6 dB width is the stated fractional bandwidth and which falls to 1/126
  (-42 dB) at 0 Hz (a transducer passes no DC); the axial FWHM is that of the pulse's
  envelope (Hilbert) times c / 2. This is the pulse model of SIMUS (Garcia, "SIMUS: an
  open-source simulator for medical ultrasound imaging", CMPB 2022), so the twin's pulse
  and the reference's are the same physics;
- **the lateral and elevation beams**: the scanner focuses its transmit at each depth and
  its receive dynamically, with the same aperture: the elements within
  ``depth / (2 F#)`` of the scanline, at most ``active_elements``. F# is the receive
  f-number at which the outermost element still sees the point at 0.71 of its on-axis
  response (directivity ``cos θ · sinc(w sin θ / λ)`` of an element of width ``w`` in a
  soft baffle, λ at the upper band edge; Perrot et al., "So you think you can DAS?",
  Ultrasonics 2021), unless the datasheet gives one. The one-way field at a point
  ``(x, y, z)`` of the focal plane (x lateral, y depth, z elevation) is the sum over the
  active elements of each element's far field laterally (directivity, ``1/√r``, the phase
  left after the focusing delays) times its elevation field: the Fresnel integral over the
  element's height of a lens focused at the elevation focus, in closed form (Fresnel
  integrals), ``1/√r`` again. Two-way is transmit × receive of the same aperture, i.e. the
  square of the one-way field; broadband, its RMS over the pulse's spectrum.
  The lateral profile through the focus keeps its side lobes; the elevation beam narrows
  in front of the lens focus (focal shift of a weakly focused aperture) and widens past it;
- **the elevation delay**: the aperture's paths to a point beside the image plane are
  longer than to the same depth in it (the Fresnel phase of the elevation field, the
  lens's delays taken off), so its echo arrives later and is drawn deeper: the two-way
  pulse's envelope peak at each elevation offset against the in-plane one, per depth node
  (:func:`elevation_delay`). Paper probe in water: 0.03 / 0.10 / 0.23 mm at 1 / 2 / 3 mm
  beside the plane at 20 mm, 0.05 / 0.14 / 0.26 mm at 35 mm; a direct sum over the
  element's height at exact distances agrees within 0.005 mm. A sphere's cap seen in a
  frame beside its centre is where this shows: drawn at its in-plane depth, the arc
  through the caps of a sweep tilts. A flat reflector gets its echo from the main lobe,
  where the delay is ≈ 0 (its b²-weighted mean ≤ 0.04 mm to 50 mm);
- **speckle against a flat reflector**: a medium's speckle sums the resolution cell's
  scatterers incoherently, a flat reflector sums the two-way field over its plane
  coherently (:func:`speckle_per_flat`). In focus their ratio goes as 1 / (lateral ×
  elevation width); away from the lens focus the plane meets a curved wavefront and the
  flat reflector loses more, so the medium's speckle relative to the surfaces is higher
  there (paper probe: 4.1 dB higher at 10 mm than at 20 mm, where the widths alone said
  3.5 dB lower; pymust 3.8 dB higher);
- **a flat reflector's echo against depth** (:func:`flat_echo`): the same coherent sum
  over the plane, relative to the elevation focus. The lateral aperture grows with depth
  (``depth / F#``, up to the active elements) and the lens's wavefront is flat across the
  plane only near its focus: a perfect reflector facing the probe echoes weaker in front
  of the focus and past it (paper probe, 1540 m/s: −11.9 dB at 10 mm, +0.6 dB at 20 mm,
  −4.1 dB at 40 mm re 18 mm; pymust's sheet: 12.0 dB between 10 and 20 mm). Every echo
  the simulator draws at a depth (surfaces, wires, the medium's speckle, whose level
  relative to the flat reflector :func:`speckle_per_flat` gives) carries it;
- **plane-wave imaging** (``ProbeConfig.plane_waves_deg``): a research scanner may instead
  fire a few plane waves steered at symmetric angles θ from all active elements and
  compound the beamformed frames coherently. Each transmit is unfocused; the beamformer
  expects its front's arrival, so at a point off the scanline the waves arrive out of step
  by ``x sin θ`` and their sum draws the compounding's tails beside an echo (at
  ``λ / sin θ`` for three waves, −25 to −30 dB): the two-way profile is the transmits'
  sum at each frequency times the receive field, each as a broadband RMS. The tails are
  tilted copies of the echo at other depths; the separable PSF draws their energy at
  the echo's depth (0 to 7 dB above the reference's brightest pixel there). The
  apertures can be Hann-weighted (``apodization``: each transmit across the active
  elements, the receive across its f-number width);
- **the medium's speed**: the scanner computes its delays and displays depth for the speed
  it assumes (``assumed_speed_m_s``, 1540 m/s); where sound travels at another (water:
  1482 m/s at 20 °C) each element's wave arrives as the true path at the true speed
  says, and the beam is out of focus. A pixel at displayed depth ``d`` shows the point at
  ``d · c_medium / c_scanner``; the phase left after the delays is ``k_medium · r −
  k_scanner · path`` (``path`` the length the scanner's delays assume). The element's
  directivity and the lens see the medium's wavelength; the lens focuses at its stated
  focus in any medium (as pymust's does), and the f-number stays the scanner's. In water
  the paper probe's focused beam at 20 mm falls to −16 dB 0.3 mm off the line (pymust
  −16 dB; −31 dB at the scanner's own speed): the skirts of the main lobe fill, the FWHM
  grows by up to 38 % (30 mm; the aperture's full 64 elements, where its quadratic
  phase error is largest). The simulator derives the beam for its medium's speed
  (:func:`transducer`, rounded to 5 m/s);
- **the echo of a mirror** (a smooth surface's specular reflection) against its tilt, in
  the image plane and in elevation: by the image method, the wave from each transmitting
  point of the aperture reaches each receiving point along the path through the mirror
  image, delayed as the focusing (laterally) or the lens (in elevation) does not expect;
  the received pulse is the sum of the pulses of every such pair (each element's
  directivity at both ends laterally, the obliquity in elevation, ``1/√r``), and the echo
  is its envelope's peak within the pulse's duration of the mirror's depth, relative to the
  untilted mirror's. A tilt θ moves the reflected beam by ``2 z tan θ`` across the
  aperture, so a mirror in focus returns the overlap of the aperture with itself shifted
  by that much (``1 − 2 F# tan θ`` of it laterally): the echo fades by 4 dB at 5° and
  17 dB at 10° for an F# 2.3 array, and past ``atan(1 / 2F#)`` only edge waves remain
  (pymust: 4.1, 17.0 dB). Plane waves: the same sum over the pairs of every transmit, each
  transmitting element delayed as its steering does. A surface rough on a scale larger
  than the wavelength (facets of rms slope s) returns its incoherent share over this lobe
  widened by the facets' tilts (Gaussian, s per axis): the geometrical-optics limit of
  the Kirchhoff model (Ogilvy, *Theory of Wave Scattering from Random Rough Surfaces*,
  1991, ch. 4).

The figures are checked against pymust (MUST/SIMUS, itself validated against Field II) by
``benchmarks/physics_reference.py``: lateral and elevation FWHM within a few per cent of
the reference from 5 to 50 mm for two probes, the first side lobe within 1 dB.

The tables are computed once per distinct transducer (cached): about a second.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray
from scipy import fft as sp_fft
from scipy.interpolate import CubicSpline
from scipy.special import fresnel

from .disk_cache import disk_cached
from .probe import ProbeConfig

__all__ = [
    "DIRECTIVITY_AT_EDGE",
    "MIRROR_SLOPES",
    "BandLoss",
    "BeamTables",
    "MirrorTables",
    "Transducer",
    "axial_fwhm_m",
    "band_loss",
    "beam_tables",
    "elevation_delay",
    "flat_echo",
    "mirror_response",
    "mirror_tables",
    "receive_fnumber",
    "slope_index",
    "speckle_per_flat",
    "table_at",
    "transducer",
    "two_way_profile",
]

Array = NDArray[np.float64]

# The element's response at the aperture's edge that sets the receive f-number.
DIRECTIVITY_AT_EDGE = 0.71
# The pulse-echo response at 0 Hz: 1/126 (-42 dB) of its peak (SIMUS's generalized
# normal window).
_RESPONSE_AT_DC = 126.0
# Frequencies summed for the broadband field: this many across ± one bandwidth about fc
# (the spectrum is below -30 dB past that; 17 give the FWHMs within 0.2 % of 31).
_FREQUENCIES = 17
# Lateral profiles: samples per λ F# out to this many λ F# (the side lobes and the
# tail past the second one, ≈ -45 dB).
_LATERAL_SAMPLES_PER_CELL = 12
_LATERAL_REACH_CELLS = 8.0
# Depth nodes of the tables: a tenth of the depth apart (the aperture grows by whole
# elements near the face, its beam changing fast), at least 0.5 mm, at most 2 mm.
_NODE_STEP = 0.1
_NODE_SPACING_M = (0.5e-3, 2e-3)
_FIRST_NODE_M = 1e-3
# Elevation profiles: this many samples out to the reach below.
_ELEVATION_SAMPLES = 161
# Elevation delays: the window searched reaches this many periods at fc past the paths.
_DELAY_PULSES = 8.0
# Speckle against a flat reflector: frequencies across ± one bandwidth (17 and 33 give
# the same ratios within 0.01 dB; the grid's period, ≈ 1 µs, is past twice the window);
# the focal plane sampled at this many points each way (301 and 801: within 0.01 dB),
# laterally out to this many λz/D (the two-way side lobes past it below -60 dB), in
# elevation past the defocused beam; the flat reflector's echo searched this long either
# side of its in-focus arrival.
_CELL_FREQUENCIES = 17
_CELL_SAMPLES = 301
_CELL_REACH_CELLS = 12.0
_CELL_WINDOW_S = 0.3e-6
# Mirror echo tables: tilts from 0 to a surface seen edge-on (a mirror's own lobe is
# edge waves below -60 dB past ≈ 30°; rough facets widen it) at this step; the elevation
# aperture sampled every half of the shortest wavelength of the band (no grating lobe of
# the sampling); pulses summed on a time grid of this many samples per period at fc; the
# echo's peak taken within this many pulse durations (the envelope's -40 dB span) of the
# mirror's depth.
_MIRROR_MAX_DEG = 90.0
_MIRROR_OWN_DEG = 45.0
_MIRROR_STEP_DEG = 1.0
_MIRROR_SAMPLES_PER_PERIOD = 16
_MIRROR_WINDOW = 1.0
# Facet slopes (rms, rad) of the rough-surface tables: the lobe widened by each.
MIRROR_SLOPES = (0.0, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28)


@dataclass(frozen=True)
class Transducer:
    """The datasheet figures the beam depends on (SI units; hashable, a cache key)."""

    f_hz: float
    bandwidth: float  # pulse-echo, -6 dB, fractional
    pulse_cycles: float
    pitch_m: float
    kerf_m: float
    active_elements: int
    f_number: float | None  # None: from the element directivity
    elevation_aperture_m: float
    elevation_focus_m: float
    speed_m_s: float
    # Plane-wave imaging: the steering angles (rad) compounded; () = focused transmits.
    plane_waves_rad: tuple[float, ...] = ()
    apodization: str = "rect"
    # The speed of sound in the medium imaged (m/s); None: the scanner's assumed speed
    # (``speed_m_s``, which its delays, its f-number and its displayed depths use).
    medium_speed_m_s: float | None = None

    @property
    def wavelength_m(self) -> float:
        return self.speed_m_s / self.f_hz

    @property
    def c_medium(self) -> float:
        """The speed the sound really travels at (m/s)."""
        return self.speed_m_s if self.medium_speed_m_s is None else self.medium_speed_m_s

    @property
    def true_per_displayed(self) -> float:
        """True over displayed depth: the medium's speed over the scanner's."""
        return self.c_medium / self.speed_m_s


# The medium's speed is rounded to this step (m/s) in the transducer's key: each distinct
# speed computes its own tables (a few seconds); 5 m/s moves the defocus of a 60 m/s
# mismatch by 8 % of itself.
_MEDIUM_SPEED_STEP = 5.0


def transducer(probe: ProbeConfig, medium_speed_m_s: float | None = None) -> Transducer:
    """The transducer of ``probe`` (its beam-relevant fields) imaging a medium where sound
    travels at ``medium_speed_m_s`` (None: at the speed the scanner assumes)."""
    if not probe.plane_waves_symmetric:
        raise ValueError(
            f"plane_waves_deg {list(probe.plane_waves_deg)}: the steering angles must be "
            "symmetric about 0 (the beam tables are)"
        )
    return Transducer(
        f_hz=probe.f_mhz * 1e6,
        bandwidth=probe.bandwidth_pct / 100.0,
        pulse_cycles=probe.pulse_cycles,
        pitch_m=probe.pitch_mm * 1e-3,
        kerf_m=probe.kerf_mm * 1e-3,
        active_elements=probe.active_elements,
        f_number=probe.f_number,
        elevation_aperture_m=probe.elevation_aperture_mm * 1e-3,
        elevation_focus_m=probe.elevation_focus_mm * 1e-3,
        speed_m_s=probe.assumed_speed_m_s,
        plane_waves_rad=tuple(float(np.radians(a)) for a in probe.plane_waves_deg),
        apodization=probe.apodization,
        medium_speed_m_s=_medium_speed(probe, medium_speed_m_s),
    )


def _medium_speed(probe: ProbeConfig, speed: float | None) -> float | None:
    """The medium's speed as the transducer's key holds it: rounded to
    :data:`_MEDIUM_SPEED_STEP`, None where it is the scanner's own."""
    if speed is None:
        return None
    rounded = float(np.round(speed / _MEDIUM_SPEED_STEP) * _MEDIUM_SPEED_STEP)
    return None if abs(rounded - probe.assumed_speed_m_s) < 1e-9 else rounded


# ------------------------------------------------------------------ the pulse


def _pulse_echo_response(t: Transducer, f: Array) -> Array:
    """The probe's pulse-echo amplitude response at frequencies ``f`` (Hz, either sign):
    a generalized normal window about fc, -6 dB at fc (1 ± B/2), 1/126 at 0 Hz."""
    half = t.bandwidth * t.f_hz / 2.0
    p = np.log(_RESPONSE_AT_DC) / np.log(t.f_hz / half)
    return np.exp(-np.log(2.0) * (np.abs(np.abs(f) - t.f_hz) / half) ** p)


def _excitation(t: Transducer, f: Array) -> Array:
    """Magnitude of the spectrum of ``pulse_cycles`` cycles of a sine at fc."""
    T = t.pulse_cycles / t.f_hz
    return np.abs(np.sinc(T * (f - t.f_hz)) - np.sinc(T * (f + t.f_hz))) * T / 2.0


def _analytic(x: Array) -> NDArray[np.complex128]:
    """The analytic signal of a real signal, the operations of ``scipy.signal.hilbert``
    (the same result bit for bit): written here because importing scipy.signal for it
    cost every rendering process ≈ 0.7 s, more than the tables it is used for."""
    n = len(x)
    X = sp_fft.fft(x)
    X[1 : (n + 1) // 2] *= 2.0  # the positive frequencies (not Nyquist's, for even n)
    X[n // 2 + 1 :] = 0.0  # the negative ones
    return sp_fft.ifft(X)


@functools.lru_cache(maxsize=64)
def axial_fwhm_m(t: Transducer) -> float:
    """Axial FWHM (m of depth) of the two-way pulse's envelope."""
    fs = 64.0 * t.f_hz
    n = 1 << 14
    f = np.fft.fftfreq(n, 1.0 / fs)
    time = np.arange(n) / fs
    burst = np.where(time < t.pulse_cycles / t.f_hz, np.sin(2 * np.pi * t.f_hz * time), 0.0)
    echo = np.real(np.fft.ifft(np.fft.fft(burst) * _pulse_echo_response(t, f)))
    echo = np.roll(echo, n // 2)  # the zero-phase response spreads both ways of t = 0
    env = np.abs(_analytic(echo))
    return _fwhm(np.arange(n) / fs, env) * t.speed_m_s / 2.0


@dataclass(frozen=True)
class BandLoss:
    """What a broadband echo loses to a power-law attenuation α(f) = α(fc) (f / fc)^n:
    ``loss_db`` against ``fc_db``, the two-way loss at the centre frequency (dB, rising),
    both for the echo's energy (its mean intensity: a speckle's, and for a spectrum near
    Gaussian also the envelope peak's). The high frequencies go first: the spectrum shifts
    down and the echo loses less than its centre frequency does (≈ 11 of 13 dB through
    2 cm of gel at 13 MHz, 65 %)."""

    fc_db: Array
    loss_db: Array

    def loss(self, fc_db: Array | float) -> Array:
        """The echo's loss (dB) for two-way losses at fc (dB)."""
        return np.interp(fc_db, self.fc_db, self.loss_db)

    def fc_for(self, loss_db: Array | float) -> Array:
        """The two-way loss at fc (dB) at which the echo has lost ``loss_db``."""
        return np.interp(loss_db, self.loss_db, self.fc_db)


@functools.lru_cache(maxsize=64)
def band_loss(t: Transducer, power: float) -> BandLoss:
    """The echo's loss against its centre frequency's for attenuation ∝ f^power, from the
    two-way echo spectrum (excitation × pulse-echo response)."""
    f = np.linspace(0.0, 3.0 * t.f_hz, 3001)[1:]
    energy = (_excitation(t, f) * _pulse_echo_response(t, f)) ** 2
    fc_db = np.concatenate([np.linspace(0.0, 20.0, 201), np.linspace(20.5, 600.0, 1160)])
    share = np.exp(-np.log(10.0) / 10.0 * fc_db[:, None] * (f[None, :] / t.f_hz) ** power)
    kept = (share * energy[None, :]).sum(axis=1) / energy.sum()
    return BandLoss(fc_db, -10.0 * np.log10(np.maximum(kept, 1e-300)))


# ------------------------------------------------------------------ the aperture
# ------------------------------------------------------------------ the aperture


@functools.lru_cache(maxsize=64)
def receive_fnumber(t: Transducer) -> float:
    """The f-number: stated, or where the element's directivity falls to 0.71."""
    if t.f_number is not None:
        return float(t.f_number)
    lam_min = t.speed_m_s / (t.f_hz * (1.0 + t.bandwidth / 2.0))
    w = t.pitch_m - t.kerf_m
    theta = np.linspace(0.0, np.pi / 2, 20001)
    g = np.cos(theta) * np.sinc(w / lam_min * np.sin(theta))
    alpha = theta[int(np.argmax(g < DIRECTIVITY_AT_EDGE))]
    return float(1.0 / (2.0 * np.tan(alpha)))


def _aperture(t: Transducer, depth_m: float) -> Array:
    """Lateral positions (m) of the elements that image a point at ``depth_m`` on the
    scanline: whole elements within depth / (2 F#) of it, at least the two beside it."""
    u = (np.arange(t.active_elements) - (t.active_elements - 1) / 2) * t.pitch_m
    on = np.abs(u) <= depth_m / (2.0 * receive_fnumber(t)) + 1e-12
    if on.sum() < 2:
        on = np.abs(u) <= np.sort(np.abs(u))[1] + 1e-12
    return u[on]


def _hann(t: Transducer, u: Array, half: float) -> Array:
    """The apodization of elements at ``u`` (m off the aperture's centre): 1, or a Hann
    window 1 at the centre and 0 at ± ``half``."""
    if t.apodization == "rect":
        return np.ones(len(u))
    return 0.5 + 0.5 * np.cos(np.pi * np.clip(np.abs(u) / half, 0.0, 1.0))


def _receive_weights(t: Transducer, depth_m: float, u: Array) -> Array:
    """The receive apodization of the elements at ``u`` (m off the scanline) for a point at
    ``depth_m``: across depth / (2 F#) (at least the elements' own extent)."""
    half = max(depth_m / (2.0 * receive_fnumber(t)), float(np.max(np.abs(u))) + t.pitch_m / 2)
    return _hann(t, u, half)


def _transmits(t: Transducer, depth_m: float) -> list[tuple[Array, Array, Array]]:
    """The transmits that image a point at ``depth_m`` on the scanline, each as (its
    elements' positions off the line (m), the path (m) the beamformer takes each
    element's wave to travel to that point, their apodization). Focused: one transmit
    from the receive aperture, weighted as it is, each path the element's distance to the
    point (the focusing delays cancel it there). Plane waves: one per steering angle θ,
    from all active elements (weighted across them), element ``u`` firing ``u sin θ / c``
    late; the beamformer expects the plane front's arrival, ``depth cos θ`` (the front
    through the array's centre at t = 0), so element ``u``'s wave is expected to travel
    ``depth cos θ − u sin θ``."""
    if not t.plane_waves_rad:
        u = _aperture(t, depth_m)
        return [(u, np.hypot(u, depth_m), _receive_weights(t, depth_m, u))]
    u = (np.arange(t.active_elements) - (t.active_elements - 1) / 2) * t.pitch_m
    w = _hann(t, u, t.active_elements * t.pitch_m / 2.0)
    return [(u, depth_m * np.cos(a) - u * np.sin(a), w) for a in t.plane_waves_rad]


def _elevation_field(z: Array, r: Array, k: float, t: Transducer) -> NDArray[np.complex128]:
    """One element's field in elevation at range ``r`` and elevation ``z`` (broadcast):
    ∫ exp(i k [(z − ζ)² / 2r − ζ² / 2F]) dζ over the height, / √r (Fresnel), closed form."""
    H, F = t.elevation_aperture_m, t.elevation_focus_m
    a = 0.5 * k * (1.0 / r - 1.0 / F)
    b = k * z / r
    # Where the quadratic phase across the height is below 1e-3 rad the lens cancels the
    # spreading: the integral is a sinc (and the closed form would divide by ≈ 0).
    flat = np.abs(a) * (H / 2.0) ** 2 < 1e-3
    a_ = np.where(flat, 1.0, a)
    g = np.sqrt(2.0 * np.abs(a_) / np.pi)
    s_lo, c_lo = fresnel((-H / 2.0 - b / (2.0 * a_)) * g)
    s_hi, c_hi = fresnel((H / 2.0 - b / (2.0 * a_)) * g)
    curved = (
        np.sqrt(np.pi / (2.0 * np.abs(a_)))
        * ((c_hi - c_lo) + 1j * np.sign(a_) * (s_hi - s_lo))
        * np.exp(-1j * b**2 / (4.0 * a_))
    )
    integral = np.where(flat, H * np.sinc(b * H / (2.0 * np.pi)), curved)
    return integral * np.exp(1j * k * z**2 / (2.0 * r)) / np.sqrt(r)


def two_way_profile(t: Transducer, depth_m: float, x: Array, z: Array) -> Array:
    """Two-way amplitude (peak 1) at points ``(x, depth, z)`` of the focal plane (m),
    imaged by the beamformer focused at ``(0, depth)``: the product of the transmit's and
    the receive's broadband RMS fields (module docstring). A focused scanner's transmit
    and receive are the same aperture: the square of its one-way field. Plane waves: the
    compounded transmits summed as waves at each frequency (their tails beside the line
    arrive out of step and partly cancel), then the RMS."""
    w = t.pitch_m - t.kerf_m
    freqs = np.linspace(t.f_hz * (1 - t.bandwidth), t.f_hz * (1 + t.bandwidth), _FREQUENCIES)
    power = (_excitation(t, freqs) ** 2) * _pulse_echo_response(t, freqs)  # one-way, squared
    xx, zz = np.asarray(x, float)[:, None], np.asarray(z, float)[:, None]
    u = _aperture(t, depth_m)
    weights = _receive_weights(t, depth_m, u)
    same = not t.plane_waves_rad  # the transmit is the receive aperture, weighted alike
    # The point the pixel at ``depth_m`` shows lies at the true depth (the echo's time at
    # the medium's speed); the delays are the scanner's, paths at its assumed speed.
    true_depth = depth_m * t.true_per_displayed

    def field(f: float, u: Array, path: Array, a: Array) -> NDArray[np.complex128]:
        k, k_scan = 2.0 * np.pi * f / t.c_medium, 2.0 * np.pi * f / t.speed_m_s
        dx = xx - u[None, :]
        r = np.sqrt(dx**2 + true_depth**2)
        directivity = true_depth / r * np.sinc(w * dx / r / (t.c_medium / f))
        one = a * directivity * np.exp(1j * (k * r - k_scan * path)) / np.sqrt(r)
        return (one * _elevation_field(zz, r, k, t)).sum(axis=1)

    rx = np.zeros(len(xx))
    tx = np.zeros(len(xx))
    transmits = _transmits(t, depth_m)
    for f, pw in zip(freqs, power, strict=True):
        received = field(f, u, np.sqrt(u**2 + depth_m**2), weights)
        rx += pw * np.abs(received) ** 2
        if not same:
            sent = sum(field(f, ut, path, wt) for ut, path, wt in transmits)
            tx += pw * np.abs(sent) ** 2
    out = rx if same else np.sqrt(rx * tx)
    return out / np.max(out)


def _lateral_field(
    t: Transducer, f: float, x: Array, depth_m: float, transmit: tuple[Array, Array, Array]
) -> NDArray[np.complex128]:
    """One transmit's (or the receive's) lateral field at frequency ``f`` at points ``x``
    (m) of the focal plane at displayed depth ``depth_m``, the elevation apart: each
    element's far field (directivity, ``1/√r``) with the phase its delays leave, summed
    over ``transmit`` = (the elements' offsets, the paths the beamformer assumes, their
    weights), as :func:`two_way_profile` sums it."""
    u, path, a = transmit
    true_depth = depth_m * t.true_per_displayed
    k, k_scan = 2.0 * np.pi * f / t.c_medium, 2.0 * np.pi * f / t.speed_m_s
    d = np.asarray(x, float)[:, None] - u[None, :]
    r = np.sqrt(d**2 + true_depth**2)
    directivity = true_depth / r * np.sinc((t.pitch_m - t.kerf_m) * d / r / (t.c_medium / f))
    return (a * directivity * np.exp(1j * (k * r - k_scan * path)) / np.sqrt(r)).sum(axis=1)


def _two_way_lateral(t: Transducer, f: float, x: Array, depth_m: float) -> NDArray[np.complex128]:
    """The two-way lateral field (transmit × receive, the elevation apart) at frequency
    ``f`` at points ``x`` (m) of the focal plane of the scanline focused at displayed depth
    ``depth_m``: a focused scanner's transmit is its receive aperture, plane waves the
    steered transmits summed as waves (:func:`_transmits`)."""
    u = _aperture(t, depth_m)
    receive = (u, np.hypot(u, depth_m), _receive_weights(t, depth_m, u))
    rx = _lateral_field(t, f, x, depth_m, receive)
    if not t.plane_waves_rad:
        return rx * rx
    return rx * sum(_lateral_field(t, f, x, depth_m, tr) for tr in _transmits(t, depth_m))


def _echo_spectrum(t: Transducer, freqs: Array) -> Array:
    """The echo pulse's amplitude spectrum: the excitation through the pulse-echo
    response."""
    return _excitation(t, freqs) * _pulse_echo_response(t, freqs)


def elevation_delay(t: Transducer, depth_m: float, z: Array) -> Array:
    """How much deeper (m of displayed depth) a point at elevation offsets ``z`` (m)
    beside the scanline's focus at displayed depth ``depth_m`` is drawn than the same
    point in the image plane: the shift of the two-way echo's envelope peak.

    The lens's paths to a point beside the plane are longer than to one in it (the
    Fresnel phase of :func:`_elevation_field`, the lens's delay taken off), so its echo
    arrives later: ``z² / 2r`` for a point seen by the aperture's centre alone, more past
    the lens focus (the aperture's edges see it farther off still), less at the focus.
    The echo's spectrum at ``z`` is the pulse's (the excitation through the pulse-echo
    response) times the two-way field on the scanline: the lateral aperture's sum at
    each frequency (transmit × receive, as :func:`two_way_profile`) times the square of
    the elevation field at the point's range (the lateral elements' own ranges, within
    2.5 % of it at the receive f-number, are not told apart here); its envelope's peak,
    found on a time grid a quarter period apart and refined by a parabola through the
    log-envelope, less the in-plane point's. A point 2 mm beside the plane at 20 mm
    (paper probe in water): 0.09 mm; pymust with its elevation counted once: 0.09 mm."""
    true_depth = depth_m * t.true_per_displayed
    zz = np.concatenate([[0.0], np.abs(np.asarray(z, float))])
    # The window searched: the longest path through the aperture's far edge and the lens,
    # both ways, beyond the in-plane one; a pulse duration either side.
    H = t.elevation_aperture_m
    far = np.hypot(true_depth, zz.max() + H / 2) - true_depth + H**2 / (8 * t.elevation_focus_m)
    reach = 2.0 * far / t.c_medium + _DELAY_PULSES / t.f_hz
    # Frequencies across ± one bandwidth about fc (the pulse's spectrum is below -100 dB
    # past it), so close that the grid's period (the echo repeats) is twice the window.
    n_freq = int(np.ceil(2.0 * t.bandwidth * t.f_hz * 4.0 * reach)) + 1
    freqs = np.linspace(t.f_hz * (1 - t.bandwidth), t.f_hz * (1 + t.bandwidth), max(n_freq, 33))
    pulse = _echo_spectrum(t, freqs)
    on_line = np.zeros(1)
    spectrum = np.empty((len(freqs), len(zz)), complex)
    for i, f in enumerate(freqs):
        lateral = _two_way_lateral(t, f, on_line, depth_m)[0]
        k = 2.0 * np.pi * f / t.c_medium
        spectrum[i] = pulse[i] * lateral * _elevation_field(zz, np.array(true_depth), k, t) ** 2
    # The echo at time τ after the in-plane arrival: Σ_f S(f) exp(−2πi f τ) (the fields'
    # phase exp(+ikr) is a delay).
    step = 0.25 / t.f_hz
    tau = np.arange(-reach, reach + step, step)
    env = np.abs(np.exp(-2j * np.pi * np.outer(tau, freqs)) @ spectrum)
    j = np.clip(np.argmax(env, axis=0), 1, len(tau) - 2)
    cols = np.arange(len(zz))
    lo, mid, hi = (np.log(np.maximum(env[j + o, cols], 1e-300)) for o in (-1, 0, 1))
    curve = lo - 2.0 * mid + hi
    frac = np.where(curve < 0, 0.5 * (lo - hi) / np.where(curve < 0, curve, -1.0), 0.0)
    # Displayed depth: the echo's time at the scanner's speed.
    peak = (tau[j] + np.clip(frac, -1.0, 1.0) * step) * t.speed_m_s / 2.0
    return peak[1:] - peak[0]


def speckle_per_flat(t: Transducer, depth_m: float) -> float:
    """A scattering medium's mean speckle intensity over the peak² of a flat reflector's
    echo, both at displayed depth ``depth_m`` on the scanline focused there (arbitrary
    but fixed units: only ratios between depths mean anything).

    The speckle sums the cell's scatterers incoherently, ``Σ_f |S(f)|² ∬ |P|² dx dz``
    (Parseval along the depth), where a flat reflector sums the field coherently over its
    plane, ``max_t |Σ_f S(f) ∬ P dx dz e^{−2πift}|`` (``S`` the echo pulse's spectrum,
    ``P`` the two-way field across the focal plane at x lateral, z elevation: the lateral
    aperture's as :func:`two_way_profile` sums it, times the square of the elevation
    field at the point's range). In focus the ratio goes as 1 / (lateral × elevation
    width); away from the lens focus the field's phase curves across the plane and the
    flat reflector's sum loses more than the speckle's: the paper probe's flat sheet at 10
    mm echoes 12 dB below one at 20 mm in pymust, the speckle relative to it is ≈ 4 dB
    higher at 10 than at 20 mm (pymust, attenuation apart: 3.8 dB)."""
    incoherent, flat = _cell_and_flat(t, depth_m)
    return incoherent / flat**2


def flat_echo(t: Transducer, depth_m: float) -> float:
    """The envelope peak of a perfect flat reflector's echo facing the probe at displayed
    depth ``depth_m``, on the scanline focused there (arbitrary but fixed units, those of
    :func:`speckle_per_flat`: only ratios between depths mean anything).

    The two-way field summed coherently over the reflector's plane: the lateral
    aperture's focused sum (which grows with the aperture, ``depth / F#`` up to the active
    elements) times the elevation lens's, whose wavefront is flat across the plane only
    near its focus. In front of the lens focus and past it the plane meets a curved
    wavefront and the sum loses: the paper probe's flat sheet (1540 m/s) echoes
    12.7 dB weaker at 10 mm than at 20 mm (pymust: 12.0 dB; ``benchmarks/
    reference_echoes.py``, the flat part)."""
    return _cell_and_flat(t, depth_m)[1]


def _cell_and_flat(t: Transducer, depth_m: float) -> tuple[float, float]:
    """The medium's speckle intensity (the cell's incoherent sum) and a flat reflector's
    echo peak (the plane's coherent sum) at displayed depth ``depth_m``
    (:func:`speckle_per_flat`, :func:`flat_echo`)."""
    freqs = np.linspace(t.f_hz * (1 - t.bandwidth), t.f_hz * (1 + t.bandwidth), _CELL_FREQUENCIES)
    pulse = _echo_spectrum(t, freqs)
    true_depth = depth_m * t.true_per_displayed
    lam = t.c_medium / t.f_hz
    span = len(_aperture(t, depth_m)) * t.pitch_m
    x_reach = _CELL_REACH_CELLS * lam * true_depth / span + 1e-3
    x = np.linspace(-x_reach, x_reach, _CELL_SAMPLES)
    H, F = t.elevation_aperture_m, t.elevation_focus_m
    z_reach = 1.5 * H * max(1.0, abs(true_depth - F) / F) + 2e-3
    z = np.linspace(-z_reach, z_reach, _CELL_SAMPLES)
    dx, dz = x[1] - x[0], z[1] - z[0]
    incoherent = 0.0
    coherent = np.empty(len(freqs), complex)
    for i, f in enumerate(freqs):
        lat = _two_way_lateral(t, f, x, depth_m)
        el = _elevation_field(z, np.array(true_depth), 2.0 * np.pi * f / t.c_medium, t) ** 2
        incoherent += pulse[i] ** 2 * np.sum(np.abs(lat) ** 2) * dx * np.sum(np.abs(el) ** 2) * dz
        coherent[i] = pulse[i] * np.sum(lat) * dx * np.sum(el) * dz
    # The flat reflector's echo about its in-focus arrival: its envelope's peak.
    tau = np.arange(-_CELL_WINDOW_S, _CELL_WINDOW_S, 0.05 / t.f_hz)
    peak = float(np.max(np.abs(np.exp(-2j * np.pi * np.outer(tau, freqs)) @ coherent)))
    return float(incoherent), peak


# ------------------------------------------------------------------ the mirror's echo


def _mirror_paths(p: Array, q: Array, depth_m: float, tilts: Array) -> tuple[Array, Array, Array]:
    """Paths (tilts, len(p), len(q)) from points ``p`` of the face (along one axis, m) to
    points ``q`` through a mirror through ``(0, depth_m)`` tilted by ``tilts`` (rad) about
    the other axis: the length (m), and the sines of the path's angle to the face's normal
    at ``p`` and at ``q`` (image method: the path to ``q`` is the straight line to its
    mirror image)."""
    a = tilts[:, None, None]
    nx, ny = np.sin(a), -np.cos(a)  # the mirror's normal, towards the probe at 0
    P, Q = p[None, :, None], q[None, None, :]

    def image(x: Array) -> tuple[Array, Array]:
        s = x * nx + (0.0 - depth_m) * ny  # (point - centre) . n, the point at depth 0
        return x - 2.0 * s * nx, -2.0 * s * ny

    qx, qy = image(Q)
    px, py = image(P)
    length = np.hypot(qx - P, qy)
    return length, (qx - P) / length, (px - Q) / np.hypot(px - Q, py)


def _spectra(delays: Array, weights: Array, fs: float, n: int) -> NDArray[np.complex128]:
    """Spectra (tilts, n) of impulse trains: ``weights`` at ``delays`` (s; tilts × pairs)
    on a grid of ``n`` samples at ``fs`` centred on 0, each impulse shared between its two
    nearest samples (linear fractional delay: rounding to one sample would leave a phase
    noise in the sum of the pairs that should cancel, ≈ -35 dB at 16 samples per period);
    pairs outside the grid are dropped (they arrive too far from the mirror's depth to be
    part of its echo)."""
    x = delays * fs + n // 2
    k = np.floor(x).astype(np.int64)
    frac = x - k
    rows = np.broadcast_to(np.arange(len(delays))[:, None], k.shape) * n
    h = np.zeros(len(delays) * n)
    for kk, ww in ((k, weights * (1.0 - frac)), (k + 1, weights * frac)):
        ok = (kk >= 0) & (kk < n)
        h += np.bincount((rows + kk)[ok], weights=ww[ok], minlength=len(delays) * n)
    return np.fft.fft(h.reshape(len(delays), n), axis=1)


def _mirror_spectra(
    t: Transducer, depth_m: float, tilts: Array, fs: float, n: int
) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Impulse-response spectra of a mirror at ``depth_m`` tilted in the image plane
    (lateral: the scanline's aperture focused at the depth, element directivity at fc) and
    in elevation (the lensed element height, obliquity)."""
    # The mirror lies at the true depth of the pixel at ``depth_m`` and the waves travel
    # at the medium's speed; the beamformer's delays are the scanner's (its speed).
    c, c_scan = t.c_medium, t.speed_m_s
    lam = c / t.f_hz
    true_depth = depth_m * t.true_per_displayed
    u = _aperture(t, depth_m)
    weights = _receive_weights(t, depth_m, u)
    w = t.pitch_m - t.kerf_m
    r0 = np.hypot(u, depth_m)

    def directivity(s: Array) -> Array:
        return np.sqrt(1.0 - s**2) * np.sinc(w * s / lam)

    # Every (transmitting, receiving) element pair of every transmit: their pulses add
    # in the beamformed sum (plane waves are compounded coherently).
    delays, amps = [], []
    for ut, path, wt in _transmits(t, depth_m):
        length, su, sv = _mirror_paths(ut, u, true_depth, tilts)
        expected = (path[None, :, None] + r0[None, None, :]) / c_scan
        delays.append((length / c - expected).reshape(len(tilts), -1))
        amp = directivity(su) * directivity(sv) * wt[None, :, None] * weights[None, None, :]
        amp = amp / np.sqrt(length)
        amps.append(amp.reshape(len(tilts), -1))
    lateral = _spectra(np.concatenate(delays, axis=1), np.concatenate(amps, axis=1), fs, n)
    H, F = t.elevation_aperture_m, t.elevation_focus_m
    lam_min = c / (t.f_hz * (1.0 + t.bandwidth / 2.0))
    m = max(int(np.ceil(H / (lam_min / 2.0))), 2)
    zeta = (np.arange(m) + 0.5) * H / m - H / 2.0
    # The lens focuses at F in any medium (as the reference's does): its delay a path.
    length, su, sv = _mirror_paths(zeta, zeta, true_depth, tilts)
    lens = np.hypot(zeta, F) - F  # the lens's delay (as a path) at each height
    delay = (length - 2.0 * true_depth - lens[None, :, None] - lens[None, None, :]) / c
    amp = np.sqrt(1.0 - su**2) * np.sqrt(1.0 - sv**2) / np.sqrt(length)
    elevation = _spectra(delay.reshape(len(tilts), -1), amp.reshape(len(tilts), -1), fs, n)
    return lateral, elevation


def _echo_pulse(t: Transducer, fs: float, n: int) -> NDArray[np.complex128]:
    """Spectrum of the two-way echo pulse (the excitation through the pulse-echo
    response) on the ``n``-sample grid at ``fs``, times 2 at positive frequencies and 0 at
    negative ones: its inverse transform is the analytic signal, whose modulus is the
    envelope."""
    f = np.fft.fftfreq(n, 1.0 / fs)
    time = np.arange(n) / fs
    burst = np.where(time < t.pulse_cycles / t.f_hz, np.sin(2 * np.pi * t.f_hz * time), 0.0)
    spectrum = np.fft.fft(burst) * _pulse_echo_response(t, f)
    return spectrum * np.where(f > 0, 2.0, np.where(f == 0, 1.0, 0.0))


def mirror_response(t: Transducer, depth_m: float, tilts: Array) -> tuple[Array, Array]:
    """Echo amplitude of a mirror at ``depth_m`` (the transmit focus) against its tilt
    (rad) in the image plane and in elevation, each relative to the untilted mirror's
    (module docstring): two arrays like ``tilts``."""
    fs = _MIRROR_SAMPLES_PER_PERIOD * t.f_hz
    n = 64 * _MIRROR_SAMPLES_PER_PERIOD  # ± 32 periods
    pulse = _echo_pulse(t, fs, n)
    tilts = np.asarray(tilts, float)
    lateral, elevation = _mirror_spectra(t, depth_m, tilts, fs, n)
    # The pulse's duration: where its envelope stays above -40 dB (it starts at sample 0).
    env = np.abs(np.fft.ifft(pulse))
    above = np.flatnonzero(env >= 1e-2 * env.max())
    start, stop = int(above[0]), int(above[-1])
    span = _MIRROR_WINDOW * (stop - start)
    # The impulse responses sit about sample n/2: the echo of an arrival at 0 spans
    # n/2 + [start, stop]; the window extends it by a pulse duration both ways.
    lo, hi = n // 2 + start - int(span), n // 2 + stop + int(span)

    def peak(spectra: NDArray[np.complex128]) -> Array:
        return np.abs(np.fft.ifft(spectra * pulse, axis=1))[:, lo : hi + 1].max(axis=1)

    # Each aperture's lobe with the other's mirror taken as perfect (an impulse): the
    # product of the two is the separable approximation, without the cross terms of the
    # two apertures' edge waves (which the reference's smooth elevation beam lacks too).
    lat, el = peak(lateral), peak(elevation)
    return _tidy(lat / lat[0]), _tidy(el / el[0])


def _tidy(lobe: Array) -> Array:
    """A lobe (on increasing tilts) at most 1, and falling for good once below -40 dB: past
    the main lobe a few of the sampled aperture's pairs land in the window by chance and
    leave spurious bumps (a continuous aperture leaves edge waves that fade with the
    tilt)."""
    lobe = np.minimum(lobe, 1.0)
    low = np.flatnonzero(lobe < 1e-2)
    if len(low):
        lobe[low[0] :] = np.minimum.accumulate(lobe[low[0] :])
    return lobe


def _widened(angles: Array, lobe: Array, slope: float) -> Array:
    """The amplitude lobe (on ``angles`` ≥ 0, symmetric) of a surface of Gaussian facets of
    rms slope ``slope`` (rad): each facet tilted by β returns the lobe at θ − β; intensities
    averaged over β."""
    if slope == 0.0:
        return lobe
    full = np.concatenate([-angles[:0:-1], angles])
    intensity = np.concatenate([lobe[:0:-1], lobe]) ** 2
    step = angles[1] - angles[0]
    beta = np.arange(-int(np.ceil(4 * slope / step)), int(np.ceil(4 * slope / step)) + 1) * step
    g = np.exp(-0.5 * (beta / slope) ** 2)
    widened = np.convolve(np.pad(intensity, len(beta)), g / g.sum(), mode="same")
    return np.sqrt(widened[len(beta) : len(beta) + len(full)][len(angles) - 1 :])


# ------------------------------------------------------------------ tables per depth


@dataclass(frozen=True)
class BeamTables:
    """The transducer's beam at depth nodes, for the simulator to interpolate.

    ``lateral`` holds the two-way amplitude profile through the focus (peak 1) at
    ``lateral_x`` (m) for each node; ``lateral_fwhm`` and ``elevation_fwhm`` the FWHMs (m);
    ``side_lobe_db`` / ``side_lobe_x`` the first lateral side lobe (two-way level, dB; its
    offset, m), NaN where the broad band leaves none. ``elevation`` holds the two-way
    elevation amplitude profile (peak 1 at each node) at ``elevation_z`` (m), and
    ``elevation_delay`` how much deeper (m of displayed depth) a point at those offsets is
    drawn than in the plane (:func:`elevation_delay`); ``speckle_per_flat`` a medium's
    speckle intensity over a flat reflector's peak² at each node
    (:func:`speckle_per_flat`); ``flat_echo`` a perfect flat reflector's echo facing the
    probe relative to one at the elevation focus (:func:`flat_echo`).
    """

    depths: Array
    lateral_x: Array
    lateral: Array
    lateral_fwhm: Array
    elevation_fwhm: Array
    side_lobe_db: Array
    side_lobe_x: Array
    axial_fwhm: float
    f_number: float
    elevation_z: Array
    elevation: Array
    elevation_delay: Array
    speckle_per_flat: Array
    flat_echo: Array

    def at(self, name: str, depth_m: Array | float) -> Array:
        """A per-node figure interpolated (linearly, held past the ends) at depths."""
        return np.interp(np.asarray(depth_m, float), self.depths, getattr(self, name))

    def elevation_at(self, depth_m: Array, z: Array) -> Array:
        """Two-way elevation amplitude at per-row offsets: ``depth_m`` (N,) m, ``z`` (N, m)
        m; linear in depth node and |z|, 0 past the table's reach (compiled)."""
        d = np.asarray(depth_m, float)
        i0, i1, wd = _node_weights(self.depths, d)
        z = np.asarray(z, float)
        step = float(self.elevation_z[1] - self.elevation_z[0])
        rows = np.ascontiguousarray(z.reshape(len(d), -1))
        out = _profile_rows(self.elevation[:, None, :], i0, i1, wd, rows, step)
        return out.reshape(z.shape)

    def delay_at(self, depth_m: Array, z: Array) -> Array:
        """How much deeper (m) points at displayed depths ``depth_m`` and elevation
        offsets ``z`` (m, arrays alike) are drawn than in the plane: linear in depth node
        and |z|, held past the table's reach (where the beam holds nothing)."""
        d = np.asarray(depth_m, float)
        i0, i1, wd = _node_weights(self.depths, d)
        step = float(self.elevation_z[1] - self.elevation_z[0])
        # Held at the last offset (just inside it: the compiled lookup is 0 past it).
        reach = (len(self.elevation_z) - 1 - 1e-9) * step
        z = np.minimum(np.abs(np.asarray(z, float)), reach).reshape(len(d), 1)
        return _profile_rows(self.elevation_delay[:, None, :], i0, i1, wd, z, step)[:, 0]

    def lateral_profile(self, depth_m: Array | float, x: Array) -> Array:
        """Two-way lateral amplitude profiles (depths, len(x)) at offsets ``x`` (m): each
        node's profile interpolated along x by a cubic spline (linear interpolation would
        put kinks into its dB slope), then linearly in depth; 0 past the table's reach."""
        d = np.atleast_1d(np.asarray(depth_m, float))
        i0, i1, w = _node_weights(self.depths, d)
        w = w[:, None]
        ax = np.abs(np.asarray(x, float))
        nodes = CubicSpline(self.lateral_x, self.lateral, axis=1, bc_type="clamped")(ax)
        nodes = np.where(ax[None, :] <= self.lateral_x[-1], np.clip(nodes, 0.0, None), 0.0)
        return (1.0 - w) * nodes[i0] + w * nodes[i1]

    def elevation_profile(self, depth_m: Array | float, z: Array) -> Array:
        """Two-way elevation amplitude (depths, len(z)) at elevation offsets ``z`` (m),
        linear in z and depth; 0 past the table's reach."""
        d = np.atleast_1d(np.asarray(depth_m, float))
        i0, i1, w = _node_weights(self.depths, d)
        w = w[:, None]
        az = np.abs(np.asarray(z, float))
        nodes = np.stack([np.interp(az, self.elevation_z, p, right=0.0) for p in self.elevation])
        return (1.0 - w) * nodes[i0] + w * nodes[i1]


def _node_weights(depths: Array, d: Array) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
    """The depth nodes either side of each depth ``d`` and the weight of the deeper one
    (held at the first and last node past the ends)."""
    pos = np.clip(np.interp(d, depths, np.arange(len(depths))), 0, None)
    i0 = np.minimum(np.floor(pos).astype(np.int64), len(depths) - 1)
    i1 = np.minimum(i0 + 1, len(depths) - 1)
    return i0, i1, pos - i0


@functools.lru_cache(maxsize=16)
@disk_cached(BeamTables)
def beam_tables(t: Transducer, max_depth_m: float) -> BeamTables:
    """The beam of ``t`` from near the face to ``max_depth_m`` (cached per transducer and
    depth range, in the process and on disk: :mod:`sim_us.disk_cache`)."""
    nodes = [_FIRST_NODE_M]
    while nodes[-1] < max_depth_m:
        nodes.append(nodes[-1] + float(np.clip(_NODE_STEP * nodes[-1], *_NODE_SPACING_M)))
    depths = np.array(nodes)
    n = len(depths)
    fn = receive_fnumber(t)
    lam = t.wavelength_m
    D_max = t.active_elements * t.pitch_m
    # One x grid for every node, fine enough for the narrowest beam (the F#-limited one)
    # and reaching past the widest one's side lobes.
    cell_min = lam * fn
    cell_max = lam * max(fn, max_depth_m / D_max)
    x = np.linspace(
        0.0,
        _LATERAL_REACH_CELLS * cell_max,
        int(_LATERAL_REACH_CELLS * cell_max / cell_min * _LATERAL_SAMPLES_PER_CELL) + 1,
    )
    H, F = t.elevation_aperture_m, t.elevation_focus_m
    lateral = np.empty((n, len(x)))
    lat_fwhm, el_fwhm, sl_db, sl_x = (np.empty(n) for _ in range(4))
    # The elevation profile on one grid reaching past the widest beam's (the face's, or
    # the deepest node's past the focus).
    reach = 0.75 * H * max(1.0, abs(depths[-1] - F) / F) + 0.5e-3
    ez = np.linspace(0.0, reach, _ELEVATION_SAMPLES)
    elevation = np.empty((n, len(ez)))
    delay = np.empty((n, len(ez)))
    cell, flat = np.empty(n), np.empty(n)
    for i, d in enumerate(depths):
        lateral[i] = two_way_profile(t, float(d), x, np.zeros_like(x))
        xm, pm = np.concatenate([-x[:0:-1], x]), np.concatenate([lateral[i][:0:-1], lateral[i]])
        lat_fwhm[i] = _fwhm(xm, pm)
        sl_db[i], sl_x[i] = _first_side_lobe(x, lateral[i])
        elevation[i] = two_way_profile(t, float(d), np.zeros_like(ez), ez)
        delay[i] = elevation_delay(t, float(d), ez)
        incoherent, flat[i] = _cell_and_flat(t, float(d))
        cell[i] = incoherent / flat[i] ** 2
        zm = np.concatenate([-ez[:0:-1], ez])
        el_fwhm[i] = _fwhm(zm, np.concatenate([elevation[i][:0:-1], elevation[i]]), outer=True)
    elevation /= elevation.max(axis=1, keepdims=True)
    # A flat reflector's echo relative to one at the elevation focus (as displayed), which
    # may lie past the tables' last node.
    flat /= flat_echo(t, F)
    return BeamTables(
        depths=depths,
        lateral_x=x,
        lateral=lateral,
        lateral_fwhm=lat_fwhm,
        elevation_fwhm=el_fwhm,
        side_lobe_db=sl_db,
        side_lobe_x=sl_x,
        axial_fwhm=axial_fwhm_m(t),
        f_number=fn,
        elevation_z=ez,
        elevation=elevation,
        elevation_delay=delay,
        speckle_per_flat=cell,
        flat_echo=flat,
    )


@dataclass(frozen=True)
class MirrorTables:
    """The echo of a surface element against its tilt, for the simulator to interpolate.

    ``lateral`` / ``elevation`` (depth nodes, slopes, tilts) hold the echo of a mirror
    tilted by ``tilts`` (rad) in the image plane / in elevation, relative to the untilted
    one (:func:`mirror_response`), for facets of rms slope :data:`MIRROR_SLOPES` (0: a
    smooth mirror).
    """

    depths: Array
    tilts: Array
    lateral: Array
    elevation: Array
    focal_spot_m: float = 0.0  # λ F#: the width a mirror must have to fill the focus
    wavelength_m: float = 0.0

    def lobes(
        self, depth_m: Array, tilt_lateral: Array, tilt_elevation: Array, slope: Array
    ) -> tuple[Array, Array, Array, Array]:
        """Echo of a surface element (per hit: its depth (m), its tilts in the image plane
        and in elevation (rad, either sign) and its facets' rms slope (rad)) relative to a
        mirror facing the probe, as its factors: the smooth mirror's lateral and elevation
        lobes, then the rough facets' (the echo is each pair's product)."""
        d = np.asarray(depth_m, float)
        i0, i1, wd = _node_weights(self.depths, d)
        sl = np.interp(np.asarray(slope, float), MIRROR_SLOPES, np.arange(len(MIRROR_SLOPES)))
        s0 = np.minimum(np.floor(sl).astype(np.int64), len(MIRROR_SLOPES) - 1)
        s1 = np.minimum(s0 + 1, len(MIRROR_SLOPES) - 1)
        ws = sl - s0
        zero = (0, 0, 0.0)
        rough = (s0, s1, ws)
        if not np.any(np.asarray(slope) > 0):  # smooth everywhere: the same lobes
            lat = self._lookup(self.lateral, (i0, i1, wd), tilt_lateral, zero)
            el = self._lookup(self.elevation, (i0, i1, wd), tilt_elevation, zero)
            return lat, el, lat, el
        return (
            self._lookup(self.lateral, (i0, i1, wd), tilt_lateral, zero),
            self._lookup(self.elevation, (i0, i1, wd), tilt_elevation, zero),
            self._lookup(self.lateral, (i0, i1, wd), tilt_lateral, rough),
            self._lookup(self.elevation, (i0, i1, wd), tilt_elevation, rough),
        )

    @property
    def tilt_step(self) -> float:
        """The tables' tilt step (rad)."""
        return float(self.tilts[1] - self.tilts[0])

    def depth_nodes(self, depth_m: Array) -> tuple[NDArray[np.int64], NDArray[np.int64], Array]:
        """The depth nodes either side of each depth (m) and the deeper one's weight."""
        return _node_weights(self.depths, np.asarray(depth_m, float))

    def elevation_lobe(self, depth_m: Array, tilt: Array) -> Array:
        """The smooth mirror's elevation lobe at ``tilt`` (rad, any shape, rows of
        ``depth_m``'s length) for depths ``depth_m`` (m, 1-D)."""
        d = np.asarray(depth_m, float)
        i0, i1, wd = _node_weights(self.depths, d)
        tilt = np.asarray(tilt, float)
        extra = (slice(None),) + (None,) * (tilt.ndim - 1)
        depth = (i0[extra], i1[extra], wd[extra])
        return self._lookup(self.elevation, depth, tilt, (0, 0, 0.0))

    def _lookup(self, table: Array, depth: tuple, tilt: Array, slopes: tuple) -> Array:
        """Bilinear in depth node and tilt, linear between two slope indices ``slopes``
        = (j0, j1, weight of j1); 0 past the table's last tilt (no echo). Compiled: a
        frame's rays make ≈ 10⁴ lookups of each table, several times."""
        i0, i1, wd = depth
        j0, j1, wj = slopes
        shape = np.broadcast_shapes(*(np.shape(v) for v in (i0, i1, wd, tilt, j0, j1, wj)))

        def flat(v: Array | float, dtype: type) -> Array:
            return np.ascontiguousarray(np.broadcast_to(v, shape), dtype=dtype).reshape(-1)

        out = _trilinear(
            table,
            flat(i0, np.int64),
            flat(i1, np.int64),
            flat(wd, np.float64),
            np.abs(flat(tilt, np.float64)) / self.tilt_step,
            flat(j0, np.int64),
            flat(j1, np.int64),
            flat(wj, np.float64),
        )
        return out.reshape(shape)


@numba.njit(cache=True, nogil=True, boundscheck=False, inline="always")
def table_at(table, i0, i1, wd, a, j0, j1, wj):  # pragma: no cover - compiled
    """``table[i, j, a]`` (nodes, slopes, tilts) at fractional tilt index ``a``, linear
    between nodes i0 and i1 (weight ``wd`` of i1), slopes j0 and j1 (weight ``wj`` of j1)
    and the tilts either side of ``a``; 0 at and past the table's last tilt."""
    last = table.shape[2] - 1
    if a >= last:
        return 0.0
    t0 = int(a)
    wa = a - t0
    acc = 0.0
    for i, wi in ((i0, 1.0 - wd), (i1, wd)):
        for j, wjj in ((j0, 1.0 - wj), (j1, wj)):
            w = wi * wjj
            if w != 0.0:
                acc += w * ((1.0 - wa) * table[i, j, t0] + wa * table[i, j, t0 + 1])
    return acc


@numba.njit(cache=True, nogil=True, boundscheck=False, inline="always")
def slope_index(slope):  # pragma: no cover - compiled
    """The two :data:`MIRROR_SLOPES` either side of a facet slope (rad) and the weight of
    the upper one (held at the ends), as ``np.interp`` on the slope grid gives them."""
    grid = MIRROR_SLOPES
    last = len(grid) - 1
    if not slope > grid[0]:
        return 0, 0, 0.0
    if slope >= grid[last]:
        return last, last, 0.0
    j = 0
    while grid[j + 1] <= slope:
        j += 1
    return j, j + 1, (slope - grid[j]) / (grid[j + 1] - grid[j])


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _trilinear(table, i0, i1, wd, a, j0, j1, wj):  # pragma: no cover - compiled
    """:func:`table_at` for arrays of lookups."""
    n = len(a)
    out = np.zeros(n)
    for k in range(n):
        out[k] = table_at(table, i0[k], i1[k], wd[k], a[k], j0[k], j1[k], wj[k])
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _profile_rows(table, i0, i1, wd, z, step):  # pragma: no cover - compiled
    """:func:`table_at` of a one-slope ``table`` at offsets ``|z[n, m]| / step`` of the
    rows' own depth nodes (``i0``, ``i1``, ``wd`` per row)."""
    N, M = z.shape
    out = np.zeros((N, M))
    for n in range(N):
        for m in range(M):
            out[n, m] = table_at(table, i0[n], i1[n], wd[n], np.abs(z[n, m]) / step, 0, 0, 0.0)
    return out


@functools.lru_cache(maxsize=16)
@disk_cached(MirrorTables)
def mirror_tables(t: Transducer, max_depth_m: float) -> MirrorTables:
    """The mirror echo of ``t`` at the depth nodes of its beam tables (cached in the
    process and on disk; ≈ 2 s to compute)."""
    depths = beam_tables(t, max_depth_m).depths
    tilts = np.radians(np.arange(0.0, _MIRROR_MAX_DEG + 1e-9, _MIRROR_STEP_DEG))
    lateral = np.empty((len(depths), len(MIRROR_SLOPES), len(tilts)))
    elevation = np.empty_like(lateral)
    # A mirror's own lobe is computed to 45° (past it, edge waves below -60 dB): zero on.
    own = tilts <= np.radians(_MIRROR_OWN_DEG) + 1e-9
    for i, d in enumerate(depths):
        lat, el = np.zeros(len(tilts)), np.zeros(len(tilts))
        lat[own], el[own] = mirror_response(t, float(d), tilts[own])
        for j, slope in enumerate(MIRROR_SLOPES):
            lateral[i, j] = _widened(tilts, lat, slope)
            elevation[i, j] = _widened(tilts, el, slope)
    return MirrorTables(
        depths=depths,
        tilts=tilts,
        lateral=lateral,
        elevation=elevation,
        focal_spot_m=t.wavelength_m * receive_fnumber(t),
        wavelength_m=t.wavelength_m,
    )


def _fwhm(x: Array, p: Array, outer: bool = False) -> float:
    """Width at half maximum of ``p`` (linear interpolation of the crossings): about the
    peak, or between the outermost crossings (``outer``: a near-field beam whose maximum
    lies off the axis)."""
    p = np.asarray(p, float) / np.max(p)
    above = np.flatnonzero(p >= 0.5)
    if outer:
        lo, hi = int(above[0]), int(above[-1])
    else:
        k = int(np.argmax(p))
        hi = k + int(np.argmax(p[k:] < 0.5)) - 1
        lo = k - int(np.argmax(p[: k + 1][::-1] < 0.5)) + 1
    if lo == 0 or hi == len(p) - 1:
        return float(x[hi] - x[lo])

    def cross(i: int, j: int) -> float:
        return float(x[i] + (0.5 - p[i]) / (p[j] - p[i]) * (x[j] - x[i]))

    return cross(hi, hi + 1) - cross(lo, lo - 1)


def _first_side_lobe(x: Array, p: Array) -> tuple[float, float]:
    """(level dB, offset m) of the first local maximum past the first minimum of a
    profile sampled on x ≥ 0; NaNs if it falls without one."""
    d = np.diff(p)
    rising = np.flatnonzero(d > 0)
    if not len(rising):
        return float("nan"), float("nan")
    falling = np.flatnonzero(d[rising[0] :] < 0)
    j = int(rising[0]) + (int(falling[0]) if len(falling) else len(d[rising[0] :]))
    return float(20.0 * np.log10(max(p[j], 1e-12))), float(x[j])
