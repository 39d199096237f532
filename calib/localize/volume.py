"""The sweep volume (paper §III-E-1 adaptive brightness, §III-E-2 sweep volume): which
pixels are bright, and the frames stacked at their offsets in the sweep's reference frame.

A pixel is bright above its frame's mean grey level (the paper's adaptive cut-off) and,
for the ``refined`` method, above its depth's noise floor too (:func:`frame_levels`). The
stack is virtual (:class:`SweepVolume`): slices are the frames at their integer in-plane
shifts, and the bright bits are packed 64 to a machine word so that the exhaustive search
(:mod:`calib.localize.search`) reads a row of candidates' labels in one or two loads
(the compiled kernels: :mod:`calib.localize.kernels`). Voxels map to points through the
image's one pixel mapping (:mod:`calib.image`).
"""

from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import NDArray

from ..errors import LocalizationError
from ..image import pixel_axes, pixel_to_us, us_to_pixel
from ..records import Sweep
from .kernels import _frame_sums, _gather_labels, _pack_bits, block_intensity, candidate_sums
from .settings import frame_offsets

__all__ = [
    "LABEL_BRIGHT",
    "LABEL_DARK",
    "LABEL_OUTSIDE",
    "LABEL_UNIT",
    "MAX_SAMPLES",
    "SweepVolume",
    "candidate_step",
    "frame_bits",
    "frame_levels",
    "stack_sweep",
]

Array = NDArray[np.float64]

# Label values of the stacked volume (int16): a sample adds 1 to the valid count, and a
# bright one also LABEL_UNIT to the bright count, so one integer sum yields both (valid =
# sum % LABEL_UNIT, bright = sum // LABEL_UNIT) for up to LABEL_UNIT - 1 samples per set.
LABEL_UNIT = 512
LABEL_OUTSIDE, LABEL_DARK, LABEL_BRIGHT = 0, 1, 1 + LABEL_UNIT
MAX_SAMPLES = LABEL_UNIT - 1


