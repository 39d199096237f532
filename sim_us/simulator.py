"""The B-mode simulator: probe poses + acoustic scene → frames.

For each frame one ray per scanline (one scanline per image column) is cast along the
axial direction in each elevation sub-plane; the echoes are weighted by the elevation
beam profile at their depth and summed incoherently over the sub-planes (partial
volume), splatted at their apparent depth (deeper beside the image plane by the lensed
aperture's longer paths: :func:`sim_us.transducer.elevation_delay`) — spread over the
depth interval the surface covers across each sub-plane's slab of elevation (continuous
elevation integration) —
and blurred with the PSF (with its side lobes and the transducer's ring-down when
configured). The scanner may draw at a geometry other than the one its frames report
(pixel scale error, image origin and centre off the transducer face), and the medium
may be rendered at another true temperature than the configured one. Backscatter speckle
of a scattering medium is summed *coherently* over the elevation beam (scatterers at
different elevations add as waves in one A-line, which keeps fully developed Rayleigh
statistics) and blurred with the complex PSF. The display chain adds noise, gain, TGC
and log compression. Pure function of (scene, poses, config, rng); ground truth stays
with the caller.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba
import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.image import pixel_to_us, us_to_pixel

from .beam import (
    FWHM_PER_SIGMA,
    axial_fwhm_m,
    band_attenuation_db,
    beam_of,
    elevation_amplitude_at,
    elevation_delay_at,
    elevation_offsets,
    elevation_weights,
    flat_echo_gain,
    lateral_amplitude,
    mirror_of,
    narrowest_lateral_fwhm_m,
    scanline_step,
    slab_edge_shares,
    slice_thickness,
    speckle_cell_gain,
)
from .display import NoiseSource, gain_profile_db, to_bmode
from .materials import (
    MATERIALS,
    Material,
    amplitude_reflection,
    medium_material,
)
from .probe import MediumConfig, ProbeConfig
from .propagation import Echoes, trace
from .raycast import AcousticScene, RayCaster
from .speckle import ScattererField, _smooth_values
from .transducer import MirrorTables, band_loss, transducer
from .wires import wire_echoes

__all__ = ["BmodeSimulator", "Timings"]

Array = NDArray[np.float64]

# Noise sources kept for the generators last drawn from (BmodeSimulator._noise_of).
_NOISE_SOURCES_KEPT = 8
# Rays whose echoes would fall this far below the display floor are not traced further.
_TRACE_MARGIN_DB = 3.0
# Speckle sums scatterers within ± this many half slice thicknesses in elevation.
_SPECKLE_COVERAGE = 1.5
# ... on lattice lines at least this many to a slice thickness (every line of the fine
# lattice where the slice is thinnest, every 2nd, 4th, ... where it is thicker).
_SPECKLE_LINES_PER_SLICE = 3.0
# The speckle's lateral PSF is cut where it stays below this (−40 dB: its tail holds
# < 0.1 % of the speckle's energy).
_SPECKLE_KERNEL_FLOOR = 1e-2
# PSF kernels are truncated at this many σ.
_TRUNCATE = 3.0
# Continuous elevation integration: a surface steeper than this in elevation (depth change
# per elevational shift, ≈ 63°) is taken at this slope: the tangent plane stops being a
# good model near a sphere's silhouette (it would carry the echo past the sphere's
# equator), and that steep only the weak diffuse echo remains (specular share < 1e-7).
_MAX_ELEVATION_SLOPE = 2.0
# The elevation lobe is integrated over each sub-plane's slab at this many points.
_SLAB_SAMPLES = 8
# Below this half-span (pixels) a hit is splatted as a point, as in the discrete model.
_MIN_SMEAR_PX = 0.05
# Surface speckle: at most this many scatterers stand for one hit's elevation slab.
_MAX_SLAB_SCATTERERS = 64
# The surfaces' scatterer field is the medium's key mixed with this (independent fields).
_SURFACE_FIELD_KEY = 0x5EC7ACE
# The ring-down tail is followed down to this level below the echo (intensity, dB).
_RING_DOWN_FLOOR_DB = 80.0


@dataclass
class Timings:
    """Seconds spent per stage since construction (for the benchmark)."""

    raycast: float = 0.0
    formation: float = 0.0
    display: float = 0.0
    frames: int = 0


class BmodeSimulator:
    """Renders B-mode frames of an acoustic scene at probe poses.

    Parameters
    ----------
    scene : AcousticScene
        Solid parts (meshes in the scene frame) with material names from
        :data:`~sim_us.materials.MATERIALS`.
    probe : ProbeConfig
    medium : MediumConfig
        The medium the probe and the parts sit in.
    speckle_key : int
        Key of the medium's scatterer field (fixed per scene: same pose, same speckle).
    """

    def __init__(
        self,
        scene: AcousticScene,
        probe: ProbeConfig,
        medium: MediumConfig,
        speckle_key: int = 0,
    ) -> None:
        self.probe = probe
        self.medium_config = medium
        self.medium = medium_material(medium.kind, medium.temperature_c)
        self.part_materials = [
            p.material if isinstance(p.material, Material) else MATERIALS[p.material]
            for p in scene.parts
        ]
        self.caster = RayCaster(scene)
        self.wires = scene.wires
        # Scatterer cells of a third of the finer resolution: ≥ 10 per PSF cell.
        cell = min(axial_fwhm_m(probe), narrowest_lateral_fwhm_m(probe)) / 3.0
        self.scatterers = ScattererField(cell, int(speckle_key))
        self._surface_speckle = probe.surface_speckle
        self.surface_scatterers = ScattererField(cell, int(speckle_key) ^ _SURFACE_FIELD_KEY)
        self.timings = Timings()
        # The noise source of each generator the frames' noise is drawn from (by identity;
        # the generator kept beside it so that its id is not reused).
        self._noises: dict[int, tuple[np.random.Generator, NoiseSource]] = {}

        self.shape = probe.image_shape
        H, W = self.shape
        # What the frames report (the scanner's nominal spacing) ...
        self.spacing = probe.spacing_m
        # ... and where the scanner really draws (scale error, image origin and centre off
        # the transducer face, in the face frame): pixel (r, c) shows the point
        # pixel_to_us(r, c, W, true_spacing) + offset. Each is exact (/ 1.0, + 0.0) when off.
        # A scale error e is a caliper error: reported distances e % too long.
        ex, ey = probe.pixel_scale_error_pct
        self.true_spacing = (
            self.spacing[0] / (1.0 + ex / 100.0),
            self.spacing[1] / (1.0 + ey / 100.0),
        )
        self.offset = (probe.lateral_offset_mm * 1e-3, probe.image_origin_offset_mm * 1e-3)
        sy = self.true_spacing[1]
        self.max_depth = self.offset[1] + (H - 1) * sy  # apparent depth below the face
        self.z, dz = elevation_offsets(probe, self.max_depth)
        # The face-frame point each pixel shows, through the one pixel ↔ image mapping.
        self._pixel_y = self.offset[1] + pixel_to_us(np.arange(H), 0, W, self.true_spacing)[:, 1]
        self._dz = dz
        # Continuous elevation: the slab each sub-plane stands for (none with one plane).
        self._smear = probe.continuous_elevation and len(self.z) > 1
        self._slab = dz if len(self.z) > 1 else np.zeros(1)
        # Scanlines on the nearest columns to an even spacing; each stands for the columns
        # nearest to it (its weight) and the lateral PSF (σ ≳ spacing) fills them in.
        # (The simulator's own sampling choice: on the reported pixel grid.)
        step = scanline_step(probe, self.spacing[0])
        self.columns = np.unique(np.rint(np.arange(0.0, W - 1 + 1e-9, step)).astype(np.int64))
        mids = (self.columns[1:] + self.columns[:-1]) / 2
        bounds = np.concatenate([[-0.5], mids, [W - 0.5]])
        self.line_width = np.diff(bounds)
        self._line_of_column = np.searchsorted(mids, np.arange(W))
        # Scanline origins in the image frame: (K planes, scanlines, 3).
        x = pixel_to_us(0, self.columns, W, self.true_spacing)[:, 0] + self.offset[0]
        self._origins_us = np.stack(
            np.broadcast_arrays(x[None, :], 0.0, self.z[:, None]), axis=-1
        ).astype(float)
        self._scanline_step = step
        self._beam_speed: float | None = None
        self._use_beam(self.medium)
        # Path loss past which no echo can reach the display floor at any row's gain: the
        # strongest interface of the scene reflects r_max, so a path weaker than
        # floor / r_max cannot show.
        self.floor_db = self._floor_db(self.medium)

    def _use_beam(self, medium: Material) -> None:
        """The beam in ``medium``: the scanner focuses for the speed it assumes, so where
        sound travels at another (water: 1482 m/s at 20 °C against 1540) its beam is out of
        focus (:mod:`sim_us.transducer`). Sets what depends on it: the mirror's echo, the
        sub-planes' weights and slab shares, the PSF kernels; kept while the medium's speed
        rounds to the same transducer (5 m/s). The sampling (scatterer cells, sub-planes,
        scanlines) follows the scanner's own beam, whatever the medium."""
        key = transducer(self.probe, medium.speed_m_s).medium_speed_m_s
        if self._beam_speed is not None and key == self._beam_key:
            return
        probe, c = self.probe, medium.speed_m_s
        self._beam_speed, self._beam_key = c, key
        sx, sy = self.true_spacing
        rows_y, dz = self._pixel_y, self._dz
        self._mirror: MirrorTables | None = None  # made when a surface is first drawn
        # A flat reflector's echo against depth (intensity per row, re the elevation
        # focus): every echo drawn at a depth carries it (sim_us.transducer.flat_echo).
        self._flat_rows = (flat_echo_gain(probe, rows_y, c) ** 2).astype(np.float32)
        self.weights = elevation_weights(probe, rows_y, self.z, dz, c).astype(np.float32)  # (K, H)
        # The beam profile's share at each slab's low-z edge, per row.
        self._edge_share = slab_edge_shares(probe, rows_y, self.z, dz, c)
        sigma_ax = axial_fwhm_m(probe) / FWHM_PER_SIGMA / sy  # amplitude PSF σ, rows
        # Lateral amplitude PSF per row (the beam changes with depth), peak 1.
        lateral = lateral_amplitude(probe, rows_y, sx, medium_speed_m_s=c)
        # Intensity PSF kernels of the surface echoes (correlation taps along rows; along
        # columns one set per row): |h|², unit sum, with the ring-down tail when configured.
        intensity = _between_scanlines(lateral**2, self._scanline_step)
        intensity /= intensity.sum(axis=1, keepdims=True)
        self._kernels = (
            _ring_down_kernel(sigma_ax / np.sqrt(2), probe, sy),
            np.ascontiguousarray(intensity, dtype=np.float32),
        )
        self._amplitude_kernels = tuple(np.sqrt(k) for k in self._kernels)
        # The medium's speckle through the amplitude PSF h, unit sum per axis; white
        # scatterers keep unit mean intensity with the norm 1 / (Σ h_ax² · Σ h_lat²) per row.
        k_ax = _gaussian_kernel(sigma_ax)
        k_lat = lateral_amplitude(
            probe, rows_y, sx, floor=_SPECKLE_KERNEL_FLOOR, medium_speed_m_s=c
        )
        k_lat /= k_lat.sum(axis=1, keepdims=True)
        self._speckle_kernels = (k_ax, np.ascontiguousarray(k_lat, dtype=np.float32))
        self._speckle_norm = (
            1.0 / (np.sum(k_ax.astype(float) ** 2) * np.sum(k_lat**2, axis=1))
        ).astype(np.float32)

    @property
    def mirror(self) -> MirrorTables:
        """The echo of a surface element through the apertures in the beam's medium
        (:func:`sim_us.beam.mirror_of`), made when the first surface is drawn: a scene
        of wires alone never needs it (its tables cost as much as the beam's)."""
        if self._mirror is None:
            self._mirror = mirror_of(self.probe, self._beam_speed)
        return self._mirror

    @property
    def T_face_image(self) -> Array:
        """(4, 4): the frame the pixels are really drawn in (``calib.image`` mapping with the
        true spacing) in the transducer-face frame: the image origin and centre offsets.
        A calibration absorbs them (it finds the pixels' frame); compared with the face
        frame they show as a translation of ``T_ee_us``. Identity when they are off."""
        return se3.make(np.eye(3), [self.offset[0], self.offset[1], 0.0])

    def _floor_db(self, medium: Material) -> float:
        """Trace budget (dB) with this medium around the parts."""
        max_gain = float(np.max(gain_profile_db(self.probe, self.shape[0])))
        # Past the elevation focus a flat reflector may echo stronger than at it (the
        # lateral aperture still growing): the trace keeps what that could show.
        strongest = float(np.max(beam_of(self.probe, medium.speed_m_s).flat_echo))
        flat_db = 20 * np.log10(max(strongest, 1.0))
        # Every pair of the medium and the parts' materials at once (a loop over the pairs
        # of a 20-part scene cost ≈ 0.7 ms a frame when the water's temperature drifts).
        imped = np.array([m.impedance for m in [medium, *self.part_materials]])
        r_max = float(np.max(amplitude_reflection(imped[:, None], imped[None, :])))
        return (
            self.probe.dynamic_range_db
            + max(max_gain, 0.0)
            + 20 * np.log10(max(r_max, 1e-6))
            + flat_db
            + _TRACE_MARGIN_DB
        )

    def _medium_at(self, temperature_c: float | None) -> tuple[Material, float]:
        """The medium and the trace budget at a true medium temperature (None: the
        configured one). The medium's material changes, and the beam with its speed where
        that rounds to another transducer (:meth:`_use_beam`, tables cached); the Embree
        scene and the scanlines are kept."""
        if temperature_c is None or temperature_c == self.medium_config.temperature_c:
            medium, floor_db = self.medium, self.floor_db
        else:
            medium = medium_material(self.medium_config.kind, float(temperature_c))
            floor_db = self._floor_db(medium)
        self._use_beam(medium)
        return medium, floor_db

    # ------------------------------------------------------------------ echoes

    def _rays(self, T_scene_us: Array) -> tuple[Array, Array, int]:
        """Ray origins and directions (n·K·L, 3) in the scene frame: frame-major, then
        sub-plane, then scanline; each ray runs along its frame's axial (y) axis."""
        n = len(T_scene_us)
        P_us = self._origins_us.reshape(-1, 3)
        # Batched matmul: (n, K·L, 3) = P_us · Rᵀ + t (einsum broadcasting is ~10× slower).
        origins = P_us[None] @ np.swapaxes(T_scene_us[:, :3, :3], 1, 2) + T_scene_us[:, None, :3, 3]
        dirs = np.repeat(T_scene_us[:, :3, 1], len(P_us), axis=0)
        return origins.reshape(-1, 3), dirs, n

    def _echo_intensity(
        self, T_scene_us: Array, medium: Material, floor_db: float
    ) -> tuple[NDArray[np.float32], NDArray[np.complex64] | None, Array]:
        """Surface echoes (n, H, W) before the PSF: the intensity of their coherent share
        and, with surface speckle, the complex amplitude of their incoherent share (None
        without); and each ray's medium end."""
        H, W = self.shape
        K = len(self.z)
        L = len(self.columns)
        origins, dirs, n = self._rays(T_scene_us)
        t0 = time.perf_counter()
        echoes = trace(
            self.caster,
            self.part_materials,
            medium,
            origins,
            dirs,
            self.max_depth,
            self.probe.f_mhz,
            self.probe.assumed_speed_m_s,
            floor_db,
            self.mirror,
            (
                np.repeat(T_scene_us[:, :3, 0], K * L, axis=0),
                np.repeat(T_scene_us[:, :3, 2], K * L, axis=0),
            ),
            self.probe.reverberation,
            slopes=self._smear,
            points=self._surface_speckle,
            band=band_loss(transducer(self.probe), medium.attenuation_power),
        )
        t1 = time.perf_counter()
        self.timings.raycast += t1 - t0
        frame, rem = np.divmod(echoes.ray, K * L)
        plane, line = np.divmod(rem, L)
        col = self.columns[line]
        P_image = np.zeros((len(echoes.depth), 3))
        P_image[:, 1] = echoes.depth - self.offset[1]
        row_f = us_to_pixel(P_image, W, self.true_spacing)[0]
        amplitude, coherent = echoes.amplitude, echoes.coherent
        assert coherent is not None
        shift, span = np.zeros(len(amplitude)), self._slab[plane].astype(float)
        if len(self.z) > 1:
            coherent, amplitude, shift, span = self._elevation_lobe_integrated(
                echoes, frame, plane, line, n
            )
        # Where the mirror's echo dominates what is drawn smooth, it is drawn from where
        # in the slab it comes from (all of it with surface speckle: the rest is speckle).
        mirror_like = (coherent**2 >= 0.5 * amplitude**2) | self._surface_speckle
        sy = self.true_spacing[1]
        if len(self.z) > 1:
            # Beside the image plane an echo is drawn deeper than its depth: the lens's
            # paths to it are longer (sim_us.transducer.elevation_delay). Each echo at its
            # sub-plane's offset; the mirror's at the elevation in the slab it comes from.
            z_plane = self.z[plane]
            late = elevation_delay_at(self.probe, echoes.depth, z_plane, self._beam_speed)
            late_smooth = late.copy()
            moved = mirror_like & (shift != 0.0)
            if moved.any():
                late_smooth[moved] = elevation_delay_at(
                    self.probe, echoes.depth[moved], z_plane[moved] + shift[moved], self._beam_speed
                )
            row_smooth = row_f + late_smooth / sy
            row_f = row_f + late / sy
        else:
            row_smooth = row_f
        if self._smear:
            assert echoes.slope is not None
            slope = np.clip(echoes.slope, -_MAX_ELEVATION_SLOPE, _MAX_ELEVATION_SLOPE)
            row_smooth = row_smooth + np.where(mirror_like, slope * shift, 0.0) / sy
            span = np.where(mirror_like, span, self._slab[plane])
        speckled = None
        if self._surface_speckle:
            # The coherent share is drawn as a smooth echo, the rest as surface speckle.
            assert echoes.point is not None
            incoherent = np.sqrt(np.maximum(amplitude**2 - coherent**2, 0.0))
            amplitude = coherent
            speckled = self._speckle_of_surfaces(
                T_scene_us, frame, plane, line, row_f, incoherent, echoes.point, echoes.slope
            )
        row_f = row_smooth
        half = None
        if self._smear:
            # Half the depth span (rows) of each hit's echo along its tangent plane.
            assert echoes.slope is not None
            slope = np.clip(echoes.slope, -_MAX_ELEVATION_SLOPE, _MAX_ELEVATION_SLOPE)
            half = 0.5 * np.abs(slope) * span / self.true_spacing[1]
        wide = half > _MIN_SMEAR_PX if half is not None else np.zeros(len(row_f), dtype=bool)
        slabs = None
        if wide.any():
            assert echoes.slope is not None and half is not None
            slabs = self._slab_segments(
                frame[wide],
                plane[wide],
                line[wide],
                row_f[wide],
                half[wide],
                echoes.slope[wide] >= 0,
                amplitude[wide] ** 2,
                np.where(mirror_like[wide] & echoes.first[wide], 0.5, np.nan),
            )
        narrow = ~wide
        frame, plane, line, col, row_f = (v[narrow] for v in (frame, plane, line, col, row_f))
        inside = (row_f > -1) & (row_f < H)
        frame, plane, line, col, row_f = (v[inside] for v in (frame, plane, line, col, row_f))
        row_idx = np.clip(np.rint(row_f).astype(np.int64), 0, H - 1)
        inten = (
            self.line_width[line] * amplitude[narrow][inside] ** 2 * self.weights[plane, row_idx]
        )
        image = np.zeros(n * H * W, dtype=np.float32)
        _splat_points(image, H, W, frame, col, row_f, inten.astype(np.float32))
        if slabs is not None:
            _splat_segments(image, H, W, *slabs)
        self.timings.formation += time.perf_counter() - t1
        medium_end = echoes.medium_end.reshape(n, K, L)[:, :, self._line_of_column]
        return image.reshape(n, H, W), speckled, medium_end

    def _elevation_lobe_integrated(
        self,
        echoes: Echoes,
        frame: NDArray[np.int64],
        plane: NDArray[np.int64],
        line: NDArray[np.int64],
        n: int,
    ) -> tuple[Array, Array, Array, Array]:
        """The echoes' coherent share and amplitude with the mirror's elevation lobe
        integrated over each sub-plane's slab, and where in the slab the coherent echo
        comes from (its offset from the sub-plane and its width, m).

        One ray per sub-plane reads one tilt; a curved surface turns across the slab (a
        sphere's top faces the probe at one elevation only), and the mirror's elevation
        lobe is sharp (−13 dB at 5° for the paper probe at 20 mm), so the tilt at the ray
        alone would miss a specular point between two sub-planes. Across the slab the tilt
        is taken linear between the ray's and its neighbour sub-planes' (same frame and
        scanline, first surface, depths within the tangent plane's reach), and the
        coherent share carries ∫ b² E(φ(z))² dz over the slab (b the beam's two-way
        elevation amplitude), where the sub-plane's weight holds b² at its own elevation
        times the slab's width: on a flank of the beam b² changes by orders of magnitude
        across a slab. The incoherent share is kept.
        The mirror's echo comes from near the specular point, not from the whole slab:
        its depth is that of the tangent plane at the b² E²-weighted mean elevation, its
        depth span that of the weighted spread.
        """
        assert echoes.tilt is not None and echoes.first is not None
        assert echoes.coherent is not None and echoes.coherent_lateral is not None
        coherent, amplitude = echoes.coherent.copy(), echoes.amplitude.copy()
        first = np.flatnonzero(echoes.first)
        if not len(first):
            return coherent, amplitude, np.zeros(len(amplitude)), self._slab[plane].astype(float)
        K, L = len(self.z), len(self.columns)
        f, k, ln = frame[first], plane[first], line[first]
        phi, depth = echoes.tilt[first], echoes.depth[first]
        tilts = np.full((n, K, L), np.nan)
        depths = np.full((n, K, L), np.nan)
        tilts[f, k, ln], depths[f, k, ln] = phi, depth
        z0, dz = self.z[k], self._slab[k]
        u = (np.arange(_SLAB_SAMPLES) + 0.5) / _SLAB_SAMPLES - 0.5
        zs = z0[:, None] + dz[:, None] * u[None, :]
        # b² across the slab and at the sub-plane itself, whose weight holds b² at its own
        # elevation times the slab's width.
        b2 = (
            elevation_amplitude_at(self.probe, depth, np.column_stack([zs, z0]), self._beam_speed)
            ** 2
        )
        centre = b2[:, -1] * _SLAB_SAMPLES
        i0, i1, wd = self.mirror.depth_nodes(depth)
        wsum, mean, spread = _slab_lobe_moments(
            tilts,
            depths,
            f,
            k,
            ln,
            self.z,
            zs,
            b2[:, :-1],
            self.mirror.elevation,
            i0,
            i1,
            wd,
            1.0 / self.mirror.tilt_step,
            _MAX_ELEVATION_SLOPE,
        )
        ok = wsum > 0
        shift, span = np.zeros(len(amplitude)), self._slab[plane].astype(float).copy()
        shift[first] = np.where(ok, mean, 0.0)
        span[first] = np.where(ok, np.minimum(np.sqrt(12.0) * spread, dz), dz)
        e_eff = np.sqrt(np.divide(wsum, centre, out=np.zeros_like(centre), where=centre > 0))
        incoherent2 = np.maximum(amplitude[first] ** 2 - coherent[first] ** 2, 0.0)
        coherent[first] = echoes.coherent_lateral[first] * e_eff
        amplitude[first] = np.sqrt(coherent[first] ** 2 + incoherent2)
        return coherent, amplitude, shift, span

    def _shallow_share(
        self, plane: NDArray[np.int64], row_idx: NDArray[np.int64], rising: NDArray[np.bool_]
    ) -> Array:
        """Share of a slab's beam-profile density at the shallow end of its echo's depth
        interval: the slab's low-z edge where the surface deepens with z (``rising``), its
        high-z edge where it rises."""
        share = self._edge_share[plane, row_idx]
        return np.where(rising, share, 1.0 - share)

    def _slab_half_rows(self, plane: NDArray[np.int64], slope: Array) -> Array:
        """Half the depth span (rows) of each hit's elevation slab along its tangent plane."""
        slope = np.clip(slope, -_MAX_ELEVATION_SLOPE, _MAX_ELEVATION_SLOPE)
        return 0.5 * np.abs(slope) * self._slab[plane] / self.true_spacing[1]

    def _speckle_of_surfaces(
        self,
        T_scene_us: Array,
        frame: NDArray[np.int64],
        plane: NDArray[np.int64],
        line: NDArray[np.int64],
        row_f: Array,
        incoherent: Array,
        point: Array,
        slope: Array | None,
    ) -> NDArray[np.complex64]:
        """Complex amplitude (n, H, W), before the PSF, of the surfaces' incoherent echoes.

        The incoherent share of a surface echo is the sum of wavelets from the surface's
        sub-resolution facets with random phases (the texture's and the material's diffuse
        return): a circular complex Gaussian amplitude, so after the PSF it is speckle
        with Rayleigh statistics, like a scattering medium's, but lying on the surface
        (Goodman, *Speckle Phenomena in Optics*, ch. 2; Ogilvy 1991, ch. 4). Each hit is
        such a scatterer, its amplitude taken from a field fixed to the scene at the hit
        point (the same surface seen again gives the same speckle), its rms the echo's
        incoherent amplitude; hits add as waves across scanlines and elevation sub-planes,
        and the PSF's amplitude blurs them. Where the smooth model spreads a hit over its
        slab's depth interval (continuous elevation), the slab is a row of such scatterers
        along its elevation, one per half pixel of depth. Their mean intensity is exactly
        the incoherent echo's of the smooth model; what changes is that a surface the beam
        meets obliquely (no specular return) draws a granular, broken line whose brightest
        pixel wanders across the echo's thickness, as on a real scanner.
        """
        H, W = self.shape
        n = len(T_scene_us)
        row_idx = np.clip(np.rint(row_f).astype(np.int64), 0, H - 1)
        energy = self.line_width[line] * incoherent**2 * self.weights[plane, row_idx]
        keep = (energy > 0) & (row_f > -1) & (row_f < H)
        frame, plane, line, row_f, energy, point = (
            v[keep] for v in (frame, plane, line, row_f, energy, point)
        )
        row_idx = row_idx[keep]
        if slope is not None:
            slope = slope[keep]
            half = self._slab_half_rows(plane, slope)
        else:
            half = np.zeros(len(row_f))
        if slope is not None:
            p = self._shallow_share(plane, row_idx, slope >= 0)
            sign = np.where(slope >= 0, 1.0, -1.0)
        else:
            p = np.full(len(row_f), 0.5)
            sign = np.ones(len(row_f))
        out = np.zeros(n * H * W, dtype=np.complex64)
        field = self.surface_scatterers
        _splat_surface_speckle(
            out,
            H,
            W,
            frame,
            self.columns[line],
            row_f,
            half,
            p,
            sign,
            self._slab[plane],
            energy,
            np.ascontiguousarray(point, dtype=np.float64),
            np.ascontiguousarray(T_scene_us[:, :3, 2], dtype=np.float64),
            field.table,
            field.key,
            field.cell_m,
        )
        return out.reshape(n, H, W)

    def _slab_segments(
        self,
        frame: NDArray[np.int64],
        plane: NDArray[np.int64],
        line: NDArray[np.int64],
        row_f: Array,
        half: Array,
        rising: NDArray[np.bool_],
        amplitude2: Array,
        share: Array | None = None,
    ) -> tuple[NDArray[np.int64], Array, Array, Array, Array]:
        """Continuous elevation integration of the hits whose slab spans a depth interval:
        the segments to splat (see :func:`_splat_segments`).

        Sub-plane k samples the beam at z_k and stands for the slab z_k ± dz_k / 2. Across
        the slab the surface is its tangent plane at the hit, so the echo's depth moves
        linearly with z, over ``row_f ± half`` rows, and the energy that reaches each depth
        is the beam's two-way intensity profile there: b²(z), taken linear between the
        slab's edges (piecewise-linear integration over elevation). The slab's energy is
        the discrete model's (line width × amplitude² × the plane's weight), so the total
        is unchanged; it is spread over the interval with that trapezoidal density and
        splatted into rows with the same linear (tent) interpolation as a point echo —
        exactly, by integrating the density against the tent in closed form. Adjacent
        slabs tile the depth range, so a surface sloping across a thick slice gives one
        thickened echo (partial volume), not an arc per sub-plane. (The slab energies
        follow the midpoint rule and the shape the edge values, so the density can step
        a little where two slabs meet; the trapezoid rule would remove the step but move
        the energy of the coarse outer slabs by up to 4×.)

        An analytic Gaussian smear along depth (σ = slope × the beam's σ) would be the
        alternative; it ignores that the slice is not centred on a curved surface's
        nearest point and smears both ways past the sphere's top, so it was not taken.
        """
        H, W = self.shape
        row_idx = np.clip(np.rint(row_f).astype(np.int64), 0, H - 1)
        energy = self.line_width[line] * amplitude2 * self.weights[plane, row_idx]
        a, b = row_f - half, row_f + half
        keep = (b > -1) & (a < H)
        frame, plane, line, a, b, energy = (v[keep] for v in (frame, plane, line, a, b, energy))
        # Density (per row) at the shallow end a and the deep end b; it integrates to energy.
        p = self._shallow_share(plane, row_idx[keep], rising[keep])
        if share is not None:  # a stated share where given (NaN: the slab's own)
            p = np.where(np.isnan(share[keep]), p, share[keep])
        width = b - a
        rho_a = 2.0 * energy * p / width
        beta = 2.0 * energy * (1.0 - 2.0 * p) / width**2  # dρ/dy
        base = frame * (H * W) + self.columns[line]
        return base, a, b, rho_a, beta

    def _add_wire_echoes(
        self, image: NDArray[np.float32], T_scene_us: Array, medium: Material, medium_end: Array
    ) -> None:
        """The scene's wires (:mod:`sim_us.wires`) added to the surface echoes ``image``
        (n, H, W) before the PSF, in place. Each echo is scaled so that after the PSF its
        peak is its amplitude² times the sub-plane's beam weight, as a flat mirror's level
        is; it is hidden where its scanline has entered a solid before its depth."""
        H, W = self.shape
        probe = self.probe
        mirror = self.mirror
        echoes = wire_echoes(
            self.wires,
            T_scene_us,
            self.z,
            medium=medium,
            width_px=W,
            true_spacing=self.true_spacing,
            offset=self.offset,
            assumed_speed_m_s=probe.assumed_speed_m_s,
            f_mhz=probe.f_mhz,
            wavelength_m=mirror.wavelength_m,
            focal_spot_m=mirror.focal_spot_m,
            elevation_lobe=lambda depth, tilt: mirror.lobes(
                depth, np.zeros_like(depth), tilt, np.zeros_like(depth)
            )[1],
            loss_db=lambda depth: band_attenuation_db(probe, medium, depth),
            dynamic_range_db=probe.dynamic_range_db,
        )
        # No elevation delay (unlike a sphere's cap): a wire crossing the image plane is a
        # line along the elevation, whose echo, by the image method, comes from the point
        # of the wire midway between each transmitting and receiving point of the lens:
        # the paths depend on their separation alone, as a flat mirror's do.
        c0 = np.floor(echoes.col).astype(np.int64)
        keep = (c0 >= 0) & (c0 + 1 < W) & (echoes.row > -1) & (echoes.row < H - 1)
        f, k, c0, row, energy = (
            v[keep] for v in (echoes.frame, echoes.plane, c0, echoes.row, echoes.energy)
        )
        frac = echoes.col[keep] - c0
        row_idx = np.clip(np.rint(row).astype(np.int64), 0, H - 1)
        seen = (row * self.true_spacing[1] + self.offset[1]) <= medium_end[f, k, c0]
        peak = self._kernels[1].max(axis=1)  # the lateral intensity PSF's peak per row
        value = energy * self.weights[k, row_idx] / peak[row_idx] * seen
        flat = image.reshape(-1)
        for col, share in ((c0, 1.0 - frac), (c0 + 1, frac)):
            _splat_points(flat, H, W, f, col, row, (value * share).astype(np.float32))

    # ------------------------------------------------------------------ speckle

    def _speckle(
        self, T_scene_us: Array, medium_end: Array, medium: Material
    ) -> NDArray[np.complex64]:
        """Complex backscatter (n, H, W) of a scattering medium before the PSF.

        Each pixel sums, coherently, the scatterers of the cells its elevation beam crosses:
        the samples sit on the scene's cell lattice along the probe's elevational axis
        (not on the probe's sub-planes), weighted by the two-way elevation profile at
        their offset. Moving the probe in elevation therefore shifts the weights smoothly
        over the same scatterers, and frames decorrelate on the scale of the slice
        thickness. Two-way attenuation applies; nothing past the first solid a scanline
        enters.
        """
        H, W = self.shape
        n = len(T_scene_us)
        depth = self._pixel_y
        x = pixel_to_us(0, np.arange(W), W, self.true_spacing)[:, 0] + self.offset[0]
        assert medium.backscatter_db is not None
        level = 10.0 ** (medium.backscatter_db / 20.0)
        # Two-way attenuation of the broadband echo in the medium (apparent ≈ true depth in
        # a uniform medium); the speckle's level against a flat reflector's follows the
        # resolution cell (``backscatter_db`` holds at the elevation focus).
        loss_db = band_attenuation_db(self.probe, medium, depth)
        amp_row = (
            level
            * 10.0 ** (-loss_db / 20.0)
            * np.sqrt(speckle_cell_gain(self.probe, depth, self._beam_speed))
        )
        cell = self.scatterers.cell_m
        st = slice_thickness(self.probe, depth, self._beam_speed)
        reach = _SPECKLE_COVERAGE * st / 2  # elevation half-span summed at each depth (m)
        n_side = int(np.ceil(reach.max() / cell)) + 1
        # Each row sums every 2^m-th line of the lattice, m as large as keeps at least
        # _SPECKLE_LINES_PER_SLICE lines to its slice thickness (the two-way profile, a
        # Gaussian of σ ≈ 0.42 ST, sampled at most ≈ 0.8 σ apart): far past the focus
        # (ST ≈ 5 mm at 40 mm) a row sums ≈ 12 lines instead of ≈ 64. The lines kept are
        # lines of the same world-fixed lattice, so the field stays the scene's; the
        # statistics and the decorrelation with elevation stay those of the full lattice
        # (tests/test_sim_us.py).
        level = np.maximum(np.floor(np.log2(st / (_SPECKLE_LINES_PER_SLICE * cell))), 0)
        stride = (2**level).astype(np.int64)  # (H,)
        out = np.zeros((n, H, W), dtype=np.complex64)
        for f in range(n):
            R, t = T_scene_us[f, :3, :3], T_scene_us[f, :3, 3]
            rows = (depth[:, None] * R[:, 1] / cell).astype(np.float32)  # (H, 3) in cells
            cols = (x[:, None] * R[:, 0] / cell).astype(np.float32)  # (W, 3)
            s0 = float(t @ R[:, 2]) / cell  # probe plane on the elevational lattice
            # Every lattice line within reach of some row: its offset from the plane, its
            # index on the world-fixed lattice, its weight per row (0 where out of reach or
            # thinned out), its offset in cells and the sub-plane that knows the shadow.
            j = np.arange(-n_side, n_side + 1)
            z = (np.floor(s0) + j - s0) * cell
            line = int(np.floor(s0)) + j
            use = (np.abs(z)[:, None] <= reach[None, :]) & (line[:, None] % stride[None, :] == 0)
            keep = use.any(axis=1)
            z, use = z[keep], use[keep]
            b = np.exp(-4.0 * np.log(2.0) * z[:, None] ** 2 / st[None, :] ** 2)  # two-way
            weights = np.where(use, b, 0.0)
            norm = np.sum(weights**2, axis=0)
            if len(z):
                offsets = ((t[None, :] + z[:, None] * R[:, 2][None, :]) / cell).astype(np.float32)
                planes = np.argmin(np.abs(self.z[None, :] - z[:, None]), axis=1).astype(np.int64)
                self.scatterers.add_lattice_lines(
                    out[f],  # summed in place
                    rows,
                    cols,
                    offsets,
                    np.ascontiguousarray(weights),
                    depth,
                    np.ascontiguousarray(medium_end[f]),
                    planes,
                )
            # Unit mean intensity per row, then the medium's level and attenuation.
            gain = np.where(norm > 0, amp_row / np.sqrt(np.maximum(norm, 1e-30)), 0.0)
            out[f] *= gain.astype(np.float32)[:, None]
        return out

    # ------------------------------------------------------------------ public

    def intensity(
        self, T_scene_us: Array, temperature_c: float | None = None
    ) -> NDArray[np.float32]:
        """Envelope intensity (n, H, W) relative to a perfect reflector facing the probe at
        the elevation focus, noise-free (at other depths such a reflector echoes as the
        apertures give it: :func:`sim_us.transducer.flat_echo`).

        ``T_scene_us`` (n, 4, 4) or (4, 4): probe image-frame poses in the scene frame.
        ``temperature_c``: the medium's true temperature for these frames (speed of sound,
        attenuation); None takes the configured ``medium.temperature_c``.
        """
        T = np.asarray(T_scene_us, dtype=float).reshape(-1, 4, 4)
        medium, floor_db = self._medium_at(temperature_c)
        image, surface, medium_end = self._echo_intensity(T, medium, floor_db)
        if self.wires:
            self._add_wire_echoes(image, T, medium, medium_end)
        t0 = time.perf_counter()
        # The intensity PSF of an incoherent echo is |h|² (with the ring-down tail when
        # configured). The medium's speckle below goes through h without the ring-down:
        # the ring-down of fully developed speckle is more speckle.
        _blur_where_nonzero(image, *self._kernels)
        if surface is not None:
            # The surfaces' speckle through the amplitude PSF h = √(|h|²) of the same
            # kernels: one scatterer alone draws exactly the smooth model's echo.
            k_rows, k_cols = self._amplitude_kernels
            _add_blurred_surface_speckle(image, surface, k_rows, k_cols)
        if medium.backscatter_db is not None:
            sp = self._speckle(T, medium_end, medium)
            _add_blurred_intensity(image, sp, *self._speckle_kernels, self._speckle_norm)
        # Every echo at a depth as a flat reflector's there re the elevation focus: applied
        # per row once all are drawn (it varies over millimetres, the PSF over 0.1 mm).
        image *= self._flat_rows[None, :, None]
        self.timings.formation += time.perf_counter() - t0
        self.timings.frames += len(T)
        return image

    def envelope(
        self, T_scene_us: Array, temperature_c: float | None = None
    ) -> NDArray[np.float32]:
        """Noise-free envelope amplitude (n, H, W)."""
        return np.sqrt(self.intensity(T_scene_us, temperature_c))

    def render(
        self,
        T_scene_us: Array,
        rng: np.random.Generator | None,
        temperature_c: float | None = None,
    ) -> NDArray[np.uint8]:
        """B-mode frames (n, H, W) uint8 as a frame grabber delivers them.

        ``rng`` draws the electronic noise; None renders without it. ``temperature_c`` as
        in :meth:`intensity`.
        """
        return self.render_at_gains(T_scene_us, [self.probe.gain_db], [rng], temperature_c)[0]

    def render_at_gains(
        self,
        T_scene_us: Array,
        gains_db: Sequence[float],
        rngs: Sequence[np.random.Generator | None],
        temperature_c: float | None = None,
    ) -> list[NDArray[np.uint8]]:
        """The frames :meth:`render` gives at each overall gain of ``gains_db`` (dB), from
        one simulation of the echoes: the gain acts in the display chain alone (noise,
        gain, log compression), so a series of gains (a robustness grid's gain axis)
        need not trace, spread and blur the same echoes again for each.

        ``rngs[i]`` draws gain i's noise as :meth:`render`'s ``rng`` does: from the same
        state, the frames are the ones :meth:`render` gives with gain i configured, except
        that the echoes are traced as deep as the configured gain (which must be the
        highest) shows them, where a lower gain's own trace stops ``_TRACE_MARGIN_DB``
        below its display's black level. Measured on the paper probe (water and gel,
        gains −20 to +10 dB traced for +20 or +60 dB): at most one grey level in about one
        pixel per million differs.
        """
        if len(rngs) != len(gains_db):
            raise ValueError(f"{len(gains_db)} gains but {len(rngs)} noise generators")
        if max(gains_db) > self.probe.gain_db:
            raise ValueError(
                f"gain {max(gains_db):g} dB: above the configured {self.probe.gain_db:g} dB, "
                "whose trace is not deep enough for it; configure the highest gain"
            )
        image = self.intensity(T_scene_us, temperature_c)
        t0 = time.perf_counter()
        size = image[0].size
        frames = [
            to_bmode(
                image, replace(self.probe, gain_db=float(g)), self._noise_of(r, size, len(rngs))
            )
            for g, r in zip(gains_db, rngs, strict=True)
        ]
        self.timings.display += time.perf_counter() - t0
        return frames

    def _noise_of(
        self, rng: np.random.Generator | None, size: int, in_use: int = 1
    ) -> NoiseSource | None:
        """The noise source drawing from ``rng`` (made at its first frame: its pool is
        drawn then; None: no noise). The sources of the last ``max(in_use, 8)``
        generators are kept (a source holds eight frames of noise and their levels: ≈ 10 MB
        for the paper probe)."""
        if rng is None:
            return None
        kept = self._noises.pop(id(rng), None)
        if kept is None or kept[0] is not rng:
            kept = (rng, NoiseSource(rng, size))
        self._noises[id(rng)] = kept  # the most recently used last
        while len(self._noises) > max(in_use, _NOISE_SOURCES_KEPT):
            del self._noises[next(iter(self._noises))]
        return kept[1]


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _slab_lobe_moments(
    tilts, depths, f, k, ln, z, zs, b2, lobe, i0, i1, wd, per_tilt, max_slope
):  # pragma: no cover - compiled
    """For each first hit q (frame f, sub-plane k, scanline ln): the tilt across its slab
    (linear towards the neighbour sub-planes' first hits within the tangent plane's reach,
    the other side's rate where one side has none), and the sum, mean and spread of the
    elevation offset under b² E(φ)² at the slab's points ``zs`` (E the smooth mirror's
    elevation lobe ``lobe[node, 0, tilt]``, bilinear in depth node and |φ|). Fused: on
    numpy these were a dozen (hits × points) temporaries, a third of a water frame."""
    n, samples = zs.shape
    K = len(z)
    last = lobe.shape[2] - 1
    wsum = np.zeros(n)
    mean = np.zeros(n)
    spread = np.zeros(n)
    w = np.empty(samples)
    for q in range(n):
        fq, kq, lq = f[q], k[q], ln[q]
        phi, depth, z0 = tilts[fq, kq, lq], depths[fq, kq, lq], z[kq]
        lo = hi = np.nan  # the rates towards the lower and the upper neighbour
        for side in range(2):
            kn = min(max(kq + 2 * side - 1, 0), K - 1)
            t_n, d_n = tilts[fq, kn, lq], depths[fq, kn, lq]
            if kn != kq and np.isfinite(t_n) and abs(d_n - depth) <= max_slope * abs(z[kn] - z0):
                if side == 0:
                    lo = (t_n - phi) / (z[kn] - z0)
                else:
                    hi = (t_n - phi) / (z[kn] - z0)
        if np.isnan(lo):
            lo = hi
        if np.isnan(hi):
            hi = lo
        total = 0.0
        first = 0.0
        for s in range(samples):
            x = zs[q, s] - z0
            rate = lo if zs[q, s] < z0 else hi
            if np.isnan(rate):
                rate = 0.0
            a = abs(phi + rate * x) * per_tilt
            e = 0.0
            if a < last:
                t0 = int(a)
                wa = a - t0
                e = (1.0 - wd[q]) * ((1.0 - wa) * lobe[i0[q], 0, t0] + wa * lobe[i0[q], 0, t0 + 1])
                e += wd[q] * ((1.0 - wa) * lobe[i1[q], 0, t0] + wa * lobe[i1[q], 0, t0 + 1])
            w[s] = b2[q, s] * e * e
            total += w[s]
            first += w[s] * x
        wsum[q] = total
        if total > 0:
            m = first / total
            var = 0.0
            for s in range(samples):
                var += w[s] / total * (zs[q, s] - z0 - m) ** 2
            mean[q] = m
            spread[q] = np.sqrt(max(var, 0.0))
    return wsum, mean, spread


