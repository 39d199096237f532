"""The sphere localizer on frames sim_us did not draw: pymust-rendered elevational sweeps
of a 5 mm PLA sphere in water, localized next to sim_us's frames of the same scene.

What it checks. ``calib.localize.localize_sphere`` (methods "refined" and "paper") on three
sweeps rendered by an independent acoustic model (pymust 0.1.9: ``simus`` + ``rf2iq`` +
``dasmtx``), and on sim_us's frames of the same scene at the same poses: per sweep, the
error of the centre found (mm, in the sweep's reference frame) or the reason it was
rejected, the ratio of the errors pymust / sim_us and of their medians per method.

The scene, the same on both sides:

- A sphere of radius 5 mm, its centre fixed in the scene frame ("base"), PLA in water at
  20 °C (``MediumConfig()``: c = 1482.3 m/s from ``calib.sound``).
- Three sweeps of the protocol's shape, 21 frames 1 mm apart (± 10 mm) along each frame's
  own z (elevation), the sphere's centre in the middle frame at (x, depth, elevation)
  (0, 15, +0.3), (4, 20, −0.45) and (−6.5, 25, +0.15) mm: three depths about the 18 mm
  lens focus, the centre on, right of and left of the centre line, and between frames
  (what the elevation fit reads). Each sweep's probe has its own orientation in the
  scene (the sphere is symmetric; the poses are not trivial). ``T_ee_us`` is the
  identity and ``T_base_ee`` each frame's image-frame pose (``calib.image``'s frame:
  x lateral centred on the image, y depth from the face, z elevation); the truth is the
  centre in the middle frame. The three sweeps are localized together, as the pipeline
  does for one sphere (with ``T_ee_us`` known the refined method uses their consensus).
- The probe: physics_reference.py's paper probe (``paper_probe``, ``array_of``: 13 MHz,
  65 % bandwidth, 0.2 mm pitch, 0.02 mm kerf, 64 active of 190 elements, 4 mm elevation
  aperture, 18 mm lens, one-cycle excitation). sim_us gets ``ProbeConfig`` with exactly
  these datasheet figures, imaging as the reference does (``plane_waves_deg`` −8°, 0°,
  +8°, ``apodization`` "hann"; a focused scanner, sim_us's default, is reported beside
  it), and its defaults otherwise (38 × 40 mm frames at 0.1 mm pixels,
  the array's own beam and side lobes, 60 dB, surface speckle), rendered noise-free
  (``render(T, None)``) from ``trimesh.creation.icosphere`` (5 subdivisions), material
  PLA (without its diffuse share for the smooth sphere), no reverberation (pymust
  follows no wave twice).
- Two spheres (``SURFACES``): "smooth", a mirror; "diffuse", PLA as the scenarios print
  it, its ``Material.diffuse`` share (0.1 in amplitude) returned at every angle. In
  pymust the diffuse share is random scatterers uniform on the sphere (one per λ² on
  average, unit-variance Gaussian amplitudes, fixed by ``SEED`` + 1), those facing the
  probe in each sweep, scaled per sweep so that a sheet of them (the perfect reflector's
  extent and taper, same density) facing the probe returns a mean compounded intensity
  of (0.1 × PLA's reflection × the perfect reflector's)² at the mirror's peak depth over
  ± 5 mm of the sphere's column (two sheets averaged): the share's definition in sim_us;
  the mirror's lattice keeps √(1 − 0.1²). Both display depth at the
  scanner's 1540 m/s (3.9 % deep); the localizer gets ``axial_scale`` = 1482.3 / 1540 for
  both.

How, reference side (``--write``):

- Imaging: coherently compounded steered plane waves at −8°, 0°, +8° from the 64 active
  elements centred over the sphere (the 64-element block of the 190-element face nearest
  its column). Focused line-by-line imaging (a transmit per 0.2 mm line, each over the
  scatterers within ±1.5 mm) was estimated at ≈ 5 × the cost, past the budget. Transmit
  delays and beamforming use 1540 m/s (``pymust_param`` of the array as stated), the
  propagation the water's speed (the same array at 1482.3 m/s): the scanner's depth
  error is in the frames as in sim_us's. Transmit: Hann-weighted across the 64 elements
  (an unweighted plane wave's edge waves echo every scatterer again 0.3-1 mm deeper at
  -25 dB, a point at 15 mm: a band inside every surface; -42 dB and below weighted).
  Receive: ``dasmtx`` with physics_reference's ``receive_fnumber`` (2.31, from the element
  directivity) and a Hann apodization over that aperture, applied to the DAS matrix's
  entries (dasmtx's own aperture is hard-edged). I/Q by ``rf2iq`` (low-pass at fc), each
  transmit's referred to true time before the three are summed: rf2iq demodulates from
  the RF's first sample, which the receive delay puts at the transmit's own t0, and
  dasmtx rotates the phase by true time, so each transmit's sum carries exp(2πj fc t0);
  left in (as in the frames stored before), the steered waves added up to 170° out of
  step with the unsteered one, a point's PSF at 15 mm had side lobes of -3 dB 0.3 mm
  beside it. Envelope |Σ I/Q| over the three waves.
- Surface: the probe-facing cap of the CAD sphere, points of a Fibonacci lattice about
  0.4 λ apart (λ in water at fc; equal area per point), each of reflection coefficient
  PLA/water (0.30, sim_us's impedances) × its area / λ², so the level does not depend on
  the lattice. A λ/2 lattice draws grating echoes of the steep flanks ("fans" beside and
  below the cap: nearly as bright as the cap over the whole hemisphere, −44 dB below it
  with the cap cut at 45°); at 0.4 λ they are below −63 dB, as with a λ/4 lattice.
  Normals within 45° of the probe direction, tapered (raised cosine) from 20°: the
  aperture sees specular normals within ≈ ± 13° (± 18° of receive at 20 mm, ± 8° of
  steering), and a λ/4 lattice over the whole probe-facing hemisphere (0° wave, hard
  receive aperture) agreed with the cap alone within 0.7 dB above −20 dB re the peak,
  no echo of the flanks above −45 dB (the differences below: the weak dots down the
  cap's column and the line).
- Elevation: each frame gets the points within ± 3 mm of its own plane (the outer 0.5 mm
  tapered): the sphere moves through the elevation beam along the sweep. pymust counts
  a scatterer's elevation offset twice in its path (``physics_reference.pymust_depth``):
  each is handed to it at the depth that cancels the second count. Frames rendered
  without it drew the cap of a frame 2-4 mm beside the centre 0.1-0.3 mm too deep (a
  point 2 mm off at 20 mm: 0.19 mm late, 0.09 mm with it: the aperture's own paths). pymust's
  two-way elevation field 3 mm off the plane is −44 to −56 dB at 10-25 mm (pfield).
  Frames more than ≈ 6.5 mm off hold no surface within reach; the echo is below the
  60 dB display ≈ 3 mm off already: 7-9 frames at each end of a sweep are black.
- Smooth: the CAD sphere sim_us is given (``ROUGHNESS_RA_M`` = 0). With the paper
  scenario's printed roughness (Ra 10 µm, ℓ 0.4 mm, ``twin.printing.roughness_height``
  along the normal) the cap's specular point moves by ≈ R × slope (0.2 mm): the refined
  centres came 0.10-0.21 mm off (0.09-0.21 mm laterally) against 0.06-0.08 on sim_us's
  untextured sphere; sim_us draws printed roughness as speckle and a lobe, not as a
  moving specular point.
- pymust's frequency grid as in reference_echoes.py: ``FrequencyStep`` set so the grid's
  period is K / fc (K ≥ 260: pymust's elevation term re-evaluated at least every 1 MHz),
  a uniform receive delay −t0 bringing one sweep's echo window (all its frames, all
  elements, the pulse either side) into the first half-period, ``dasmtx`` told t0, the
  envelope × K (simus's RF scales as 1 / K: a point's envelope × K at K = 260, 400, 700
  agrees within 0.5 %). Element splitting pymust's default (3 per element); water's
  attenuation at fc (0.028 dB/cm/MHz, pymust's is linear in f).
- Pixels: each sweep's sphere is beamformed at the frame's own pixel centres
  (``calib.image.pixel_axes``, displayed depth) over ± 6 mm about its column, from 4 mm
  above its cap's top to 3 mm below its centre (true depths); the rest of the 401 × 381
  frame is 0, as sim_us's noise-free water. The pixel ↔ image mapping is exact.
- Display: 0 dB is a perfect reflector's echo at the elevation focus as displayed
  (18 mm), as sim_us's: the same compounded envelope of a smooth unit sheet (λ/2 square
  grid: no Bragg echo) there on the sphere's column, under the aperture (± 6.4 mm + the
  steered waves' shift + 1 mm, 1.5 mm tapered), ± 3 mm in elevation, without
  attenuation. Grey = (20 log10(envelope / 0 dB) + 60) · 255 / 60, rounded and clipped
  (sim_us's display at gain 0). The same sheet at each cap's depth (the diffuse share's
  calibration, below) echoes −7.4 / −1.2 / −0.2 dB re the focus at 10 / 15 / 20 mm
  (sim_us's flat reflector with this imaging: −7.1 / −1.3 / −0.3 dB). The frames stored
  before 2026-11-30 had the cap's depth as their 0 dB (sim_us's 0 dB was then the same
  at every depth); ``--write-zero-db`` showed them again with the focus's (each lit grey
  level moved by the ratio and rounded again), which moved the shallowest sweep's
  frames 7.4 dB down.

What remains of a plane-wave image's artefacts (the smooth sphere, frame nearest the
centre, dB below the cap's peak): the horizontal line a specular top throws across the
image (every pixel at its depth sums part of its echo) is gone beside the cap (≤ −42 dB
1.5-6 mm from its column; −23 to −37 dB with dasmtx's hard aperture): the Hann receive
removed it. The compounding's tails beside and below the cap (0.6-1.2 mm off its column,
0.3-1.5 mm under its top) are below the 60 dB display; what remains is a weak echo down
the cap's column 0.5-2.5 mm under its top (−31 to −38 dB). Before the I/Q phase and the
transmit weighting were fixed, the tails stood at −25 to −30 dB and a ladder of
edge-wave echoes ran under the cap.

What the frames show. The smooth sphere: the cap alone (≈ 2 mm wide, fading within ± 2 mm
of elevation) in both models; a smooth sphere's flanks send their echo away from the
aperture, and a score over the whole proximal shell sees little of a sphere in such
frames. The diffuse sphere: the cap and, ≈ 20 dB below it, the whole probe-facing
outline as granular speckle in every frame the sphere reaches.

Prints one row per sweep and method (error on pymust's frames "ref", on sim_us's
"twin" with speckle key 0, their ratio) with every rejection's reason, then the median
errors and their ratio per method. The diffuse sphere's speckle is a random draw on
either side: pymust's error is then taken over every stored realization of its
scatterers (each, and their median) and sim_us's over ``SPECKLE_REALIZATIONS`` (20) of
its speckle, imaging as the reference does and as a focused scanner (median, 10th-90th
percentile); pymust's median is taken over the first ``CRITERION_REALIZATIONS`` (5)
draws, the number fixed before they were made, and a last table gives the ratio over
those and over every stored draw with its 90 % bootstrap interval (either side
resampled). Before the tables, a point's PSF in water (pymust's, stored, beside
sim_us's lateral kernel for water's speed; focused scanner and plane waves). The last
line is ``worst_error_ratio=<largest ref / twin error over the sweeps and methods both
accepted; for the diffuse sphere pymust's median over sim_us's> wrong_centres=<centres
accepted from pymust's frames more than 1 mm off>``.

``--write [smooth|diffuse]`` renders a sphere with pymust (the smooth one ≈ 25 min, the
diffuse one ≈ 45 min on one core: ≈ 400 k scatterer-frames per sweep through three
waves, and the reference sheets; ≈ 90 min with two renders and other work on the 2
cores) and stores the frames (uint8), spacing, poses, ``T_ee_us``, true centres,
radius, axial scale, the probe, the method, the pymust version and the command in
``benchmarks/reference/sweeps.npz`` (smooth) or ``sweeps_diffuse.npz``
(``--realization K``: the diffuse scatterers' K-th draw, in ``sweeps_diffuse_rK.npz``);
then runs the check. ``--write-psf`` recomputes the PSF in water (≈ 1 min,
``water_psf.json``). Without them, the check reads those files (no pymust needed;
≈ 30 s).

Run: python benchmarks/reference_sweeps.py [--write [smooth|diffuse] [--realization K]]
[--write-psf]
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
import time  # noqa: E402
from dataclasses import asdict, dataclass, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from types import ModuleType  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from bench.files import replaced_atomically, write_text_atomic  # noqa: E402
from calib import se3  # noqa: E402
from calib.image import pixel_axes  # noqa: E402
from calib.localize import LocalizerConfig, SweepLocalization, localize_sphere  # noqa: E402
from calib.records import Sweep  # noqa: E402
from sim_us import MediumConfig, ProbeConfig  # noqa: E402
from sim_us.beam import beam_of  # noqa: E402
from sim_us.materials import MATERIALS, Material, amplitude_reflection, water  # noqa: E402
from sim_us.raycast import AcousticScene, ScenePart  # noqa: E402
from sim_us.simulator import BmodeSimulator  # noqa: E402
from twin.printing import roughness_height  # noqa: E402

ROOT = Path(_HERE).parent
STORED = Path(_HERE) / "reference" / "sweeps.npz"
COMMAND = "python benchmarks/reference_sweeps.py --write"


def command(surface: str, realization: int = 0) -> str:
    """The command that writes a surface's frames (a realization of its scatterers)."""
    if surface == "smooth":
        return COMMAND
    return f"{COMMAND} {surface}" + (f" --realization {realization}" if realization else "")