class SweepVolume:
    """A sweep stacked in its reference frame: a regular grid of labels.

    Label (k, r, c) is 0 outside the acquired volume, else dark/bright versus the frame it
    came from; voxel (k, r, c) sits at ``z = z0 + k·dz`` (metres, reference frame) and, in
    plane, where the image's pixel (r + row0, c + col0) does (:mod:`calib.image`: ``x = (c
    + col0 − (W − 1)/2)·dx, y = (r + row0)·dy``); ``shape`` is (K, H, W).

    The stack is virtual: slice k *is* frame ``nearest[k]`` placed at its integer in-plane
    shift (``frame_rows``, ``frame_cols``), so a re-stack under a new ``T_ee_us`` changes
    only those numbers, never copies pixels. The labels themselves are the frames' bright
    bits (:func:`frame_bits`, which depend on the frames alone and are computed once per
    sweep), split by column phase for the grid search: ``bits[j, d, row, :]`` holds frame
    j's columns ``d, d + column_step, …`` as one bit each, so the labels under a row of
    candidates ``column_step`` voxels apart sit in one or two machine words.
    """

    def __init__(
        self,
        bits: NDArray[np.uint64],
        shape: tuple[int, int, int],
        spacing: tuple[float, float, float],
        z0: float,
        width: int,
        row0: int,
        col0: int,
        frames: NDArray[np.uint8],
        levels: Array,
        nearest: NDArray[np.int64],
        frame_rows: NDArray[np.int64],
        frame_cols: NDArray[np.int64],
        frame_residuals: Array,
    ) -> None:
        self.bits = bits
        self.column_step = bits.shape[1]
        self.shape = shape
        self.spacing = spacing
        self.z0 = z0
        self.width = width
        self.row0 = row0
        self.col0 = col0
        self._frames, self._levels, self._nearest = frames, levels, nearest
        self._frame_rows, self._frame_cols = frame_rows, frame_cols
        self.frame_residuals = frame_residuals  # (frames, 2) metres: see stack_sweep

    def residual_shift(self, k: NDArray[np.int64], weights: Array) -> Array:
        """(x, y) metres: the mean, over slices ``k`` weighted by ``weights``, of how far
        each slice's frame sits from the integer pixel shift it is stacked at — what a
        position measured on the stack is off by there (:func:`stack_sweep`)."""
        total = float(np.sum(weights))
        if total <= 0:
            return np.zeros(2)
        return np.asarray(weights, dtype=float) @ self.frame_residuals[self._nearest[k]] / total

    def position(self, k: Array, r: Array, c: Array) -> Array:
        """Reference-frame points (..., 3), metres, of voxel indices (fractional allowed)."""
        P = pixel_to_us(r + self.row0, c + self.col0, self.width, self.spacing[:2])
        P[..., 2] = self.z0 + k * self.spacing[2]
        return P

    def pixel(self, P: Array) -> tuple[Array, Array]:
        """Fractional (rows, cols) of the frames' pixels under points (..., 3), metres,
        reference frame (:func:`calib.image.us_to_pixel`; the stack's origin ``row0``,
        ``col0`` not yet taken off, z ignored)."""
        return us_to_pixel(P, self.width, self.spacing[:2])

    def index(self, P: Array) -> tuple[Array, Array, Array]:
        """Nearest voxel (k, r, c) of points (..., 3), metres, reference frame; unbounded."""
        rows, cols = self.pixel(P)
        c = np.rint(cols).astype(np.int64) - self.col0
        r = np.rint(rows).astype(np.int64) - self.row0
        k = np.rint((P[..., 2] - self.z0) / self.spacing[2]).astype(np.int64)
        return k, r, c

    def axes(self, rs: NDArray[np.int64], cs: NDArray[np.int64]) -> tuple[Array, Array]:
        """(x of each voxel column ``cs``, y of each voxel row ``rs``), metres: a block's
        in-plane coordinates as separate axes (:func:`calib.image.pixel_axes`)."""
        return pixel_axes(rs + self.row0, cs + self.col0, self.width, self.spacing[:2])

    def virtual_stack(self) -> tuple:
        """What the compiled label kernels read of the stack (:mod:`calib.localize.kernels`):
        (bits, each slice's nearest frame, each frame's row and column shift, H, W)."""
        H, W = self._frames.shape[1:]
        return self.bits, self._nearest, self._frame_rows, self._frame_cols, H, W

    def label_at(self, k: NDArray[np.int64], r: NDArray[np.int64], c: NDArray[np.int64]):
        """Labels of voxels (any shape of integer indices); 0 (outside) past the volume."""
        k, r, c = np.broadcast_arrays(k, r, c)
        out = _gather_labels(
            *self.virtual_stack(),
            np.ascontiguousarray(k, dtype=np.int64).ravel(),
            np.ascontiguousarray(r, dtype=np.int64).ravel(),
            np.ascontiguousarray(c, dtype=np.int64).ravel(),
        )
        return out.reshape(k.shape)

    def label_sums(self, candidates: NDArray[np.int64], offsets: NDArray[np.int64]):
        """Encoded label sums (valid + LABEL_UNIT · bright), (N,), of candidate voxels
        (N, 3) as (k, r, c), each over the integer sample ``offsets`` (m, 3): the sum of
        :meth:`label_at` at every candidate + offset, in one compiled pass."""
        return candidate_sums(
            *self.virtual_stack(),
            np.ascontiguousarray(candidates, dtype=np.int64).reshape(-1, 3),
            np.ascontiguousarray(offsets, dtype=np.int64),
        )

    def with_column_step(self, step: int) -> SweepVolume:
        """The same volume with its bits split for another candidate column step."""
        return SweepVolume(
            frame_bits(self._frames, self._levels, step),
            self.shape,
            self.spacing,
            self.z0,
            self.width,
            self.row0,
            self.col0,
            self._frames,
            self._levels,
            self._nearest,
            self._frame_rows,
            self._frame_cols,
            self.frame_residuals,
        )

    def intensity(
        self,
        ks: NDArray[np.int64],
        rs: NDArray[np.int64],
        cs: NDArray[np.int64],
        *,
        level: float | None = None,
    ) -> Array:
        """Grey level minus its brightness level of the voxel block ks × rs × cs (0
        outside); rs and cs are consecutive index ranges. ``level`` subtracts that one
        level everywhere instead of each frame row's own."""
        if not (len(ks) and len(rs) and len(cs)):
            return np.zeros((len(ks), len(rs), len(cs)))
        # rs and cs are consecutive ranges: each slice's block is a plain window of its frame.
        return block_intensity(
            self._frames,
            self._levels,
            self._nearest,
            self._frame_rows,
            self._frame_cols,
            np.ascontiguousarray(ks, dtype=np.int64),
            int(rs[0]),
            len(rs),
            int(cs[0]),
            len(cs),
            0.0 if level is None else float(level),
            level is not None,
        )