def _between_scanlines(kernels: Array, step: float) -> Array:
    """Lateral intensity kernels (rows, taps) with the scanner's interpolation between its
    scanlines folded in: scan conversion fills the columns between two lines linearly
    (a tent of half-width ``step`` columns), so a surface met by lines every other column
    draws a continuous line, not a dotted one, when the beam is narrower than the line
    spacing (a 0.26 mm beam, lines at the 0.2 mm pitch). Unchanged at one line per
    column."""
    if step <= 1.0 + 1e-9:
        return kernels
    reach = int(np.ceil(step)) - 1
    d = np.arange(-reach, reach + 1)
    tent = np.maximum(0.0, 1.0 - np.abs(d) / step)
    tent /= tent.sum()
    padded = np.pad(kernels, ((0, 0), (reach, reach)))
    return np.stack([np.convolve(row, tent, mode="same") for row in padded])


def _gaussian_kernel(sigma: float) -> NDArray[np.float32]:
    """Normalised Gaussian taps out to ``_TRUNCATE`` σ (as scipy's gaussian_filter1d)."""
    radius = int(_TRUNCATE * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


# Written by hand and compiled with numba: scipy's gaussian_filter1d took ≈ 5 ms a frame
# for the four passes of a speckle frame's blur (real and imaginary parts, two axes);
# here each tap is one pass over a contiguous row, which the compiler vectorises (the
# whole blur ≈ 0.6 ms a frame). Edges as scipy's default mode, "reflect" (d c b a | a b c
# d).
@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _add_blurred_intensity(image, field, k_rows, k_cols, norm):  # pragma: no cover
    """``image += norm · |h * field|²`` for frames (n, H, W): the complex ``field`` blurred
    by the separable amplitude PSF (symmetric taps along rows, then along columns with
    row r's taps ``k_cols[r]``), in place; ``norm`` per row."""
    n, H, W = field.shape
    R, C = len(k_rows) // 2, k_cols.shape[1] // 2
    # The complex values as interleaved (real, imaginary) float32 pairs: every pass below
    # runs over contiguous rows of 2W floats (split into two planes, the axial pass read
    # them with a stride of two and was not vectorized: 2× slower).
    pairs = field.view(np.float32).reshape((n, H, 2 * W))
    tmp = np.zeros((H, 2 * W), np.float32)
    buf = np.zeros(2 * (W + 2 * C), np.float32)
    acc = np.zeros(2 * W, np.float32)
    for f in range(n):
        tmp[:] = 0.0
        for r in range(H):
            for t in range(len(k_rows)):
                rr = r + t - R
                if rr < 0:
                    rr = -rr - 1
                elif rr >= H:
                    rr = 2 * H - rr - 1
                _add_scaled(tmp[r], k_rows[t], pairs[f, rr])
        for r in range(H):
            # The row with its reflected margins, then one contiguous pass per tap.
            row = tmp[r]
            buf[2 * C : 2 * (C + W)] = row
            for c in range(C):
                for p in range(2):
                    buf[2 * (C - 1 - c) + p] = row[2 * c + p]
                    buf[2 * (C + W + c) + p] = row[2 * (W - 1 - c) + p]
            acc[:] = 0.0
            for t in range(k_cols.shape[1]):
                _add_scaled(acc, k_cols[r, t], buf[2 * t : 2 * (t + W)])
            g = norm[r]
            out = image[f, r]
            for c in range(W):
                out[c] += g * (acc[2 * c] * acc[2 * c] + acc[2 * c + 1] * acc[2 * c + 1])


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _row_extents(frame, lo, hi):  # pragma: no cover - compiled
    """First and last column of each row of ``frame`` (H, W) holding a non-zero value
    (``lo = W``, ``hi = -1`` for an empty row). Branch-free (vectorized) scans."""
    H, W = frame.shape
    for r in range(H):
        row = frame[r]
        first, last = W, -1
        for c in range(W):
            nz = row[c] != 0
            first = min(first, c if nz else W)
            last = max(last, c if nz else -1)
        lo[r], hi[r] = first, last


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _reach(lo, hi, k_rows, r, C, W):  # pragma: no cover - compiled
    """Output columns (o0, o1) of row r: those within the lateral taps' reach (C) of a
    value in the rows within the axial taps' reach (o0 > o1: none)."""
    H = lo.shape[0]
    R = len(k_rows) // 2
    c0, c1 = np.int64(1 << 30), np.int64(-1)
    for t in range(len(k_rows)):
        rr = r + t - R
        if 0 <= rr < H and k_rows[t] != 0.0 and hi[rr] >= 0:
            c0 = min(c0, lo[rr])
            c1 = max(c1, hi[rr])
    if c0 > c1:
        return np.int64(1), np.int64(0)
    return max(c0 - C, 0), min(c1 + C, W - 1)


# The loops below run over slices from 0, not over ranges from an offset: numba's
# compiler vectorizes the former only (8× faster here).
@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _add_scaled(out, w, src):  # pragma: no cover - compiled
    """``out += w · src`` (same length)."""
    for c in range(out.shape[0]):
        out[c] += w * src[c]


@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _correlate_span(out, taps, src, o0, o1):  # pragma: no cover - compiled
    """``out[o0..o1] = Σ_t taps[t] · src[o0 + t ..]`` (correlation with the centred taps
    of a source padded by half their length on each side)."""
    m = o1 + 1 - o0
    acc = out[o0 : o1 + 1]
    acc[:] = 0.0
    for t in range(taps.shape[0]):
        w = taps[t]
        if w != 0.0:
            _add_scaled(acc, w, src[o0 + t : o0 + t + m])


@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _axial_into(col, k_rows, source, lo, hi, r, C):  # pragma: no cover - compiled
    """``col[C + c] += Σ_t k_rows[t] · source[r + t − R, c]`` over the rows within reach
    that hold values (columns ``lo..hi`` of each), zeros outside."""
    H = source.shape[0]
    R = len(k_rows) // 2
    for t in range(len(k_rows)):
        rr = r + t - R
        w = k_rows[t]
        if rr < 0 or rr >= H or w == 0.0 or hi[rr] < 0:
            continue
        a, b = lo[rr], hi[rr] + 1
        _add_scaled(col[C + a : C + b], w, source[rr, a:b])


# Written by hand and compiled with numba: blurring the real and imaginary parts as two
# stacks of whole frames, squaring and adding them made five full-frame temporaries per
# frame; here only the rows within reach of a surface's scatterers are touched, and in
# each only the columns within the lateral taps' reach of them (an oblique floor crosses
# many rows, a few columns in each).
@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _add_blurred_surface_speckle(image, field, k_rows, k_cols):  # pragma: no cover
    """``image += |h * field|²`` for frames (n, H, W): the complex ``field`` through the
    separable amplitude PSF (correlation taps ``k_rows`` along rows, zeros outside; row
    r's taps ``k_cols[r]`` along columns), computed only within reach of its non-zero
    values."""
    n, H, W = field.shape
    C = k_cols.shape[1] // 2
    # Read as interleaved (real, imaginary) float32 pairs, each pass over contiguous
    # floats (as _add_blurred_intensity): no copy into planes of their own.
    pairs = field.view(np.float32).reshape((n, H, 2 * W))
    col = np.zeros(2 * (W + 2 * C), np.float32)
    acc = np.zeros(2 * W, np.float32)
    lo = np.empty(H, np.int64)
    hi = np.empty(H, np.int64)
    lo2 = np.empty(H, np.int64)
    hi2 = np.empty(H, np.int64)
    for f in range(n):
        _row_extents(field[f], lo, hi)
        for r in range(H):
            lo2[r], hi2[r] = (2 * lo[r], 2 * hi[r] + 1) if hi[r] >= 0 else (2 * W, -1)
        for r in range(H):
            o0, o1 = _reach(lo, hi, k_rows, r, C, W)
            if o0 > o1:
                continue
            # Output columns o0..o1 read col[o0 .. o1 + 2C]: the axial pass and zeros.
            col[2 * o0 : 2 * (o1 + 2 * C + 1)] = 0.0
            _axial_into(col, k_rows, pairs[f], lo2, hi2, r, 2 * C)
            _correlate_pairs(acc, k_cols[r], col, o0, o1)
            out = image[f, r]
            for c in range(o0, o1 + 1):
                out[c] += acc[2 * c] * acc[2 * c] + acc[2 * c + 1] * acc[2 * c + 1]


@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _correlate_pairs(out, taps, src, o0, o1):  # pragma: no cover - compiled
    """:func:`_correlate_span` of interleaved pairs: ``out[2c + p] = Σ_t taps[t] ·
    src[2 (c + t) + p]`` for c in o0..o1, p in 0, 1."""
    m = 2 * (o1 + 1 - o0)
    acc = out[2 * o0 : 2 * o0 + m]
    acc[:] = 0.0
    for t in range(taps.shape[0]):
        w = taps[t]
        if w != 0.0:
            _add_scaled(acc, w, src[2 * (o0 + t) : 2 * (o0 + t) + m])


def _ring_down_kernel(sigma: float, probe: ProbeConfig, spacing: float) -> NDArray[np.float32]:
    """Axial intensity kernel (correlation taps): the Gaussian PSF, with the transducer's
    ring-down behind it when ``probe.ring_down_cycles`` > 0.

    A lightly damped transducer rings on after the pulse: its envelope decays as
    exp(−f t / N) (a resonator of Q = π N). In displayed depth one cycle is c / (2 f), so
    the tail's amplitude below an echo at depth y is exp(−y / ℓ), ℓ = N c / (2 f), and its
    intensity exp(−2 y / ℓ). The configured Gaussian PSF already is the main pulse: the
    tail starts at the echo's peak and shows only where it exceeds the Gaussian's trailing
    edge (the kernel is the larger of the two behind the peak, unchanged above it), so the
    echo's leading edge, peak and axial FWHM stay as configured.
    """
    g = _gaussian_kernel(sigma)
    n_cycles = probe.ring_down_cycles
    if n_cycles <= 0:
        return g
    ell = n_cycles * probe.assumed_speed_m_s / (2.0 * probe.f_mhz * 1e6) / spacing  # pixels
    reach = int(np.ceil(ell * _RING_DOWN_FLOOR_DB * np.log(10.0) / 20.0))
    r_g = len(g) // 2
    radius = max(r_g, reach)
    spread = np.zeros(2 * radius + 1)  # spread[radius + m]: share landing m rows below
    spread[radius - r_g : radius + r_g + 1] = g  # symmetric: spread = correlation taps
    m = np.arange(1, radius + 1)
    spread[radius + 1 :] = np.maximum(spread[radius + 1 :], g[r_g] * np.exp(-2.0 * m / ell))
    # correlate1d takes taps out[i] = Σ_j k[j] in[i + j − radius]: the spread reversed.
    return spread[::-1].astype(np.float32)


# Written by hand and compiled with numba: spreading each segment over the rows it reaches
# with numpy took ≈ 15 array passes over every (hit, row) pair, a third of the water
# frame's time; the loop touches each pair once.
@numba.njit(cache=True, nogil=True, boundscheck=False)
def _splat_segments(
    image: NDArray[np.float32],
    H: int,
    W: int,
    base: NDArray[np.int64],
    a: Array,
    b: Array,
    rho_a: Array,
    beta: Array,
) -> None:  # pragma: no cover - compiled
    """Add linear-density segments to flat frames ``image`` (n·H·W,), in place.

    Segment j covers rows [a_j, b_j] (fractional) of the column at flat index base_j (+
    row · W) with density ρ(y) = ρ_a + β (y − a). Row i receives ∫_a^b ρ(y) tent(i − y) dy,
    tent(s) = max(0, 1 − |s|) the linear interpolation a point echo is splatted with:
    with R0(t) = ∫_{-∞}^t tent = 1/2 + t − t|t|/2 and R1(t) = ∫_{-∞}^t s·tent(s) ds =
    t²/2 − |t|³/3 − 1/6 on [−1, 1] (constant outside), it is
    (ρ_a + β (i − a)) [R0(i − a) − R0(i − b)] − β [R1(i − a) − R1(i − b)].
    """
    for j in range(len(a)):
        aj, bj, ra, be = a[j], b[j], rho_a[j], beta[j]
        first = max(int(np.floor(aj)), 0)
        last = min(int(np.floor(bj)) + 1, H - 1)
        for i in range(first, last + 1):
            ta = min(max(i - aj, -1.0), 1.0)
            tb = min(max(i - bj, -1.0), 1.0)
            d0 = (ta - tb) - 0.5 * (ta * abs(ta) - tb * abs(tb))
            d1 = 0.5 * (ta * ta - tb * tb) - (ta * ta * abs(ta) - tb * tb * abs(tb)) / 3.0
            image[base[j] + i * W] += np.float32((ra + be * (i - aj)) * d0 - be * d1)


# Written by hand and compiled with numba: the sub-scatterers of every hit built as numpy
# arrays (≈ 20 passes over a million entries a sweep) took three quarters of a water
# frame's time with surface speckle on; here each is made, looked up and splatted once.
@numba.njit(cache=True, nogil=True, boundscheck=False)
def _splat_surface_speckle(
    out, H, W, frame, col, row_f, half, share, sign, slab, energy, point, z_axis, table, key, cell
):  # pragma: no cover - compiled
    """Add the surfaces' incoherent echoes to flat complex frames ``out`` (n·H·W,).

    Hit j stands for ``m`` sub-scatterers along its elevation slab: one for a point echo
    (half-span ≤ _MIN_SMEAR_PX rows), else one per half pixel of its depth span
    ``row_f ± half`` (at most _MAX_SLAB_SCATTERERS), at u = (i + ½) / m along it: depth
    ``row_f − half + 2 u half``, elevation ``(u − ½) · slab · sign`` off the hit point
    along its frame's z axis, energy share ``(2 p + 2 (1 − 2 p) u) / m`` (the trapezoidal
    density of the smooth model's slab, p its shallow end's share). Each one's amplitude
    is the scene-fixed field at its point (:meth:`sim_us.speckle.ScattererField.smooth_at`) times
    the root of its energy, split linearly over its two rows.
    """
    # The sub-scatterers are made in chunks, the field looked up for a chunk at once
    # (its hashing vectorizes), then splatted in the order they were made.
    chunk = 2048
    cells = np.empty((chunk, 3))  # each sub-scatterer's point in cell units
    scale = np.empty(chunk, dtype=np.float32)
    rows = np.empty(chunk)
    bases = np.empty(chunk, dtype=np.int64)
    val = np.empty(chunk, dtype=np.complex64)
    k = 0
    for j in range(len(row_f)):
        h = half[j]
        m = 1
        if h > _MIN_SMEAR_PX:
            m = min(int(np.ceil(4.0 * h)) + 1, _MAX_SLAB_SCATTERERS)
        f = frame[j]
        for i in range(m):
            u = (i + 0.5) / m
            y = row_f[j] - h + 2.0 * u * h
            if not (-1.0 < y < H):
                continue
            w = (2.0 * share[j] + 2.0 * (1.0 - 2.0 * share[j]) * u) / m if m > 1 else 1.0
            if w <= 0.0:
                continue
            dz = (u - 0.5) * slab[j] * sign[j] if m > 1 else 0.0
            for a in range(3):
                cells[k, a] = (point[j, a] + dz * z_axis[f, a]) / cell
            scale[k] = np.float32(np.sqrt(energy[j] * w))
            rows[k] = y
            bases[k] = f * H * W + col[j]
            k += 1
            if k == chunk:
                _splat_scatterers(out, H, W, cells, scale, rows, bases, val, k, table, key)
                k = 0
    _splat_scatterers(out, H, W, cells, scale, rows, bases, val, k, table, key)


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _splat_scatterers(out, H, W, cells, scale, rows, bases, val, k, table, key):  # pragma: no cover
    """Splat the first ``k`` sub-scatterers of a chunk (see :func:`_splat_surface_speckle`):
    the field at each point (``cells``: cell units) times its ``scale``, split linearly
    over the two rows about its row ``rows`` of the column at flat index ``bases``."""
    _smooth_values(cells[:k], table, key, val)
    for i in range(k):
        y = rows[i]
        v = val[i] * scale[i]
        r0 = int(np.floor(y))
        frac = np.float32(y - r0)
        base = bases[i] + r0 * W
        if r0 >= 0:
            out[base] += v * (np.float32(1.0) - frac)
        if r0 + 1 < H:
            out[base + W] += v * frac


def _splat_points(
    image: NDArray[np.float32] | NDArray[np.complex64],
    H: int,
    W: int,
    frame: NDArray[np.int64],
    col: NDArray[np.int64],
    row_f: Array,
    values: NDArray[np.float32] | NDArray[np.complex64],
) -> None:
    """Add point echoes to flat frames ``image`` (n·H·W,), in place, each split linearly
    over its two neighbouring rows (keeps the sub-pixel depth)."""
    row0 = np.floor(row_f).astype(np.int64)
    frac = (row_f - row0).astype(np.float32)
    base = (frame * H + row0) * W + col
    lo, hi = row0 >= 0, row0 + 1 < H
    index = np.concatenate([base[lo], base[hi] + W])
    value = np.concatenate([values[lo] * (1 - frac[lo]), values[hi] * frac[hi]])
    np.add.at(image, index, value.astype(image.dtype))


# Written by hand and compiled with numba: each row has its own lateral taps, which no
# scipy filter takes, and surface echoes are sparse (a sphere's cap, a floor line): only
# the rows within the axial taps' reach of an echo are blurred, and in each only the
# columns within the lateral taps' reach of one (blurring zeros cost most of the time).
@numba.njit(cache=True, nogil=True, boundscheck=False, fastmath=True)
def _blur_where_nonzero(image, k_rows, k_cols):  # pragma: no cover - compiled
    """Separable blur of frames (n, H, W), in place: correlation taps ``k_rows`` along
    rows and row r's taps ``k_cols[r]`` along columns (the lateral beam changes with
    depth), zeros outside."""
    n, H, W = image.shape
    C = k_cols.shape[1] // 2
    source = np.empty((H, W), np.float32)
    col = np.zeros(W + 2 * C, np.float32)
    lo = np.empty(H, np.int64)
    hi = np.empty(H, np.int64)
    for f in range(n):
        frame = image[f]
        _row_extents(frame, lo, hi)
        for r in range(H):
            if hi[r] >= 0:
                source[r, lo[r] : hi[r] + 1] = frame[r, lo[r] : hi[r] + 1]
                frame[r, lo[r] : hi[r] + 1] = 0.0
        for r in range(H):
            o0, o1 = _reach(lo, hi, k_rows, r, C, W)
            if o0 > o1:
                continue
            col[o0 : o1 + 2 * C + 1] = 0.0
            _axial_into(col, k_rows, source, lo, hi, r, C)
            # Nothing of this row is left in the frame: the output overwrites o0..o1.
            _correlate_span(frame[r], k_cols[r], col, o0, o1)