Array = NDArray[np.float64]


def _physics_reference() -> ModuleType:
    """benchmarks/physics_reference.py (not a package): the paper probe, pymust's PARAM
    and the receive f-number, one definition for every pymust reference."""
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

# ------------------------------------------------------------------ the scene

MM = 1e-3
RADIUS_M = 5e-3
MEDIUM = MediumConfig()  # water at 20 °C
WATER = water(MEDIUM.temperature_c)
WATER_C = WATER.speed_m_s
PLA = MATERIALS["pla"]
# The sphere's surface: PLA's normal-incidence pressure reflection coefficient in water.
PLA_REFLECTION = float(amplitude_reflection(WATER.impedance, PLA.impedance))
# The two spheres compared, each rendered by both models. "smooth": a mirror (the CAD
# sphere; sim_us given PLA without its diffuse share). "diffuse": PLA as the scenarios
# print it, its diffuse share (``Material.diffuse``, 0.1 in amplitude: what roughness finer
# than the wavelength returns at every angle) in pymust as random scatterers on the whole
# probe-facing hemisphere, scaled so that a facing sheet of them returns that share of a
# mirror's echo (mean intensity, at the mirror's peak depth).
SURFACES = ("smooth", "diffuse")
DIFFUSE_SHARE = PLA.diffuse
# Diffuse scatterers: uniformly random on the sphere, one per this many λ squared.
DIFFUSE_SPACING_WAVELENGTHS = 1.0
# The facing sheet's mean intensity, read over ± this about the sphere's column, from
# this many independent sheets.
DIFFUSE_CALIBRATION_HALF_WIDTH_M = 5e-3
DIFFUSE_CALIBRATION_SHEETS = 2


def sphere_material(surface: str) -> Material:
    """sim_us's material for the sphere: PLA, without its diffuse share if ``surface`` is
    "smooth"."""
    return PLA if surface == "diffuse" else replace(PLA, name="pla, smooth", diffuse=0.0)


def stored_path(surface: str, realization: int = 0) -> Path:
    """Where the frames of a surface (a realization of its diffuse scatterers) are kept."""
    if surface == "smooth":
        return STORED
    return STORED.with_name(
        f"sweeps_{surface}" + (f"_r{realization}" if realization else "") + ".npz"
    )


# The diffuse sphere's scatterers are one random draw: realizations 0, 1, … each a draw
# of their own (0: the first stored), rendered and stored apart.
def stored_realizations(surface: str) -> list[int]:
    """The realizations of a surface stored (the smooth sphere: [0] if stored)."""
    if surface == "smooth":
        return [0] if STORED.exists() else []
    return [k for k in range(MAX_REALIZATIONS) if stored_path(surface, k).exists()]


MAX_REALIZATIONS = 8


# Printed roughness along the normal (twin/printing.py's model): off, the CAD sphere
# sim_us is given. The paper scenario's figures (Ra 10 µm, ℓ 0.4 mm) move the cap's
# specular point by R × slope (module docstring).
ROUGHNESS_RA_M = 0.0
ROUGHNESS_LENGTH_M = 0.4e-3
SEED = 35
# Where the sphere sits in the scene ("base") frame: any fixed point.
CENTRE_BASE = np.array([0.30, 0.02, 0.05])
# The protocol's sweep: 21 frames 1 mm apart along the image's elevation axis.
FRAMES = 21
FRAME_STEP_M = 1e-3


@dataclass(frozen=True)
class SweepSpec:
    """Where the sphere's centre lies in a sweep's centre frame (the ``us`` frame of its
    middle frame: x lateral, y depth, z elevation, mm; depth true, not displayed) and the
    probe's orientation in the scene (xyz Euler angles, degrees)."""

    lateral_mm: float
    depth_mm: float
    elevation_mm: float
    rotation_deg: tuple[float, float, float]


SWEEPS = (
    SweepSpec(0.0, 15.0, 0.3, (0.0, 0.0, 0.0)),
    SweepSpec(4.0, 20.0, -0.45, (10.0, 35.0, -5.0)),
    SweepSpec(-6.5, 25.0, 0.15, (-20.0, 120.0, 15.0)),
)


IMAGING = ("plane waves", "focused")


def probe_config(imaging: str = "plane waves") -> ProbeConfig:
    """sim_us's probe: the paper probe's datasheet figures, no reverberation (pymust
    follows no wave twice: the cap's echo bounced off the probe face and back, at twice
    its depth, has no counterpart in the reference), everything else default; imaging
    as the reference does ("plane waves": :data:`STEER_DEG` compounded, the receive
    aperture Hann-weighted) or as a focused scanner does (sim_us's default)."""
    a = PR.paper_probe().array
    waves = {"plane_waves_deg": STEER_DEG, "apodization": "hann"}
    return ProbeConfig(
        **(waves if imaging == "plane waves" else {}),
        reverberation=False,
        f_mhz=a.f_mhz,
        bandwidth_pct=a.bandwidth_pct,
        pitch_mm=a.pitch_mm,
        kerf_mm=a.kerf_mm,
        active_elements=a.active_elements,
        elevation_aperture_mm=a.elevation_aperture_mm,
        elevation_focus_mm=a.elevation_focus_mm,
    )


def axial_scale(probe: ProbeConfig) -> float:
    """True over displayed depth: c_water / the scanner's assumed speed."""
    return WATER_C / probe.assumed_speed_m_s