def candidate_step(spacing: tuple[float, float, float], grid: float) -> tuple[int, int, int]:
    """Candidate-grid step in voxels (k, r, c) for a grid spacing in metres."""
    dx, dy, dz = spacing
    return tuple(max(1, int(np.rint(grid / s))) for s in (dz, dy, dx))


_BITS_CACHE: dict[tuple[int, int, int], NDArray[np.uint64]] = {}


_LEVELS_CACHE: dict[tuple[int, bool], Array] = {}

# A pixel is above its depth's noise floor when it exceeds the median of that image row
# (pooled over the sweep's frames) by _NOISE_SIGMAS robust standard deviations (IQR/1.349).
# For a log-compressed Rayleigh envelope (electronic noise, fully developed speckle) 2 σ
# is ≈ 10 dB above the median: the noise alone gets there with probability ≈ 10⁻³.
_NOISE_SIGMAS = 2.0


def _row_noise_floor(images: NDArray[np.uint8]) -> Array:
    """Per image row (depth): median + _NOISE_SIGMAS · IQR/1.349 of its grey levels over
    all frames, from one histogram per row. Where most of a row sits at the display floor
    (dark water) this is 0 and the frame mean decides alone."""
    H = images.shape[1]
    rows = np.broadcast_to(np.arange(H, dtype=np.int32)[None, :, None] * 256, images.shape)
    hist = np.bincount((rows + images).ravel(), minlength=H * 256).reshape(H, 256)
    cdf = np.cumsum(hist, axis=1)
    total = cdf[:, -1:]
    q25, q50, q75 = (np.argmax(cdf >= q * total, axis=1) for q in (0.25, 0.5, 0.75))
    return q50 + _NOISE_SIGMAS * (q75 - q25) / 1.349


def frame_levels(images: NDArray[np.uint8], *, noise_floor: bool = False) -> Array:
    """Brightness level of every row of every frame, (n, H): a pixel is bright above it.

    The paper's cut-off is the frame's own mean grey level. With ``noise_floor`` (method
    "refined") a pixel must also stand above its depth's noise floor
    (:func:`_row_noise_floor`): where the gain lifts electronic noise or speckle above the
    frame mean, about half of the water is otherwise "bright", and a laterally uniform band
    (the transducer's ring-down, a plate, the tank floor) is bright only where it stands
    out from its own depth. Memoised like :func:`frame_bits` for as long as the frames live.
    """
    key = (id(images), bool(noise_floor))
    cached = _LEVELS_CACHE.get(key)
    if cached is None:
        H, W = images.shape[1:]
        means = _frame_sums(np.ascontiguousarray(images)) / (H * W)
        cached = np.repeat(means[:, None], H, axis=1)
        if noise_floor:
            cached = np.maximum(cached, _row_noise_floor(images)[None, :])
        _LEVELS_CACHE[key] = cached
        weakref.finalize(images, _LEVELS_CACHE.pop, key, None)
    return cached


