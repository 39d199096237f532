"""The B-mode simulator: probe poses + acoustic scene → frames.

For each frame one ray per scanline (one scanline per image column) is cast along the
axial direction in each elevation sub-plane; the echoes are weighted by the elevation
beam profile at their depth and summed incoherently over the sub-planes (partial
volume), splatted at their apparent depth and blurred with the PSF. Backscatter speckle
of a scattering medium is summed *coherently* over the elevation beam (scatterers at
different elevations add as waves in one A-line, which keeps fully developed Rayleigh
statistics) and blurred with the complex PSF. The display chain adds noise, gain, TGC
and log compression. Pure function of (scene, poses, config, rng); ground truth stays
with the caller.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import correlate1d, gaussian_filter1d

from calib.image import pixel_to_us

from .beam import FWHM_PER_SIGMA, elevation_offsets, elevation_weights, slice_thickness
from .display import NoiseSource, gain_profile_db, to_bmode
from .materials import MATERIALS, amplitude_reflection, attenuation_db_per_m, medium_material
from .probe import MediumConfig, ProbeConfig
from .propagation import trace
from .raycast import AcousticScene, RayCaster
from .speckle import ScattererField

__all__ = ["BmodeSimulator"]

Array = NDArray[np.float64]

# Rays whose echoes would fall this far below the display floor are not traced further.
_TRACE_MARGIN_DB = 3.0
# Speckle sums scatterers within ± this many half slice thicknesses in elevation.
_SPECKLE_COVERAGE = 1.5
# PSF kernels are truncated at this many σ.
_TRUNCATE = 3.0


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
        self.medium = medium_material(medium.kind, medium.temperature_c)
        self.part_materials = [MATERIALS[p.material] for p in scene.parts]
        self.caster = RayCaster(scene)
        # Scatterer cells of a third of the finer resolution: ≥ 10 per PSF cell.
        cell = min(probe.axial_fwhm_mm, probe.lateral_fwhm_mm) * 1e-3 / 3.0
        self.scatterers = ScattererField(cell, int(speckle_key))
        self.timings = Timings()
        self._noise: NoiseSource | None = None
        self._noise_rng: np.random.Generator | None = None

        self.shape = probe.image_shape
        H, W = self.shape
        self.spacing = probe.spacing_m
        sx, sy = self.spacing
        self.max_depth = (H - 1) * sy
        self.z, dz = elevation_offsets(probe, self.max_depth)
        rows_y = np.arange(H) * sy
        self.weights = elevation_weights(probe, rows_y, self.z, dz).astype(np.float32)  # (K, H)
        # Scanlines on the nearest columns to an even spacing; each stands for the columns
        # nearest to it (its weight) and the lateral PSF (σ ≳ spacing) fills them in.
        step = max(1.0, probe.scanline_spacing_mm * 1e-3 / sx)
        self.columns = np.unique(np.rint(np.arange(0.0, W - 1 + 1e-9, step)).astype(np.int64))
        mids = (self.columns[1:] + self.columns[:-1]) / 2
        bounds = np.concatenate([[-0.5], mids, [W - 0.5]])
        self.line_width = np.diff(bounds)
        self._line_of_column = np.searchsorted(mids, np.arange(W))
        # Scanline origins in the image frame: (K planes, scanlines, 3).
        x = pixel_to_us(0, self.columns, W, self.spacing)[:, 0]
        self._origins_us = np.stack(
            np.broadcast_arrays(x[None, :], 0.0, self.z[:, None]), axis=-1
        ).astype(float)
        sigma_lat = probe.lateral_fwhm_mm * 1e-3 / FWHM_PER_SIGMA / sx
        sigma_ax = probe.axial_fwhm_mm * 1e-3 / FWHM_PER_SIGMA / sy
        self.sigma_px = (sigma_ax, sigma_lat)  # amplitude PSF σ in (rows, cols)
        # Path loss past which no echo can reach the display floor at any row's gain: the
        # strongest interface of the scene reflects r_max, so a path weaker than
        # floor / r_max cannot show.
        max_gain = float(np.max(gain_profile_db(probe, H)))
        imped = [m.impedance for m in [self.medium, *self.part_materials]]
        r_max = max((float(amplitude_reflection(a, b)) for a in imped for b in imped), default=1.0)
        self.floor_db = (
            probe.dynamic_range_db
            + max(max_gain, 0.0)
            + 20 * np.log10(max(r_max, 1e-6))
            + _TRACE_MARGIN_DB
        )

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

    def _echo_intensity(self, T_scene_us: Array) -> tuple[NDArray[np.float32], Array]:
        """Surface-echo intensity (n, H, W) before the PSF, and each ray's medium end."""
        H, W = self.shape
        K = len(self.z)
        origins, dirs, n = self._rays(T_scene_us)
        t0 = time.perf_counter()
        echoes = trace(
            self.caster,
            self.part_materials,
            self.medium,
            origins,
            dirs,
            self.max_depth,
            self.probe.f_mhz,
            self.probe.assumed_speed_m_s,
            self.floor_db,
            self.probe.reverberation,
        )
        t1 = time.perf_counter()
        self.timings.raycast += t1 - t0
        L = len(self.columns)
        frame, rem = np.divmod(echoes.ray, K * L)
        plane, line = np.divmod(rem, L)
        col = self.columns[line]
        row_f = echoes.depth / self.spacing[1]
        inside = (row_f > -1) & (row_f < H)
        frame, plane, line, col, row_f = (v[inside] for v in (frame, plane, line, col, row_f))
        row_idx = np.clip(np.rint(row_f).astype(np.int64), 0, H - 1)
        inten = self.line_width[line] * echoes.amplitude[inside] ** 2 * self.weights[plane, row_idx]
        # Linear splat over the two neighbouring rows keeps the sub-pixel depth.
        row0 = np.floor(row_f).astype(np.int64)
        frac = (row_f - row0).astype(np.float32)
        inten = inten.astype(np.float32)
        base = (frame * H + row0) * W + col
        lo, hi = row0 >= 0, row0 + 1 < H
        index = np.concatenate([base[lo], base[hi] + W])
        value = np.concatenate([inten[lo] * (1 - frac[lo]), inten[hi] * frac[hi]])
        image = np.zeros(n * H * W, dtype=np.float32)
        np.add.at(image, index, value)
        self.timings.formation += time.perf_counter() - t1
        medium_end = echoes.medium_end.reshape(n, K, L)[:, :, self._line_of_column]
        return image.reshape(n, H, W), medium_end

    # ------------------------------------------------------------------ speckle

    def _speckle(self, T_scene_us: Array, medium_end: Array) -> NDArray[np.complex64]:
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
        depth = np.arange(H) * self.spacing[1]
        x = pixel_to_us(0, np.arange(W), W, self.spacing)[:, 0]
        level = 10.0 ** (self.medium.backscatter_db / 20.0)
        att = attenuation_db_per_m(self.medium, self.probe.f_mhz)
        # Two-way attenuation in the medium (apparent ≈ true depth in a uniform medium).
        amp_row = level * 10.0 ** (-2.0 * att * depth / 20.0)
        cell = self.scatterers.cell_m
        st = slice_thickness(self.probe, depth)
        reach = _SPECKLE_COVERAGE * st / 2  # elevation half-span summed at each depth (m)
        n_side = int(np.ceil(reach.max() / cell)) + 1
        out = np.zeros((n, H, W), dtype=np.complex64)
        for f in range(n):
            R, t = T_scene_us[f, :3, :3], T_scene_us[f, :3, 3]
            rows = (depth[:, None] * R[:, 1] / cell).astype(np.float32)  # (H, 3) in cells
            cols = (x[:, None] * R[:, 0] / cell).astype(np.float32)  # (W, 3)
            s0 = float(t @ R[:, 2]) / cell  # probe plane on the elevational lattice
            norm = np.zeros(H)
            acc = np.zeros((H, W), dtype=np.complex64)
            for j in range(-n_side, n_side + 1):
                z = (np.floor(s0) + j - s0) * cell  # this lattice line's offset from the plane
                sel = np.flatnonzero(np.abs(z) <= reach)
                if sel.size == 0:
                    continue
                b = np.exp(-4.0 * np.log(2.0) * z**2 / st[sel] ** 2)  # two-way amplitude
                norm[sel] += b**2
                offset = ((t + z * R[:, 2]) / cell).astype(np.float32)
                idx = np.floor(rows[sel, None, :] + (cols + offset)[None]).astype(np.int64)
                k = int(np.argmin(np.abs(self.z - z)))  # sub-plane that knows the shadow
                visible = depth[sel, None] < medium_end[f, k][None, :]
                acc[sel] += self.scatterers.at_cells(idx) * (b[:, None] * visible)
            # Unit mean intensity per row, then the medium's level and attenuation.
            gain = np.where(norm > 0, amp_row / np.sqrt(np.maximum(norm, 1e-30)), 0.0)
            out[f] = acc * gain.astype(np.float32)[:, None]
        return out

    # ------------------------------------------------------------------ public

    def intensity(self, T_scene_us: Array) -> NDArray[np.float32]:
        """Envelope intensity (n, H, W) relative to a perfect reflector, noise-free.

        ``T_scene_us`` (n, 4, 4) or (4, 4): probe image-frame poses in the scene frame.
        """
        T = np.asarray(T_scene_us, dtype=float).reshape(-1, 4, 4)
        image, medium_end = self._echo_intensity(T)
        t0 = time.perf_counter()
        sig_ax, sig_lat = self.sigma_px
        # The intensity PSF of an incoherent echo is |h|²: Gaussian with σ / √2.
        _blur_where_nonzero(image, sig_ax / np.sqrt(2), sig_lat / np.sqrt(2))
        if self.medium.backscatter_db is not None:
            sp = self._speckle(T, medium_end)
            for axis, sig in ((1, sig_ax), (2, sig_lat)):
                # Normalise so white scatterers keep unit mean intensity after the blur.
                norm = np.float32(np.sqrt(2.0 * np.sqrt(np.pi) * sig))
                sp = (
                    gaussian_filter1d(sp.real, sig, axis=axis, truncate=_TRUNCATE)
                    + 1j * gaussian_filter1d(sp.imag, sig, axis=axis, truncate=_TRUNCATE)
                ).astype(np.complex64) * norm
            image += (sp.real**2 + sp.imag**2).astype(np.float32)
        self.timings.formation += time.perf_counter() - t0
        self.timings.frames += len(T)
        return image

    def envelope(self, T_scene_us: Array) -> NDArray[np.float32]:
        """Noise-free envelope amplitude (n, H, W)."""
        return np.sqrt(self.intensity(T_scene_us))

    def render(self, T_scene_us: Array, rng: np.random.Generator | None) -> NDArray[np.uint8]:
        """B-mode frames (n, H, W) uint8 as a frame grabber delivers them.

        ``rng`` draws the electronic noise; None renders without it.
        """
        image = self.intensity(T_scene_us)
        t0 = time.perf_counter()
        noise = None
        if rng is not None:
            if self._noise is None or self._noise_rng is not rng:
                self._noise = NoiseSource(rng, image[0].size)
                self._noise_rng = rng
            noise = self._noise
        frames = to_bmode(image, self.probe, noise)
        self.timings.display += time.perf_counter() - t0
        return frames


