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
  in front of the lens focus (focal shift of a weakly focused aperture) and widens past it.

The figures are checked against pymust (MUST/SIMUS, itself validated against Field II) by
``benchmarks/physics_reference.py``: lateral and elevation FWHM within a few per cent of
the reference from 5 to 50 mm for two probes, the first side lobe within 1 dB.

The tables are computed once per distinct transducer (cached): about a second.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import CubicSpline
from scipy.signal import hilbert
from scipy.special import fresnel

from .probe import ProbeConfig

__all__ = [
    "DIRECTIVITY_AT_EDGE",
    "BeamTables",
    "Transducer",
    "axial_fwhm_m",
    "beam_tables",
    "receive_fnumber",
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

    @property
    def wavelength_m(self) -> float:
        return self.speed_m_s / self.f_hz


def transducer(probe: ProbeConfig) -> Transducer:
    """The transducer of ``probe`` (its beam-relevant fields)."""
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
    )


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
    env = np.abs(hilbert(echo))
    return _fwhm(np.arange(n) / fs, env) * t.speed_m_s / 2.0


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
    transmit and receive focused at ``(0, depth)``: broadband RMS of the square of the
    one-way field (module docstring)."""
    u = _aperture(t, depth_m)
    w = t.pitch_m - t.kerf_m
    freqs = np.linspace(t.f_hz * (1 - t.bandwidth), t.f_hz * (1 + t.bandwidth), _FREQUENCIES)
    power = (_excitation(t, freqs) ** 2) * _pulse_echo_response(t, freqs)  # one-way, squared
    dx = np.asarray(x, float)[:, None] - u[None, :]
    r = np.sqrt(dx**2 + depth_m**2)
    r0 = np.sqrt(u**2 + depth_m**2)
    zz = np.asarray(z, float)[:, None]
    out = np.zeros(len(dx))
    for f, pw in zip(freqs, power, strict=True):
        k = 2.0 * np.pi * f / t.speed_m_s
        lam = t.speed_m_s / f
        directivity = depth_m / r * np.sinc(w * dx / r / lam)
        field = directivity * np.exp(1j * k * (r - r0)) / np.sqrt(r)
        field = field * _elevation_field(zz, r, k, t)
        out += pw * np.abs(field.sum(axis=1)) ** 2
    return out / np.max(out)


# ------------------------------------------------------------------ tables per depth


@dataclass(frozen=True)
class BeamTables:
    """The transducer's beam at depth nodes, for the simulator to interpolate.

    ``lateral`` holds the two-way amplitude profile through the focus (peak 1) at
    ``lateral_x`` (m) for each node; ``lateral_fwhm`` and ``elevation_fwhm`` the FWHMs (m);
    ``side_lobe_db`` / ``side_lobe_x`` the first lateral side lobe (two-way level, dB; its
    offset, m), NaN where the broad band leaves none.
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

    def at(self, name: str, depth_m: Array | float) -> Array:
        """A per-node figure interpolated (linearly, held past the ends) at depths."""
        return np.interp(np.asarray(depth_m, float), self.depths, getattr(self, name))

    def lateral_profile(self, depth_m: Array | float, x: Array) -> Array:
        """Two-way lateral amplitude profiles (depths, len(x)) at offsets ``x`` (m): each
        node's profile interpolated along x by a cubic spline (linear interpolation would
        put kinks into its dB slope), then linearly in depth; 0 past the table's reach."""
        d = np.atleast_1d(np.asarray(depth_m, float))
        pos = np.clip(np.interp(d, self.depths, np.arange(len(self.depths))), 0, None)
        i0 = np.minimum(np.floor(pos).astype(int), len(self.depths) - 1)
        i1 = np.minimum(i0 + 1, len(self.depths) - 1)
        w = (pos - i0)[:, None]
        ax = np.abs(np.asarray(x, float))
        nodes = CubicSpline(self.lateral_x, self.lateral, axis=1, bc_type="clamped")(ax)
        nodes = np.where(ax[None, :] <= self.lateral_x[-1], np.clip(nodes, 0.0, None), 0.0)
        return (1.0 - w) * nodes[i0] + w * nodes[i1]


@functools.lru_cache(maxsize=16)
def beam_tables(t: Transducer, max_depth_m: float) -> BeamTables:
    """The beam of ``t`` from near the face to ``max_depth_m`` (cached per transducer and
    depth range)."""
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
    for i, d in enumerate(depths):
        lateral[i] = two_way_profile(t, float(d), x, np.zeros_like(x))
        xm, pm = np.concatenate([-x[:0:-1], x]), np.concatenate([lateral[i][:0:-1], lateral[i]])
        lat_fwhm[i] = _fwhm(xm, pm)
        sl_db[i], sl_x[i] = _first_side_lobe(x, lateral[i])
        reach = 0.75 * max(H, H * abs(d - F) / F) + 0.5e-3
        z = np.linspace(0.0, reach, _ELEVATION_SAMPLES)
        pe = two_way_profile(t, float(d), np.zeros_like(z), z)
        zm, pz = np.concatenate([-z[:0:-1], z]), np.concatenate([pe[:0:-1], pe])
        el_fwhm[i] = _fwhm(zm, pz, outer=True)
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