def frame_bits(images: NDArray[np.uint8], levels: Array, column_step: int) -> NDArray[np.uint64]:
    """Bright bits of every frame (grey level above its row's level, :func:`frame_levels`),
    split by column phase: (n, column_step, H, words) uint64 (see :class:`SweepVolume`).

    They depend on the frames alone, so they are memoised for as long as the frames array
    lives (a sweep is re-stacked many times while localization and calibration
    alternate; the bits are 1/8 of the frames' size).
    """
    key = (id(images), id(levels), int(column_step))
    cached = _BITS_CACHE.get(key)
    if cached is not None:
        return cached
    n, H, W = images.shape
    sc = int(column_step)
    per_phase = -(-W // sc)  # columns of phase 0, the longest
    words = max(1, -(-per_phase // 64))
    bits = np.zeros((n, sc, H, words), dtype=np.uint64)
    # "Brighter than the level" for integer grey levels: at least floor(level) + 1.
    thresholds = np.floor(levels).astype(np.int64) + 1
    _pack_bits(np.ascontiguousarray(images), thresholds, sc, bits)
    _BITS_CACHE[key] = bits
    weakref.finalize(images, _BITS_CACHE.pop, key, None)
    return bits


def stack_sweep(
    sweep: Sweep,
    T_ee_us: Array | None,
    *,
    axial_scale: float = 1.0,
    column_step: int = 1,
    noise_floor: bool = False,
) -> SweepVolume:
    """Stack (or re-stack) a sweep into a labelled volume in its reference frame.

    ``axial_scale`` corrects the displayed axial spacing for the medium's true speed of
    sound (c_medium / c_assumed); ``column_step`` is the candidate grid's column step the
    labels are split for (see :class:`SweepVolume`; any step works, a matching one is fast).
    """
    images = sweep.images
    n, H, W = images.shape
    sx, sy = sweep.spacing
    sy = sy * axial_scale
    offsets = frame_offsets(sweep, T_ee_us)
    z = offsets[:, 2]
    order = np.argsort(z)
    dz = float(np.median(np.diff(z[order]))) if n > 1 else 1e-3
    if dz <= 0:
        raise LocalizationError(f"{sweep.target} sweep {sweep.pose_id}: frames do not advance")
    z0 = float(z[order[0]])
    n_slices = int(np.rint((z[order[-1]] - z0) / dz)) + 1
    # Nearest frame of each slice.
    slice_z = z0 + np.arange(n_slices) * dz
    nearest = order[np.argmin(np.abs(slice_z[:, None] - z[order][None, :]), axis=1)]
    levels = frame_levels(images, noise_floor=noise_floor)
    # Integer pixel shift of each frame's in-plane offset (nearest voxel); the grid spans
    # every shifted frame. What the rounding leaves (up to half a pixel) is kept: a sweep
    # whose axis is a few degrees off the image normal (the coarse mount's error) shifts
    # its frames in plane by z·tan α, and near the sphere the rounding differs from sweep
    # to sweep with the pose — an error of up to half a pixel that the refinement of the
    # cap corrects (:meth:`SweepVolume.residual_shift`).
    shift_c = np.rint(offsets[:, 0] / sx).astype(np.int64)
    shift_r = np.rint(offsets[:, 1] / sy).astype(np.int64)
    residuals = offsets[:, :2] - np.column_stack([shift_c * sx, shift_r * sy])
    col0, row0 = int(min(0, shift_c.min())), int(min(0, shift_r.min()))
    width = W - col0 + int(max(0, shift_c.max()))
    height = H - row0 + int(max(0, shift_r.max()))
    return SweepVolume(
        frame_bits(images, levels, column_step),
        (n_slices, height, width),
        (sx, sy, dz),
        z0,
        W,
        row0,
        col0,
        images,
        levels,
        nearest.astype(np.int64),
        (shift_r - row0).astype(np.int64),
        (shift_c - col0).astype(np.int64),
        residuals,
    )