def _gaussian_kernel(sigma: float) -> NDArray[np.float32]:
    """Normalised Gaussian taps out to ``_TRUNCATE`` σ (as scipy's gaussian_filter1d)."""
    radius = int(_TRUNCATE * sigma + 0.5)
    x = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def _blur_where_nonzero(image: NDArray[np.float32], sigma_rows: float, sigma_cols: float) -> None:
    """Separable Gaussian blur of frames (n, H, W), in place, limited to the row bands
    that hold echoes in any frame (plus the kernel radius) and to their columns: surface
    echoes are sparse (a sphere's cap, a floor line), and blurring zeros would cost most
    of the time. The frames of a sweep share their bands, so each band is one call."""
    _, _, W = image.shape
    k_rows, k_cols = _gaussian_kernel(sigma_rows), _gaussian_kernel(sigma_cols)
    pad_r, pad_c = len(k_rows) // 2 + 1, len(k_cols) // 2 + 1
    occupied = image.any(axis=(0, 2))
    if not occupied.any():
        return
    band = np.convolve(occupied, np.ones(2 * pad_r + 1), mode="same") > 0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], band.astype(np.int8), [0]])))
    for r0, r1 in zip(edges[::2], edges[1::2], strict=True):
        cols = np.flatnonzero(image[:, r0:r1].any(axis=(0, 1)))
        c0, c1 = max(cols[0] - pad_c, 0), min(cols[-1] + pad_c + 1, W)
        block = correlate1d(image[:, r0:r1, c0:c1], k_rows, axis=1, mode="constant")
        image[:, r0:r1, c0:c1] = correlate1d(block, k_cols, axis=2, mode="constant")