def sweep_poses(spec: SweepSpec) -> Array:
    """(FRAMES, 4, 4): each frame's image (``us``) frame in the scene, the sweep moving
    along its own z through the sphere; the sphere's centre in the middle frame is
    ``spec``'s (x, y, z)."""
    R = se3.matrix_from_euler(np.radians(spec.rotation_deg))
    p_mid = np.array([spec.lateral_mm, spec.depth_mm, spec.elevation_mm]) * MM
    z = (np.arange(FRAMES) - FRAMES // 2) * FRAME_STEP_M
    return np.array([se3.make(R, CENTRE_BASE - R @ (p_mid - [0.0, 0.0, zk])) for zk in z])


def true_centre(T_base_us: Array) -> Array:
    """The sphere's centre (3,) in the sweep's reference frame (its middle frame)."""
    return se3.apply(se3.invert(T_base_us[FRAMES // 2]), CENTRE_BASE)


# ------------------------------------------------------------------ reference (pymust)

# Compounded steered plane waves (degrees), the 64 active elements centred over the sphere.
STEER_DEG = (-8.0, 0.0, 8.0)
# Surface points: a Fibonacci lattice at this many wavelengths (in water, at fc).
LATTICE_WAVELENGTHS = 0.4
# The cap: outward normals within CAP_DEG[1] of the probe direction, tapered (raised
# cosine) from CAP_DEG[0]; in elevation, within ELEVATION_REACH_M of the frame's plane,
# the outer ELEVATION_TAPER_M tapered.
CAP_DEG = (20.0, 45.0)
ELEVATION_REACH_M = 3e-3
ELEVATION_TAPER_M = 0.5e-3
# The beamformed crop about the sphere (the rest of the frame is black): ± this laterally
# about its centre, from this much above the cap's top to this much below the centre.
CROP_HALF_WIDTH_M = 6e-3
CROP_ABOVE_M = 4e-3
CROP_BELOW_M = 3e-3
# The perfect reflector (0 dB): a smooth unit sheet at the cap's depth, as wide as the
# array plus the steered waves' lateral shift at that depth plus this margin, ± the
# elevation reach; the outer SHEET_TAPER_M (lateral) and ELEVATION_TAPER_M tapered.
SHEET_MARGIN_M = 1e-3
SHEET_TAPER_M = 1.5e-3
# Receive: dasmtx's f-number aperture (physics_reference's directivity F#), Hann-apodized.
# pymust re-evaluates its elevation (MGBM) term every 20th frequency sample: the grid's
# period K / fc keeps K ≥ this (a re-evaluation at least every 1 MHz at 13 MHz).
MIN_PERIOD_CYCLES = 260


def _taper(u: Array) -> Array:
    """Raised cosine of ``u`` clipped to [0, 1]: 0 at 0, 1 at 1."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))


def wavelength_m(a: Any) -> float:
    """λ in water at the centre frequency."""
    return WATER_C / (a.f_mhz * 1e6)


def sphere_surface(a: Any) -> tuple[Array, Array]:
    """The sphere in the scene: points (n, 3) of a Fibonacci lattice on its surface about
    ``LATTICE_WAVELENGTHS`` λ apart (equal area per point), moved along the normal by
    the printed roughness (if ``ROUGHNESS_RA_M``), and their outward normals (n, 3)."""
    spacing = LATTICE_WAVELENGTHS * wavelength_m(a)
    n = int(np.ceil(4 * np.pi * RADIUS_M**2 / spacing**2))
    i = np.arange(n) + 0.5
    cos_t = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    sin_t = np.sqrt(1.0 - cos_t**2)
    normal = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    cad = CENTRE_BASE + RADIUS_M * normal
    if ROUGHNESS_RA_M <= 0:
        return cad, normal
    rng = np.random.default_rng(SEED)
    height = roughness_height(cad, ROUGHNESS_RA_M, ROUGHNESS_LENGTH_M, rng)
    return cad + height[:, None] * normal, normal


def cap_in_frame(points: Array, normals: Array, T_base_us: Array) -> tuple[Array, Array]:
    """The surface points a frame can see, in its ``us`` frame (n, 3), and their cap
    weight (n,): the outward normal within ``CAP_DEG[1]`` of the direction to the probe
    (−y), tapered; all elevations (the frame's slab is cut per frame)."""
    T_inv = se3.invert(T_base_us)
    p = se3.apply(T_inv, points)
    n = normals @ T_inv[:3, :3].T
    beta = np.degrees(np.arccos(np.clip(-n[:, 1], -1.0, 1.0)))
    w = _taper((CAP_DEG[1] - beta) / (CAP_DEG[1] - CAP_DEG[0]))
    keep = w > 0
    return p[keep], w[keep]


def elevation_slab(p: Array, w: Array) -> tuple[Array, Array]:
    """The points within ``ELEVATION_REACH_M`` of the image plane and their weights
    times the elevation taper."""
    we = w * _taper((ELEVATION_REACH_M - np.abs(p[:, 2])) / ELEVATION_TAPER_M)
    keep = we > 0
    return p[keep], we[keep]


@dataclass(frozen=True)
class Diffuse:
    """The sphere's diffuse scatterers: points (n, 3) uniformly random on its surface
    (scene frame), their outward normals (n, 3) and amplitudes (n,) of unit variance,
    one per ``area_m2``."""

    points: Array
    normals: Array
    amplitudes: Array
    area_m2: float


def diffuse_scatterers(a: Any, realization: int = 0) -> Diffuse:
    """Random scatterers on the sphere, ``DIFFUSE_SPACING_WAVELENGTHS`` λ apart on average
    (fixed by ``SEED`` and the realization: the same sphere in every frame and sweep)."""
    spacing = DIFFUSE_SPACING_WAVELENGTHS * wavelength_m(a)
    area = 4 * np.pi * RADIUS_M**2
    n = int(np.ceil(area / spacing**2))
    rng = np.random.default_rng(SEED + 1 if realization == 0 else (SEED + 1, realization))
    normal = rng.standard_normal((n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return Diffuse(CENTRE_BASE + RADIUS_M * normal, normal, rng.standard_normal(n), area / n)


def facing_in_frame(d: Diffuse, T_base_us: Array) -> tuple[Array, Array]:
    """The diffuse scatterers of the probe-facing hemisphere in a frame's ``us`` frame
    and their amplitudes (the rest lie in the sphere's shadow)."""
    T_inv = se3.invert(T_base_us)
    facing = (d.normals @ T_inv[:3, :3].T)[:, 1] < 0
    return se3.apply(T_inv, d.points[facing]), d.amplitudes[facing]


@dataclass
class Scanner:
    """The paper probe's 64 active elements centred at ``x_aperture`` (m, image x):
    pymust's PARAM for the water the sound travels in (``medium``) and for the scanner's
    assumed 1540 m/s (``scan``: transmit delays, beamforming, display)."""

    array: Any
    medium: Any
    scan: Any
    x_aperture: float
    fnumber: float
    pulse_s: float


def scanner(a: Any, x_centre: float) -> Scanner:
    """The active aperture nearest to ``x_centre`` (m): 64 of the 190 elements, its
    centre on the pitch grid, inside the face."""
    import pymust  # optional: only the reference needs pymust

    pitch = a.pitch_mm * MM
    half = (a.elements - a.active_elements) / 2
    x_ap = float(np.clip(np.round(x_centre / pitch), -half, half) * pitch)
    ones = np.ones(a.active_elements, np.float32)
    medium = PR.pymust_param(replace(a, speed_m_s=WATER_C), ones)
    scan = PR.pymust_param(a, ones)
    for p in (medium, scan):
        del p["TXapodization"]
        p.fs = 4 * p.fc
        p.radius = np.inf
    # The transmit Hann-weighted across the active elements (sim_us's apodization
    # "hann"): an unweighted plane wave's edge waves echo every scatterer again 0.3-1 mm
    # deeper at -25 dB (a point at 15 mm), a band under every surface no scanner shows.
    xe = (np.arange(a.active_elements) - (a.active_elements - 1) / 2) * pitch
    half = a.active_elements * pitch / 2
    medium.TXapodization = (0.5 + 0.5 * np.cos(np.pi * xe / half)).reshape(1, -1)
    # pymust's attenuation is linear in f: water's f² law matched at fc.
    f = a.f_mhz
    medium.attenuation = WATER.attenuation_db_cm_mhz * f ** (WATER.attenuation_power - 1)
    _, tp = pymust.getpulse(medium, 2)
    return Scanner(a, medium, scan, x_ap, PR.receive_fnumber(a), float(tp[-1]))


def _elements_x(s: Scanner) -> Array:
    a = s.array
    return (np.arange(a.active_elements) - (a.active_elements - 1) / 2) * a.pitch_mm * MM


def _pymust_xyz(p_us: Array, s: Scanner) -> tuple[Array, Array, Array]:
    """pymust's (x lateral from the aperture's centre, y elevation, z depth) of us-frame
    points (x lateral, y depth, z elevation)."""
    return p_us[:, 0] - s.x_aperture, p_us[:, 2], p_us[:, 1]


@dataclass
class Transmit:
    """One steered plane wave: its delays, the RF window (K, t0) all the echoes of a
    sweep fall in, and the DAS matrix of the crop's pixels for it."""

    delays: Array
    k: int
    t0: float
    das: Any


def transmit(
    s: Scanner,
    angle_deg: float,
    p_us: Array,
    x_px: Array,
    z_px: Array,
    delays: Array | None = None,
    hann: bool = True,
) -> Transmit:
    """The plane wave at ``angle_deg`` (or the transmit of ``delays`` (1, elements), NaN
    for an element off) for echoes of the points ``p_us`` (all a sweep's frames hold,
    their elevations up to the slab's reach), beamformed at pixels (``x_px``, ``z_px``:
    pymust's x, displayed depth); the receive aperture Hann-weighted (else dasmtx's
    own, hard-edged)."""
    import pymust  # optional: only the reference needs pymust

    if delays is None:
        delays = np.asarray(pymust.txdelay(s.scan, np.radians(angle_deg)), float).reshape(1, -1)
    x, _, z = _pymust_xyz(p_us, s)
    dx2 = (x[:, None] - _elements_x(s)) ** 2
    r_lo = np.sqrt(dx2 + z[:, None] ** 2)
    r_hi = np.sqrt(dx2 + z[:, None] ** 2 + ELEVATION_REACH_M**2)
    c = WATER_C
    # Transmit: the plane wave reaches a point between its elements' earliest and latest
    # wavelets; receive: its nearest and farthest element; the pulse either side.
    t_lo = float(np.min(np.nanmin(delays + r_lo / c, axis=1) + r_lo.min(axis=1) / c)) - s.pulse_s
    t_hi = float(np.max(np.nanmax(delays + r_hi / c, axis=1) + r_hi.max(axis=1) / c)) + s.pulse_s
    span = t_hi - t_lo
    fc = s.medium.fc
    k = max(int(np.ceil(2.2 * span * fc)), MIN_PERIOD_CYCLES)
    t0 = t_lo - (k / fc / 2 - span) / 2
    p = s.scan.copy()
    p.TXdelay = delays.copy()
    p.t0 = np.array([t0])
    p.fnumber = s.fnumber
    das = pymust.dasmtx(1j * np.array([2 * k, s.array.active_elements]), x_px, z_px, p)
    return Transmit(delays, k, t0, _hann(das, 2 * k, x_px, z_px, s) if hann else das)


def _hann(das: Any, samples: int, x_px: Array, z_px: Array, s: Scanner) -> Any:
    """The DAS matrix with a Hann receive apodization over each pixel's f-number
    aperture (dasmtx's own is a hard-edged one): each entry weighted by its element's
    offset from the pixel's column, 1 on it, 0 at ± depth / (2 F#). Its columns are
    (sample, element) in column-major order, its rows the pixels (column-major)."""
    from scipy.sparse import csr_matrix

    m = das.tocoo()
    element = m.col // samples
    x = np.asarray(x_px, float).flatten(order="F")[m.row]
    z = np.asarray(z_px, float).flatten(order="F")[m.row]
    u = np.abs(x - _elements_x(s)[element]) / (z / (2.0 * s.fnumber))
    w = 0.5 + 0.5 * np.cos(np.pi * np.clip(u, 0.0, 1.0))
    return csr_matrix((m.data * w, (m.row, m.col)), shape=m.shape)


def beamformed(s: Scanner, tx: Transmit, p_us: Array, rc: Array) -> NDArray[np.complex128]:
    """I/Q at the transmit's pixels of scatterers ``p_us`` (us frame) with reflection
    coefficients ``rc``, times K (simus's RF scales as 1 / K)."""
    import pymust  # optional: only the reference needs pymust
    from pymust import utils

    x, y, z = _pymust_xyz(p_us, s)
    z = PR.pymust_depth(y, z)  # its elevation counted once (pymust_depth)
    p = s.medium.copy()
    fc = p.fc
    # simus's own frequency step (half the inverse of the longest path's time: its
    # in-plane distance plus the pulse, and the largest delay), scaled so that its grid
    # has the period K / fc; the RF advanced by t0 (a uniform receive delay: a phase per
    # frequency, exact) puts the window's echoes in the first half-period, which simus
    # returns.
    p.RXdelay = np.full((1, s.array.active_elements), -tx.t0)
    max_d = np.sqrt(np.max((x[:, None] - _elements_x(s)) ** 2 + z[:, None] ** 2))
    max_d += s.pulse_s * WATER_C
    step = 0.5 / (2 * max_d / WATER_C + max(float(np.nanmax(tx.delays)), float(np.max(p.RXdelay))))
    opt = utils.Options()
    opt.WaitBar = False
    opt.FrequencyStep = fc / (tx.k - 0.5) / step
    logging.disable(logging.WARNING)  # simus warns whenever FrequencyStep > 1
    try:
        rf, _ = pymust.simus(
            x[None].copy(),
            y[None].copy(),
            z[None].copy(),
            rc[None].astype(float),
            tx.delays.copy(),
            p,
            opt,
        )
    finally:
        logging.disable(logging.NOTSET)
    if rf.shape[0] != 2 * tx.k:
        raise RuntimeError(
            f"pymust's frequency grid is not the one asked for ({rf.shape[0]} RF samples, "
            f"expected {2 * tx.k}): its simus changed"
        )
    iq = pymust.rf2iq(rf, p.fs, fc)
    # rf2iq demodulates from the RF's first sample, which the receive delay put at t0, and
    # dasmtx rotates the I/Q's phase by true time: each transmit's sum carries
    # exp(2πj fc t0). The phase must go before the transmits are compounded (their t0
    # differ): left in, the steered waves added to the unsteered one 170° out of step at
    # 15 mm and drew side lobes of -3 dB 0.3 mm beside a point (a point's PSF, checked
    # against pymust without the window shift: equal within 0.6 dB to -40 dB).
    phase = np.exp(-2j * np.pi * fc * tx.t0)
    return np.asarray(tx.das @ iq.flatten(order="F")) * tx.k * phase


@dataclass(frozen=True)
class Crop:
    """The pixels beamformed about a sweep's sphere: rows and columns of the frame."""

    rows: NDArray[np.int64]
    cols: NDArray[np.int64]


def crop_of(probe: ProbeConfig, centre_us: Array) -> Crop:
    """± ``CROP_HALF_WIDTH_M`` about the sphere's column; from ``CROP_ABOVE_M`` above its
    cap's top to ``CROP_BELOW_M`` below its centre, at displayed depths."""
    H, W = probe.image_shape
    sx, sy = probe.spacing_m
    x, _ = pixel_axes(0, np.arange(W), W, (sx, sy))
    cols = np.flatnonzero(np.abs(x - centre_us[0]) <= CROP_HALF_WIDTH_M + 1e-9)
    shown = 1.0 / axial_scale(probe)  # displayed / true depth
    top = (centre_us[1] - RADIUS_M - CROP_ABOVE_M) * shown / sy
    bottom = (centre_us[1] + CROP_BELOW_M) * shown / sy
    rows = np.arange(max(int(np.ceil(top)), 0), min(int(np.floor(bottom)), H - 1) + 1)
    return Crop(rows, cols)


def to_grey(envelope: Array, reference: float, dynamic_range_db: float) -> NDArray[np.uint8]:
    """Log compression as sim_us's display does it (gain 0): 0 dB (white) at
    ``reference``, black ``dynamic_range_db`` below, rounded to 8 bits."""
    db = 20.0 * np.log10(np.maximum(envelope / reference, 1e-30))
    grey = (db + dynamic_range_db) * 255.0 / dynamic_range_db + 0.5
    return np.clip(grey, 0.0, 255.0).astype(np.uint8)


def cap_depth(centre_us: Array) -> float:
    """The true depth (m) of the sphere's top, its centre at ``centre_us``."""
    return float(centre_us[1] - RADIUS_M)


def sheet(s: Scanner, depth: float, steer_deg: tuple[float, ...]) -> tuple[Array, Array]:
    """A perfect flat reflector (reflection coefficient 1, smooth) at true ``depth`` (m),
    under the aperture: points (n, 3, us frame) of a λ/2 square grid (its first Bragg echo
    would need sin θ_in + sin θ_out = 2: none) and their weights (taper × area per point /
    λ², as the sphere's)."""
    lam = wavelength_m(s.array)
    spacing = 0.5 * lam
    a = s.array
    half_array = a.active_elements * a.pitch_mm * MM / 2
    hx = half_array + depth * np.tan(np.radians(max(abs(v) for v in steer_deg))) + SHEET_MARGIN_M
    hz = ELEVATION_REACH_M
    u = np.arange(-hx, hx + 1e-12, spacing)
    v = np.arange(-hz, hz + 1e-12, spacing)
    w = np.outer(
        _taper((hx - np.abs(u)) / SHEET_TAPER_M), _taper((hz - np.abs(v)) / ELEVATION_TAPER_M)
    )
    uu, vv = np.meshgrid(u, v, indexing="ij")
    p = np.column_stack([s.x_aperture + uu.ravel(), np.full(uu.size, depth), vv.ravel()])
    keep = w.ravel() > 0
    return p[keep], w.ravel()[keep] * spacing**2 / lam**2


def reference_level(s: Scanner, depth: float, x_px: float, shown: float) -> tuple[float, float]:
    """The envelope (× K, compounded as the frames) of the perfect reflector at true
    ``depth`` (m) on the sphere's column ``x_px`` (pymust's x), and the displayed depth of
    its peak (m). ``shown`` is displayed / true depth."""
    p, w = sheet(s, depth, STEER_DEG)
    z = depth * shown + np.arange(-1e-3, 1e-3 + 1e-9, 0.01e-3)
    x = np.full_like(z, x_px)
    medium = s.medium
    s_flat = replace(s, medium=medium.copy())
    s_flat.medium.attenuation = 0.0  # a reference: the perfect reflector without loss
    iq = sum(beamformed(s_flat, transmit(s_flat, a, p, x, z), p, w) for a in STEER_DEG)
    env = np.abs(np.asarray(iq)).ravel()
    return float(np.max(env)), float(z[int(np.argmax(env))])


def zero_db_level(s: Scanner, x_px: float, probe: ProbeConfig) -> float:
    """The frames' 0 dB: the perfect reflector's envelope (as :func:`reference_level`) at
    the elevation focus as displayed, where sim_us's display puts its 0 dB
    (:func:`sim_us.beam.flat_echo_gain` is 1 there)."""
    shown = 1.0 / axial_scale(probe)
    focus = probe.elevation_focus_mm * MM / shown  # true depth
    return reference_level(s, focus, x_px, shown)[0]


def regreyed(
    frames: NDArray[np.uint8], envelope_from: float, envelope_to: float, dr: float
) -> NDArray[np.uint8]:
    """Frames displayed with 0 dB at ``envelope_from`` shown with 0 dB at ``envelope_to``
    (≥ it: darker, so nothing lit was clipped black): every lit grey level moved by the
    ratio in dB and rounded again (±0.5 grey, 0.12 dB, of re-quantization), black kept
    black."""
    if envelope_to < envelope_from:
        raise ValueError("re-displaying brighter would need the pixels clipped black")
    shift = 20.0 * np.log10(envelope_from / envelope_to) * 255.0 / dr
    grey = np.clip(np.floor(frames.astype(float) + shift + 0.5), 0.0, 255.0)
    return np.where(frames > 0, grey, 0.0).astype(np.uint8)


def diffuse_scale(
    s: Scanner, centre_us: Array, x_px: float, z_peak: float, cap_level: float, d: Diffuse
) -> float:
    """The amplitude scale of the diffuse scatterers: a sheet of them (their density, unit
    variance; the perfect reflector's extent and taper, at the cap's depth) facing the
    probe returns a mean intensity ``(DIFFUSE_SHARE · PLA_REFLECTION · cap_level)²`` (the
    perfect reflector's envelope there) at the
    mirror's peak depth ``z_peak`` (displayed), compounded as the frames, over ± 5 mm of
    the sphere's column ``x_px``, without attenuation."""
    p_sheet, _ = sheet(s, cap_depth(centre_us), STEER_DEG)
    lo, hi = p_sheet.min(axis=0), p_sheet.max(axis=0)
    extent = (hi[0] - lo[0]) * (hi[2] - lo[2])
    n = round(extent / d.area_m2)
    s_flat = replace(s, medium=s.medium.copy())
    s_flat.medium.attenuation = 0.0
    x = x_px + np.arange(
        -DIFFUSE_CALIBRATION_HALF_WIDTH_M, DIFFUSE_CALIBRATION_HALF_WIDTH_M + 1e-9, 0.1e-3
    )
    z = np.full_like(x, z_peak)
    rng = np.random.default_rng(SEED + 2)
    intensity = []
    for _ in range(DIFFUSE_CALIBRATION_SHEETS):
        u = rng.uniform(lo, hi, size=(n, 3))
        u[:, 1] = lo[1]
        # The perfect reflector's taper at each random point.
        hx, hz = (hi[0] - lo[0]) / 2, (hi[2] - lo[2]) / 2
        taper = _taper((hx - np.abs(u[:, 0] - s.x_aperture)) / SHEET_TAPER_M) * _taper(
            (hz - np.abs(u[:, 2])) / ELEVATION_TAPER_M
        )
        rc = rng.standard_normal(n) * taper
        iq = sum(beamformed(s_flat, transmit(s_flat, a, u, x, z), u, rc) for a in STEER_DEG)
        intensity.append(np.mean(np.abs(np.asarray(iq)) ** 2))
    return float(DIFFUSE_SHARE * PLA_REFLECTION * cap_level / np.sqrt(np.mean(intensity)))


def _surface_weights(n_points: int, lam: float) -> float:
    """A lattice point's share of the surface, per λ² (the sheet's too): reflectivity
    per unit area, whatever the lattice."""
    return 4 * np.pi * RADIUS_M**2 / n_points / lam**2


def sweep_scanner(
    a: Any, probe: ProbeConfig, spec: SweepSpec
) -> tuple[Array, Scanner, Crop, Array, Array, float]:
    """A sweep's sphere centre (its reference frame), its scanner (the aperture over the
    sphere), the frames' crop and its pixel axes (x, displayed depth), and the sphere's
    column in pymust's x."""
    centre = true_centre(sweep_poses(spec))
    s = scanner(a, float(centre[0]))
    crop = crop_of(probe, centre)
    x, y = pixel_axes(crop.rows, crop.cols, probe.image_shape[1], probe.spacing_m)
    col = int(np.argmin(np.abs(x - centre[0])))
    return centre, s, crop, x, y, float(x[col] - s.x_aperture)


def render_sweep(
    a: Any,
    probe: ProbeConfig,
    spec: SweepSpec,
    surface: tuple[Array, Array],
    diffuse: Diffuse | None = None,
    log: bool = True,
) -> tuple[NDArray[np.uint8], dict[str, Any]]:
    """One sweep's frames (FRAMES, H, W) rendered with pymust, and what it took: the
    mirror's lattice, and with ``diffuse`` its share as random scatterers."""
    t_start = time.perf_counter()
    T = sweep_poses(spec)
    centre, s, crop, x, y, x_col = sweep_scanner(a, probe, spec)
    X, Z = np.meshgrid(x - s.x_aperture, y)  # pymust's x; displayed depth
    points, normals = surface
    p_mid, w_cap = cap_in_frame(points, normals, T[FRAMES // 2])
    rc = w_cap * PLA_REFLECTION * _surface_weights(len(points), wavelength_m(a))
    shown = 1.0 / axial_scale(probe)
    reference, z_peak = reference_level(s, cap_depth(centre), x_col, shown)
    zero_db = zero_db_level(s, x_col, probe)
    scale = None
    if diffuse is not None:
        # The mirror keeps 1 − d² of the energy; the diffuse share d² is the scatterers'.
        scale = diffuse_scale(s, centre, x_col, z_peak, reference, diffuse)
        p_d, amp_d = facing_in_frame(diffuse, T[FRAMES // 2])
        p_mid = np.concatenate([p_mid, p_d])
        rc = np.concatenate([rc * np.sqrt(1.0 - DIFFUSE_SHARE**2), amp_d * scale])
    txs = [transmit(s, angle, p_mid, X, Z) for angle in STEER_DEG]
    frames = np.zeros((FRAMES, *probe.image_shape), np.uint8)
    z = (np.arange(FRAMES) - FRAMES // 2) * FRAME_STEP_M
    counts = []
    for k, zk in enumerate(z):
        p, w = elevation_slab(p_mid - [0.0, 0.0, zk], rc)
        counts.append(len(p))
        if not len(p):
            continue  # nothing within the elevation reach: a black frame
        iq = sum(beamformed(s, tx, p, w) for tx in txs)
        env = np.abs(np.asarray(iq)).reshape(X.shape, order="F")
        frames[k][np.ix_(crop.rows, crop.cols)] = to_grey(env, zero_db, probe.dynamic_range_db)
    seconds = time.perf_counter() - t_start
    if log:
        print(
            f"  pymust sweep {spec}: {sum(counts)} scatterer-frames, {seconds:.0f} s",
            file=sys.stderr,
        )
    info = {
        "scatterers_per_frame": counts,
        "aperture_centre_mm": s.x_aperture / MM,
        "reference_envelope": reference,
        "zero_db_envelope": zero_db,
        "diffuse_scale": scale,
        "window_periods_k": [tx.k for tx in txs],
        "crop_rows": [int(crop.rows[0]), int(crop.rows[-1])],
        "crop_cols": [int(crop.cols[0]), int(crop.cols[-1])],
        "seconds": round(seconds, 1),
    }
    return frames, info


ZERO_DB_RECORD = (
    "the compounded envelope of a smooth perfect reflector (unit sheet) at the elevation "
    "focus as displayed (18 mm), on the sphere's column, no attenuation (sim_us's 0 dB); "
    "the diffuse share is calibrated against the same sheet at the cap's depth "
    "(reference_envelope)"
)


def method_record(surface: str = "smooth") -> dict[str, Any]:
    """How the stored frames of ``surface`` were made (the module docstring in figures)."""
    record = {
        "imaging": "coherently compounded steered plane waves (64 active elements centred "
        "over the sphere), pymust simus (3-D, elevation lens) + rf2iq (low-pass at fc) + "
        "dasmtx at the scanner's 1540 m/s with the directivity f-number, the transmit and the "
        "receive Hann-apodized; "
        "each transmit's I/Q phase referred to true time (exp(-2πj fc t0)) before compounding; "
        "each scatterer at elevation y, depth z handed to simus at depth sqrt(z^2 - y^2) "
        "(pymust counts the elevation twice: physics_reference.pymust_depth)",
        "steer_deg": list(STEER_DEG),
        "receive_fnumber": round(PR.receive_fnumber(PR.paper_probe().array), 4),
        "medium": "water 20 °C (MediumConfig()): c from calib.sound, attenuation at fc "
        "(pymust's is linear in f)",
        "speed_m_s": WATER_C,
        "surface": "Fibonacci lattice on the CAD sphere (roughness along the normal by "
        "twin.printing.roughness_height if roughness_ra_m > 0), reflection coefficient "
        "of PLA in water, weight area per point / λ²",
        "lattice_wavelengths": LATTICE_WAVELENGTHS,
        "roughness_ra_m": ROUGHNESS_RA_M,
        "roughness_length_m": ROUGHNESS_LENGTH_M,
        "pla_reflection": PLA_REFLECTION,
        "cap_deg": list(CAP_DEG),
        "elevation_reach_m": ELEVATION_REACH_M,
        "elevation_taper_m": ELEVATION_TAPER_M,
        "crop_m": {"half_width": CROP_HALF_WIDTH_M, "above_cap": CROP_ABOVE_M},
        "crop_below_centre_m": CROP_BELOW_M,
        "zero_db": ZERO_DB_RECORD,
        "grey": "(20 log10(envelope / 0 dB) + DR) · 255 / DR, rounded, clipped (sim_us's "
        "display at gain 0); outside the crop 0",
        "dynamic_range_db": probe_config().dynamic_range_db,
        "min_period_cycles": MIN_PERIOD_CYCLES,
        "seed": SEED,
    }
    if surface == "diffuse":
        record["diffuse"] = {
            "what": "random scatterers uniform on the whole sphere (those facing the probe "
            "in each sweep), unit-variance Gaussian amplitudes fixed by seed + 1, scaled so "
            "that a facing sheet of them (the perfect reflector's extent and taper, random "
            "points at the same density, seed + 2) has a mean compounded intensity at the "
            "mirror's peak depth of (share · PLA reflection · 0 dB)², over ± half_width of "
            "the sphere's column, no attenuation; the mirror's lattice × √(1 − share²)",
            "share": DIFFUSE_SHARE,
            "spacing_wavelengths": DIFFUSE_SPACING_WAVELENGTHS,
            "calibration_half_width_m": DIFFUSE_CALIBRATION_HALF_WIDTH_M,
            "calibration_sheets": DIFFUSE_CALIBRATION_SHEETS,
        }
    return record


def write_stored(
    frames: list[NDArray[np.uint8]],
    infos: list[dict[str, Any]],
    surface: str = "smooth",
    realization: int = 0,
) -> None:
    """Frames (uint8), spacing, poses, true centres, the probe, the method, pymust's
    version and the command, in the surface's (realization's) file (compressed)."""
    path = stored_path(surface, realization)
    probe = probe_config()
    poses = np.array([sweep_poses(spec) for spec in SWEEPS])
    meta = {
        "what": "elevational sweeps of a 5 mm PLA sphere in water rendered with pymust "
        "(benchmarks/reference_sweeps.py's docstring)",
        "command": command(surface, realization),
        "realization": realization,
        "pymust_version": importlib.metadata.version("pymust"),
        "array": asdict(PR.paper_probe().array),
        "probe": {
            k: getattr(probe, k)
            for k in (
                "f_mhz",
                "bandwidth_pct",
                "pitch_mm",
                "kerf_mm",
                "active_elements",
                "elevation_aperture_mm",
                "elevation_focus_mm",
                "width_mm",
                "depth_mm",
                "pixel_spacing_mm",
                "assumed_speed_m_s",
                "dynamic_range_db",
            )
        },
        "sweeps": [asdict(spec) for spec in SWEEPS],
        "method": method_record(surface),
        "per_sweep": infos,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    # An interrupted render (hours of pymust) leaves the stored file it had.
    with replaced_atomically(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(
            f,
            frames=np.array(frames, np.uint8),
            spacing=np.array(probe.spacing_m),
            T_base_ee=poses,
            T_ee_us=np.eye(4),
            centre_base=CENTRE_BASE,
            centre_ref=np.array([true_centre(T) for T in poses]),
            radius=np.array(RADIUS_M),
            axial_scale=np.array(axial_scale(probe)),
            meta=np.array(json.dumps(meta, ensure_ascii=False)),
        )


def write_zero_db() -> None:
    """Frames stored with the cap's depth as their 0 dB (before 2026-11-30: sim_us's 0 dB
    was the same perfect reflector at every depth until its echoes carried the flat
    reflector's level against depth) shown again with the elevation focus's: pymust's
    perfect reflector at the focus, per sweep (≈ 1.5 min of one core each, once for every
    stored file: the sweeps' apertures are the same), each file's lit grey levels moved by
    the ratio (:func:`regreyed`) and its record updated."""
    from threadpoolctl import threadpool_limits

    a = PR.paper_probe().array
    probe = probe_config()
    levels: dict[int, float] = {}
    for surface in SURFACES:
        for k in stored_realizations(surface):
            path = stored_path(surface, k)
            with np.load(path, allow_pickle=False) as f:
                arrays = {name: f[name] for name in f.files}
            meta = json.loads(str(arrays["meta"]))
            if all("zero_db_envelope" in p for p in meta["per_sweep"]):
                continue
            for i, spec in enumerate(SWEEPS):
                if i not in levels:
                    _, s, _, _, _, x_col = sweep_scanner(a, probe, spec)
                    with threadpool_limits(1):
                        levels[i] = zero_db_level(s, x_col, probe)
                info = meta["per_sweep"][i]
                arrays["frames"][i] = regreyed(
                    arrays["frames"][i],
                    info["reference_envelope"],
                    levels[i],
                    probe.dynamic_range_db,
                )
                info["zero_db_envelope"] = levels[i]
            meta["method"]["zero_db"] = ZERO_DB_RECORD
            meta["method"]["regreyed"] = (
                "rendered with the cap's depth as 0 dB and shown again with the elevation "
                "focus's (write_zero_db: each lit grey level moved by 20 log10(reference / "
                "zero_db) · 255 / DR and rounded again)"
            )
            arrays["meta"] = np.array(json.dumps(meta, ensure_ascii=False))
            with replaced_atomically(path) as tmp, open(tmp, "wb") as f:
                np.savez_compressed(f, **arrays)
            print(f"re-displayed {path.relative_to(ROOT)}")


# ------------------------------------------------------------------ the beam in water

# The scanner's delays assume 1540 m/s; in water sound travels at ≈ 1480 m/s, so its
# focus is off: a point's PSF at these depths (true, mm), each column's brightest pixel
# (as the display shows the compounding's tilted tails), its levels at these offsets.
WATER_PSF_DEPTHS_MM = (15.0, 20.0, 25.0)
WATER_PSF_OFFSETS_MM = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.2, 1.5)
WATER_PSF_STORED = Path(_HERE) / "reference" / "water_psf.json"


def reference_psf(imaging: str, depth_m: float) -> dict[str, Any]:
    """pymust's displayed PSF of one point in water at ``depth_m`` (true) under the
    aperture's centre, imaged as :func:`probe_config` (``imaging``) says: "plane waves"
    (:data:`STEER_DEG`, Hann across the transmit and over the receive F#, beamformed at
    every pixel about the point) or "focused" (sim_us's focused default: each scanline
    its own transmit, focused on it at the point's displayed depth from the elements
    within depth / 2F#, dasmtx's hard receive aperture; the line at offset x images the
    point as the line at 0 images the point at −x, the aperture moving with the line).
    Each column's brightest pixel within ± 1 mm of the point's depth; its FWHM and levels
    (dB, both sides' mean) at :data:`WATER_PSF_OFFSETS_MM`."""
    import pymust  # optional: only the reference needs pymust
    from threadpoolctl import threadpool_limits

    a = PR.paper_probe().array
    s = scanner(a, 0.0)
    shown = 1.0 / axial_scale(probe_config())
    z = depth_m * shown + np.arange(-1.0, 1.0 + 1e-9, 0.01) * MM
    with threadpool_limits(1):
        if imaging == "plane waves":
            p = np.array([[0.0, depth_m, 0.0]])
            x = np.arange(-2.0, 2.0 + 1e-9, 0.01) * MM
            X, Z = np.meshgrid(x, z)
            iq = sum(beamformed(s, transmit(s, ang, p, X, Z), p, np.ones(1)) for ang in STEER_DEG)
            env = np.abs(np.asarray(iq)).reshape(X.shape, order="F")
            profile = env.max(axis=0)
            x_mm = x / MM
        else:
            del s.medium["TXapodization"]  # sim_us's focused default: rect
            apod = PR.aperture(a, depth_m * shown, s.fnumber)
            delays = np.asarray(pymust.txdelay(0.0, depth_m * shown, s.scan), float)
            delays = delays.reshape(1, -1)
            delays[0, apod == 0] = np.nan  # off: no transmit
            delays[0] -= np.nanmin(delays)
            offsets = np.arange(0.0, 2.0 + 1e-9, 0.02) * MM
            column = np.zeros_like(z)
            points = np.column_stack([-offsets, np.full_like(offsets, depth_m), 0 * offsets])
            tx = transmit(s, 0.0, points, column, z, delays, hann=False)
            half = np.array(
                [np.abs(np.asarray(beamformed(s, tx, q[None], np.ones(1)))).max() for q in points]
            )
            profile = np.concatenate([half[:0:-1], half])
            x_mm = np.concatenate([-offsets[:0:-1], offsets]) / MM
    return _psf_figures(x_mm, profile / profile.max())


def _psf_figures(x_mm: Array, profile: Array) -> dict[str, Any]:
    """FWHM (mm) and the levels (dB, both sides' mean amplitude) of a lateral profile."""

    def level(o: float) -> float:
        both = np.interp(o, x_mm, profile) + np.interp(-o, x_mm, profile)
        return round(float(20.0 * np.log10(max(both / 2.0, 1e-6))), 2)

    return {
        "fwhm_mm": round(PR.fwhm(x_mm, profile), 4),
        "levels_db": [level(o) for o in WATER_PSF_OFFSETS_MM],
    }


def twin_psf(imaging: str, depth_m: float) -> dict[str, Any]:
    """sim_us's lateral PSF in water for the same imaging at the point's displayed depth:
    the kernel it blurs echoes with (``beam_of(probe, water's speed)``)."""
    probe = probe_config(imaging)
    x = np.arange(-2.0, 2.0 + 1e-9, 0.005)
    prof = beam_of(probe, WATER_C).lateral_profile(depth_m / axial_scale(probe), x * MM)[0]
    return _psf_figures(x, prof / prof.max())


def write_water_psf() -> None:
    """pymust's PSFs in water (both imagings, every depth) in :data:`WATER_PSF_STORED`."""
    rec: dict[str, Any] = {
        "what": "a point's displayed PSF in water (20 °C) imaged by a scanner assuming "
        f"{probe_config().assumed_speed_m_s:g} m/s, pymust {importlib.metadata.version('pymust')}",
        "command": f"{COMMAND}-psf",
        "depths_mm": list(WATER_PSF_DEPTHS_MM),
        "offsets_mm": list(WATER_PSF_OFFSETS_MM),
    }
    for imaging in IMAGING:
        rec[imaging] = [reference_psf(imaging, d * MM) for d in WATER_PSF_DEPTHS_MM]
    write_text_atomic(WATER_PSF_STORED, json.dumps(rec, indent=1) + "\n")


def print_water_psf() -> float:
    """The stored reference's PSFs in water beside sim_us's; returns the largest level
    difference (dB) down to -20 dB of the main lobe."""
    rec = json.loads(WATER_PSF_STORED.read_text())
    offsets = rec["offsets_mm"]
    print(
        f"\nA point's PSF in water, scanner at {probe_config().assumed_speed_m_s:g} m/s "
        f"(column max, dB at offsets in mm; {rec['what']}):"
    )
    print(
        f"{'imaging':>11} {'mm':>3} | FWHM ref twin ratio | "
        + " ".join(f"{o:5.2f}" for o in offsets)
    )
    worst = 0.0
    for imaging in IMAGING:
        for d, ref in zip(rec["depths_mm"], rec[imaging], strict=True):
            tw = twin_psf(imaging, d * MM)
            main = [i for i, v in enumerate(ref["levels_db"]) if v >= -20.0]
            worst = max(worst, *(abs(tw["levels_db"][i] - ref["levels_db"][i]) for i in main))
            print(
                f"{imaging:>11} {d:3.0f} | {ref['fwhm_mm']:.3f} {tw['fwhm_mm']:.3f} "
                f"{tw['fwhm_mm'] / ref['fwhm_mm']:5.2f} | "
                + " ".join(f"{v:5.1f}" for v in ref["levels_db"])
                + "\n"
                + " " * 37
                + "twin | "
                + " ".join(f"{v:5.1f}" for v in tw["levels_db"])
            )
    return worst


# ------------------------------------------------------------------ the check


def load_stored(surface: str = "smooth", realization: int = 0) -> dict[str, Any]:
    """A surface's stored sweeps (a realization of its diffuse scatterers; no pickles):
    arrays by name, ``meta`` decoded, and the ``surface``."""
    with np.load(stored_path(surface, realization), allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    data["meta"] = json.loads(str(data["meta"]))
    data["surface"] = surface
    return data


def sweeps_of(frames: NDArray[np.uint8], data: dict[str, Any]) -> list[Sweep]:
    """The localizer's sweeps of ``frames`` (S, n, H, W) at the stored poses."""
    spacing = (float(data["spacing"][0]), float(data["spacing"][1]))
    return [
        Sweep("sphere_1", i, np.ascontiguousarray(f), spacing, np.zeros((len(f), 6)), T)
        for i, (f, T) in enumerate(zip(frames, data["T_base_ee"], strict=True))
    ]


def twin_frames(
    poses: Array,
    surface: str = "smooth",
    probe: ProbeConfig | None = None,
    speckle_key: int = 0,
) -> NDArray[np.uint8]:
    """sim_us's frames (S, n, H, W) of the same scene at the same poses: an icosphere of
    PLA in water (without its diffuse share for the "smooth" surface), noise-free, imaged
    as the reference does unless ``probe`` says otherwise; ``speckle_key`` picks the
    realization of the surface's speckle (the diffuse share's random phases)."""
    probe = probe or probe_config()
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS_M)
    mesh.apply_translation(CENTRE_BASE)
    scene = AcousticScene((ScenePart("sphere", mesh, sphere_material(surface)),))
    sim = BmodeSimulator(scene, probe, MEDIUM, speckle_key=speckle_key)
    return np.array([sim.render(T, None) for T in poses])


# The diffuse sphere's speckle is one random draw on either side: sim_us's error is
# measured over this many realizations of it (keys 0, 1, …), and pymust's single
# realization is compared with their median.
SPECKLE_REALIZATIONS = 20
# pymust's draws of the diffuse sphere the issue's criterion reads: realizations 0-4, the
# number fixed before they were made. Those past it (up to MAX_REALIZATIONS) were rendered
# after the five had given their verdict, to measure how far the ratio of medians moves
# with the draws: reported beside it with a bootstrap interval, never judged (a verdict
# read on draws added until it passed would be fitted to them).
CRITERION_REALIZATIONS = 5
# Resamples of the bootstrap interval of pymust's median over sim_us's (fixed seed).
BOOTSTRAP_RESAMPLES = 4000
BOOTSTRAP_SEED = 35


def twin_spread(data: dict[str, Any], imaging: str = "plane waves") -> dict[str, Array]:
    """sim_us's error (mm, NaN where rejected) per method, speckle realization and sweep,
    each (SPECKLE_REALIZATIONS, sweeps), for the stored surface's scene and poses."""
    probe = probe_config(imaging)
    out: dict[str, list] = {method: [] for method in METHODS}
    for key in range(SPECKLE_REALIZATIONS):
        sweeps = sweeps_of(twin_frames(data["T_base_ee"], data["surface"], probe, key), data)
        for method in METHODS:
            out[method].append(errors_mm(localize(sweeps, data, method), data["centre_ref"]))
    return {method: np.array(v) for method, v in out.items()}


def reference_errors(
    surface: str, criterion_only: bool = False
) -> tuple[list[int], dict[str, Array]]:
    """The localizer's error (mm, NaN where rejected) on each stored realization of
    pymust's frames of a surface (with ``criterion_only`` those the criterion reads:
    :data:`CRITERION_REALIZATIONS`): (the realizations, {method: (realizations,
    sweeps)})."""
    reals = stored_realizations(surface)
    if criterion_only:
        reals = [k for k in reals if k < CRITERION_REALIZATIONS]
    out: dict[str, list] = {method: [] for method in METHODS}
    for k in reals:
        data = load_stored(surface, k)
        sweeps = sweeps_of(data["frames"], data)
        for method in METHODS:
            out[method].append(errors_mm(localize(sweeps, data, method), data["centre_ref"]))
    return reals, {method: np.array(v) for method, v in out.items()}


def _spread_cell(e: Array) -> tuple[float, float, float, int]:
    """(median, 10th, 90th percentile, count) of the finite errors."""
    ok = e[np.isfinite(e)]
    if not len(ok):
        return np.nan, np.nan, np.nan, 0
    lo, med, hi = np.percentile(ok, [10, 50, 90])
    return float(med), float(lo), float(hi), len(ok)


def ratio_interval(e_ref: Array, e_twin: Array, level: float = 0.9) -> tuple[float, float]:
    """Percentile-bootstrap interval (``level``) of median(``e_ref``) / median(``e_twin``)
    over their finite values, each side resampled on its own: how far the ratio of medians
    moves with the draws on either side (five to eight pymust draws, twenty of sim_us's)."""
    a, b = e_ref[np.isfinite(e_ref)], e_twin[np.isfinite(e_twin)]
    if not (len(a) and len(b)):
        return np.nan, np.nan
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    ra = np.median(rng.choice(a, (BOOTSTRAP_RESAMPLES, len(a))), axis=1)
    rb = np.median(rng.choice(b, (BOOTSTRAP_RESAMPLES, len(b))), axis=1)
    tail = 50.0 * (1.0 - level)
    lo, hi = np.percentile(ra / rb, [tail, 100.0 - tail])
    return float(lo), float(hi)


def print_spread(data: dict[str, Any]) -> float:
    """pymust's error per sweep over its stored realizations of the scatterers against
    sim_us's over its speckle realizations (the reference's imaging, and a focused
    scanner's); returns the worst ratio of pymust's median to sim_us's over the sweeps
    and methods both accept, pymust's median over the criterion's draws
    (:data:`CRITERION_REALIZATIONS`). Where more are stored, a second table gives the
    ratio over all of them with its bootstrap interval (:func:`ratio_interval`)."""
    reals, ref = reference_errors(data["surface"])
    n_crit = sum(k < CRITERION_REALIZATIONS for k in reals)
    spreads = {imaging: twin_spread(data, imaging) for imaging in IMAGING}
    print(
        f"\nThe speckle is a random draw on either side: pymust over {len(reals)} stored "
        f"realizations of the scatterers ({', '.join(map(str, reals))}; each error, mm; "
        f"the criterion's median over the first {n_crit}, fixed before they were made), "
        f"sim_us over {SPECKLE_REALIZATIONS} of its speckle (median [10th-90th "
        "percentile]); ratio = pymust's median / sim_us's"
    )
    print(
        f"{'sweep':>5} {'method':>8} | {'pymust mm':^{6 * len(reals) + 8}} | "
        f"{'twin (plane waves)':^26} {'ratio':>5} | {'focused scanner':^22}"
    )
    worst = float("nan")
    for method in METHODS:
        for i in range(len(data["centre_ref"])):
            e_ref = ref[method][:n_crit, i]
            med_ref = float(np.median(e_ref)) if np.all(np.isfinite(e_ref)) else np.nan
            med, lo, hi, n = _spread_cell(spreads["plane waves"][method][:, i])
            fmed, flo, fhi, fn = _spread_cell(spreads["focused"][method][:, i])
            ratio = med_ref / med if np.isfinite(med_ref) and np.isfinite(med) else np.nan
            if np.isfinite(ratio):
                worst = ratio if not np.isfinite(worst) else max(worst, ratio)
            each = " ".join(f"{v:5.3f}" for v in ref[method][:, i])
            print(
                f"{i:>5} {method:>8} | {each} med {med_ref:5.3f} | {med:6.3f} "
                f"[{lo:5.3f}-{hi:5.3f}] {n:>2}/{SPECKLE_REALIZATIONS} {ratio:5.2f} | "
                f"{fmed:6.3f} [{flo:5.3f}-{fhi:5.3f}] {fn:>2}"
            )
    print(
        f"\nThe ratio's spread over the draws (refined; 90 % bootstrap interval of pymust's "
        f"median over sim_us's, {BOOTSTRAP_RESAMPLES} resamples of either side):"
    )
    print(f"{'sweep':>5} | {'first ' + str(n_crit):^20} | {'all ' + str(len(reals)):^20}")
    for i in range(len(data["centre_ref"])):
        twin = spreads["plane waves"]["refined"][:, i]
        cells = []
        for e in (ref["refined"][:n_crit, i], ref["refined"][:, i]):
            r = float(np.median(e) / np.nanmedian(twin)) if np.all(np.isfinite(e)) else np.nan
            lo, hi = ratio_interval(e, twin)
            cells.append(f"{r:5.2f} [{lo:4.2f}-{hi:4.2f}]")
        print(f"{i:>5} | {cells[0]:^20} | {cells[1]:^20}")
    return worst


def localize(sweeps: list[Sweep], data: dict[str, Any], method: str) -> list[SweepLocalization]:
    """The repository's localizer on the sweeps of one sphere (together, as the pipeline
    runs it: with ``T_ee_us`` known, method "refined" uses their consensus)."""
    return localize_sphere(
        sweeps,
        np.asarray(data["T_ee_us"]),
        float(data["radius"]),
        LocalizerConfig(method=method),
        axial_scale=float(data["axial_scale"]),
    )


def errors_mm(locs: list[SweepLocalization], truths: Array) -> Array:
    """Each sweep's centre error (mm; NaN where rejected)."""
    return np.array(
        [
            np.linalg.norm(r.centre - t) / MM if r.accepted else np.nan
            for r, t in zip(locs, truths, strict=True)
        ]
    )


METHODS = ("refined", "paper")
WRONG_MM = 1.0


def _status(r: SweepLocalization) -> str:
    return "accepted" if r.accepted else "rejected"


def print_table(data: dict[str, Any], results: dict[str, dict[str, list]]) -> tuple[float, int]:
    """One row per sweep and method: the error of the centre found in pymust's frames and
    in sim_us's, and each rejection's reason; the ratio of the median errors per method.
    Returns (the worst per-sweep error ratio pymust / sim_us over sweeps both accepted,
    the number of centres accepted from pymust's frames more than ``WRONG_MM`` off)."""
    truths = data["centre_ref"]
    print(
        "\nThe localizer on pymust's frames (ref) and on sim_us's (twin), same scene and "
        "poses; error = |centre − truth|, mm (sweep reference frame)."
    )
    print(
        f"{'sweep':>5} {'centre x/depth/elev mm':>24} {'method':>8} | {'ref mm':>7} "
        f"{'ref':>8} | {'twin mm':>7} {'twin':>8} | {'ratio':>5}"
    )
    worst, wrong = float("nan"), 0
    reasons: list[str] = []
    for i, t in enumerate(truths):
        where = f"{t[0] / MM:+6.2f} {t[1] / MM:6.2f} {t[2] / MM:+6.2f}"
        for method in METHODS:
            r_ref, r_twin = results["ref"][method][i], results["twin"][method][i]
            e_ref = np.linalg.norm(r_ref.centre - t) / MM if r_ref.accepted else np.nan
            e_twin = np.linalg.norm(r_twin.centre - t) / MM if r_twin.accepted else np.nan
            ratio = e_ref / e_twin if np.isfinite(e_ref) and np.isfinite(e_twin) else np.nan
            if np.isfinite(ratio):
                worst = ratio if not np.isfinite(worst) else max(worst, ratio)
            wrong += int(r_ref.accepted and e_ref > WRONG_MM)
            print(
                f"{i:>5} {where:>24} {method:>8} | {e_ref:7.3f} {_status(r_ref):>8} | "
                f"{e_twin:7.3f} {_status(r_twin):>8} | {ratio:5.2f}"
            )
            for side, r in (("ref", r_ref), ("twin", r_twin)):
                if not r.accepted:
                    reasons.append(f"  sweep {i} {method} {side}: {r.reason}")
    if reasons:
        print("rejected:")
        print("\n".join(reasons))
    for method in METHODS:
        e = {side: errors_mm(results[side][method], truths) for side in ("ref", "twin")}
        med = {side: np.nanmedian(v) if np.isfinite(v).any() else np.nan for side, v in e.items()}
        print(
            f"{method}: median error ref {med['ref']:.3f} mm, twin {med['twin']:.3f} mm, "
            f"ratio ref / twin {med['ref'] / med['twin']:.2f} "
            f"(accepted {np.isfinite(e['ref']).sum()} / {len(truths)} ref, "
            f"{np.isfinite(e['twin']).sum()} / {len(truths)} twin)"
        )
    return worst, wrong


def render_reference(
    surface: str = "smooth", log: bool = True, realization: int = 0
) -> tuple[list[NDArray[np.uint8]], list[dict[str, Any]]]:
    """All sweeps' pymust frames of a surface (a realization of its diffuse scatterers),
    on one BLAS thread."""
    from threadpoolctl import threadpool_limits

    a = PR.paper_probe().array
    probe = probe_config()
    lattice = sphere_surface(a)
    diffuse = diffuse_scatterers(a, realization) if surface == "diffuse" else None
    frames, infos = [], []
    with threadpool_limits(1):
        for spec in SWEEPS:
            f, info = render_sweep(a, probe, spec, lattice, diffuse, log)
            frames.append(f)
            infos.append(info)
    return frames, infos


def focused_frame(surface: str, sweep: int, frame: int) -> NDArray[np.float64]:
    """One frame of a stored sweep's scene imaged as a focused scanner does it, with
    pymust: a transmit per scanline 0.2 mm apart (focused on the line at the cap's depth,
    the elements within depth / 2F# of it), dynamic receive as the plane-wave frames
    (``dasmtx``, Hann over the directivity F#), the scatterers within ± 2 mm of the
    line; the columns between lines interpolated. The envelope (H, W), not displayed."""
    import pymust  # optional: only the reference needs pymust
    from threadpoolctl import threadpool_limits

    a = PR.paper_probe().array
    probe = probe_config()
    spec = SWEEPS[sweep]
    T = sweep_poses(spec)
    centre = true_centre(T)
    info = load_stored(surface)["meta"]["per_sweep"][sweep]
    points, normals = sphere_surface(a)
    p_mid, w_cap = cap_in_frame(points, normals, T[FRAMES // 2])
    rc = w_cap * PLA_REFLECTION * _surface_weights(len(points), wavelength_m(a))
    if surface == "diffuse":
        p_d, amp_d = facing_in_frame(diffuse_scatterers(a), T[FRAMES // 2])
        p_mid = np.concatenate([p_mid, p_d])
        rc = np.concatenate([rc * np.sqrt(1.0 - DIFFUSE_SHARE**2), amp_d * info["diffuse_scale"]])
    p, w = elevation_slab(p_mid - [0.0, 0.0, (frame - FRAMES // 2) * FRAME_STEP_M], rc)
    crop = crop_of(probe, centre)
    H, W = probe.image_shape
    x, y = pixel_axes(crop.rows, crop.cols, W, probe.spacing_m)
    shown = 1.0 / axial_scale(probe)
    focus = cap_depth(centre)  # true
    out = np.zeros((H, W))
    lines = np.arange(0, len(crop.cols), 2)
    with threadpool_limits(1):
        for j in lines:
            xl = float(x[j])
            s = scanner(a, xl)
            near = np.abs(p[:, 0] - xl) <= 2e-3
            if not near.any():
                continue
            apod = PR.aperture(a, focus, s.fnumber)
            delays = np.asarray(
                pymust.txdelay(xl - s.x_aperture, focus * shown, s.scan), float
            ).reshape(1, -1)
            delays[0, apod == 0] = np.nan  # off: no transmit
            delays[0] -= np.nanmin(delays)
            X = np.full(len(crop.rows), xl - s.x_aperture)
            tx = transmit(s, 0.0, p[near], X, y, delays)
            env = np.abs(np.asarray(beamformed(s, tx, p[near], w[near]))).ravel()
            out[crop.rows, crop.cols[j]] = env
    cols = crop.cols[lines]
    for r in crop.rows:
        out[r, crop.cols] = np.interp(crop.cols, cols, out[r, cols])
    return out


def print_focused(surface: str, sweep: int, frame: int) -> None:
    """The lit pixels of one frame, plane waves (stored), focused (pymust, now) and
    sim_us: within 20, 30 and 40 dB of each frame's own peak, and above the display."""
    data = load_stored(surface)
    t0 = time.perf_counter()
    env = focused_frame(surface, sweep, frame)
    seconds = time.perf_counter() - t0
    plane = data["frames"][sweep, frame].astype(float)
    twin = twin_frames(data["T_base_ee"][sweep : sweep + 1], surface)[0, frame].astype(float)
    dr = probe_config().dynamic_range_db
    db = 20.0 * np.log10(np.maximum(env / env.max(), 1e-30))
    focused = np.clip(plane.max() + db * 255.0 / dr, 0.0, 255.0)  # its peak at the stored
    print(
        f"\n{surface} sphere, sweep {sweep} frame {frame}: pixels within 20 / 30 / 40 dB of "
        f"the frame's peak, and lit (focused: {seconds:.0f} s)"
    )
    for name, g in (("plane waves", plane), ("focused", focused), ("sim_us", twin)):
        within = [int((g >= g.max() - v * 255.0 / dr).sum()) for v in (20, 30, 40)]
        lit = int((g > 0).sum())
        print(f"  {name:>11}: {within[0]:5d} {within[1]:5d} {within[2]:5d}  {lit:5d}")


def check(surface: str) -> tuple[float, int]:
    """The localizer on a surface's stored frames and on sim_us's: the table, and (the
    worst error ratio, the wrong centres)."""
    t_start = time.perf_counter()
    data = load_stored(surface)
    meta = data["meta"]
    t0 = time.perf_counter()
    twin = twin_frames(data["T_base_ee"], surface)
    t_twin = time.perf_counter() - t0
    results: dict[str, dict[str, list]] = {"ref": {}, "twin": {}}
    t0 = time.perf_counter()
    for side, frames in (("ref", data["frames"]), ("twin", twin)):
        sweeps = sweeps_of(frames, data)
        for method in METHODS:
            results[side][method] = localize(sweeps, data, method)
    t_loc = time.perf_counter() - t0
    print(f"\n== {surface} sphere ==")
    worst, wrong = print_table(data, results)
    if surface == "diffuse":  # the smooth sphere has no speckle: one realization
        worst = print_spread(data)
    render_s = sum(p["seconds"] for p in meta["per_sweep"])
    print(
        f"reference read from {stored_path(surface).relative_to(ROOT)} (pymust "
        f"{meta['pymust_version']}, rendered in {render_s:.0f} s); sim_us {t_twin:.1f} s, "
        f"localizer {t_loc:.1f} s, total {time.perf_counter() - t_start:.0f} s"
    )
    return worst, wrong


def main() -> None:
    parser = argparse.ArgumentParser(
        description="the sphere localizer on pymust-rendered sweeps, next to sim_us's",
        epilog="Details: the module docstring.",
    )
    parser.add_argument(
        "--write",
        nargs="?",
        const="smooth",
        choices=SURFACES,
        help="render a surface's sweeps with pymust (default: smooth) and store them",
    )
    parser.add_argument(
        "--write-zero-db",
        action="store_true",
        help="show stored frames rendered with the cap's depth as 0 dB with the elevation "
        "focus's instead (pymust, ≈ 5 min once)",
    )
    parser.add_argument(
        "--write-psf",
        action="store_true",
        help="compute a point's PSF in water with pymust (≈ 1 min) and store it",
    )
    parser.add_argument(
        "--realization",
        type=int,
        default=0,
        metavar="K",
        help=f"with --write diffuse: the realization of its scatterers to render (0 to "
        f"{MAX_REALIZATIONS - 1}; 0, the first, is the default)",
    )
    parser.add_argument(
        "--focused-frame",
        nargs=3,
        metavar=("SURFACE", "SWEEP", "FRAME"),
        help="image one stored frame as a focused scanner does (pymust, ≈ 5 min) and "
        "compare its lit pixels with the plane waves' and sim_us's",
    )
    args = parser.parse_args()
    if args.write_zero_db:
        write_zero_db()
        return
    if args.focused_frame:
        surface, sweep, frame = args.focused_frame
        if surface not in SURFACES:
            parser.error(f"--focused-frame: SURFACE must be one of {', '.join(SURFACES)}")
        print_focused(surface, int(sweep), int(frame))
        return
    if not 0 <= args.realization < MAX_REALIZATIONS or (
        args.realization and args.write != "diffuse"
    ):
        parser.error(
            f"--realization {args.realization}: 0 to {MAX_REALIZATIONS - 1}, and only with "
            "--write diffuse (the smooth sphere has no random scatterers)"
        )
    if args.write:
        frames, infos = render_reference(args.write, realization=args.realization)
        write_stored(frames, infos, args.write, args.realization)
        path = stored_path(args.write, args.realization)
        print(f"wrote {path.relative_to(ROOT)} ({path.stat().st_size / 1e6:.2f} MB)")
    if args.write_psf:
        write_water_psf()
        print(f"wrote {WATER_PSF_STORED.relative_to(ROOT)}")
    if WATER_PSF_STORED.exists():
        print(f"largest PSF level difference down to -20 dB: {print_water_psf():.1f} dB")
    worst, wrong = float("nan"), 0
    for surface in SURFACES:
        if not stored_path(surface).exists():
            print(f"\n== {surface} sphere: not stored (run with --write {surface}) ==")
            continue
        w, n = check(surface)
        worst = w if not np.isfinite(worst) else max(worst, w) if np.isfinite(w) else worst
        wrong += n
    print(f"worst_error_ratio={worst:.2f} wrong_centres={wrong}")


if __name__ == "__main__":
    main()
