"""The sweep volume (paper, "Threshold-Free Sphere Localization", steps 1-2): which pixels
are bright, and the frames stacked at their offsets in the sweep's reference frame.

A pixel is bright above its frame's mean grey level (the paper's adaptive cut-off) and,
for the ``refined`` method, above its depth's noise floor too (:func:`frame_levels`). The
stack is virtual (:class:`SweepVolume`): slices are the frames at their integer in-plane
shifts, and the bright bits are packed 64 to a machine word so that the exhaustive search
(:mod:`calib.localize`) reads a row of candidates' labels in one or two loads. The
compiled kernels here are the hot loops of that search and of the cap's moments, written
by hand with numba: they touch each packed word once, where the obvious numpy scorer
(:func:`calib.localize.score_candidates_reference`) is ≈ 24 000× slower on a sweep
(``benchmarks/localize.py``).
"""

from __future__ import annotations

import weakref

import numba
import numpy as np
from numpy.typing import NDArray

from .errors import LocalizationError
from .localization import frame_offsets
from .records import Sweep

__all__ = [
    "LABEL_BRIGHT",
    "LABEL_DARK",
    "LABEL_OUTSIDE",
    "LABEL_UNIT",
    "MAX_SAMPLES",
    "SweepVolume",
    "candidate_step",
    "cap_weights",
    "frame_bits",
    "frame_levels",
    "grid_sums",
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
    came from; voxel (k, r, c) sits at ``x = (c + col0 − (W − 1)/2)·dx, y = (r + row0)·dy,
    z = z0 + k·dz`` (metres, reference frame); ``shape`` is (K, H, W).

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
        """Reference-frame points (..., 3) of voxel indices."""
        dx, dy, dz = self.spacing
        return np.stack(
            [(c + self.col0 - (self.width - 1) / 2) * dx, (r + self.row0) * dy, self.z0 + k * dz],
            axis=-1,
        )

    def index(self, P: Array) -> tuple[Array, Array, Array]:
        """Nearest voxel (k, r, c) of points (..., 3), unbounded."""
        dx, dy, dz = self.spacing
        c = np.rint(P[..., 0] / dx + (self.width - 1) / 2).astype(np.int64) - self.col0
        r = np.rint(P[..., 1] / dy).astype(np.int64) - self.row0
        k = np.rint((P[..., 2] - self.z0) / dz).astype(np.int64)
        return k, r, c

    def label_at(self, k: NDArray[np.int64], r: NDArray[np.int64], c: NDArray[np.int64]):
        """Labels of voxels (any shape of integer indices); 0 (outside) past the volume."""
        k, r, c = np.broadcast_arrays(k, r, c)
        out = _gather_labels(
            self.bits,
            self._nearest,
            self._frame_rows,
            self._frame_cols,
            self._frames.shape[1],
            self._frames.shape[2],
            np.ascontiguousarray(k, dtype=np.int64).ravel(),
            np.ascontiguousarray(r, dtype=np.int64).ravel(),
            np.ascontiguousarray(c, dtype=np.int64).ravel(),
        )
        return out.reshape(k.shape)

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
        level: float | None = None,
    ) -> Array:
        """Grey level minus its brightness level of the voxel block ks × rs × cs (0
        outside); rs and cs are consecutive index ranges. ``level`` subtracts that one
        level everywhere instead of each frame row's own."""
        out = np.zeros((len(ks), len(rs), len(cs)))
        if not (len(ks) and len(rs) and len(cs)):
            return out
        H, W = self._frames.shape[1:]
        # rs and cs are consecutive ranges: each slice's block is a plain window of its frame.
        for a, k in enumerate(ks):
            j = self._nearest[k]
            r_lo = max(rs[0] - self._frame_rows[j], 0)
            r_hi = min(rs[-1] + 1 - self._frame_rows[j], H)
            c_lo = max(cs[0] - self._frame_cols[j], 0)
            c_hi = min(cs[-1] + 1 - self._frame_cols[j], W)
            if r_hi <= r_lo or c_hi <= c_lo:
                continue
            sub = self._levels[j, r_lo:r_hi, None] if level is None else level
            block = self._frames[j, r_lo:r_hi, c_lo:c_hi] - sub
            ro = r_lo + self._frame_rows[j] - rs[0]
            co = c_lo + self._frame_cols[j] - cs[0]
            out[a, ro : ro + r_hi - r_lo, co : co + c_hi - c_lo] = block
        return out


def candidate_step(spacing: tuple[float, float, float], grid: float) -> tuple[int, int, int]:
    """Candidate-grid step in voxels (k, r, c) for a grid spacing in metres."""
    dx, dy, dz = spacing
    return tuple(max(1, int(np.rint(grid / s))) for s in (dz, dy, dx))


# ----------------------------------------------------------------------------- kernels
# Written by hand and compiled with numba: they are the localizer's whole cost.


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _frame_sums(images):  # pragma: no cover - compiled
    """Integer grey-level sum of each frame (exact; no float copy of the frames)."""
    out = np.zeros(images.shape[0], np.int64)
    for j in range(images.shape[0]):
        acc = np.int64(0)
        for r in range(images.shape[1]):
            row = images[j, r]
            for c in range(images.shape[2]):
                acc += row[c]
        out[j] = acc
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _pack_bits(images, thresholds, sc, out):  # pragma: no cover - compiled
    """out[j, d, r, w] bit b = pixel (r, d + (64 w + b)·sc) of frame j ≥ thresholds[j, r]."""
    H, W = images.shape[1], images.shape[2]
    for j in range(images.shape[0]):
        for r in range(H):
            t = thresholds[j, r]
            src = images[j, r]
            for d in range(sc):
                dst = out[j, d, r]
                n = (W - d + sc - 1) // sc
                for w in range((n + 63) // 64):
                    word = np.uint64(0)
                    for b in range(min(64, n - 64 * w)):
                        bright = np.uint64(src[d + (64 * w + b) * sc] >= t)
                        word |= bright << np.uint64(b)
                    dst[w] = word


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _gather_labels(bits, nearest, frame_rows, frame_cols, H, W, k, r, c):  # pragma: no cover
    """Labels at voxel indices (flat arrays) of a virtual stack, 0 outside."""
    sc = bits.shape[1]
    K = nearest.shape[0]
    out = np.zeros(k.shape[0], np.int16)
    for i in range(k.shape[0]):
        ki = k[i]
        if ki < 0 or ki >= K:
            continue
        j = nearest[ki]
        fr = r[i] - frame_rows[j]
        fc = c[i] - frame_cols[j]
        if 0 <= fr < H and 0 <= fc < W:
            q = fc // sc
            bit = (bits[j, fc % sc, fr, q >> 6] >> np.uint64(q & 63)) & np.uint64(1)
            out[i] = 1 + 512 * np.int16(bit)
    return out


@numba.njit(cache=True, nogil=True, boundscheck=False)
def grid_sums(
    bits, nearest, frame_rows, frame_cols, H, W, start, step, count, offsets
):  # pragma: no cover - compiled
    """Encoded label sums (valid + LABEL_UNIT · bright) of every grid candidate.

    Per (slice, sample offset) the slice's frame and shift are fixed, so for each row of
    candidates the samples read one bit-row of one column phase of that frame, and the
    candidates whose sample lands inside the frame form one run, found once. Samples past
    the acquired volume count as outside. The grid's column step must be the bits' phase
    count (:meth:`SweepVolume.with_column_step` re-splits otherwise).
    """
    sc = bits.shape[1]
    K = nearest.shape[0]
    nk, nr, nc = count[0], count[1], count[2]
    out = np.zeros((nk, nr, nc), np.int32)
    one = np.uint64(1)
    for i in range(nk):
        for m in range(offsets.shape[0]):
            k = start[0] + i * step[0] + offsets[m, 0]
            if k < 0 or k >= K:
                continue
            j = nearest[k]
            fc0 = start[2] + offsets[m, 2] - frame_cols[j]  # frame column of candidate 0
            d = fc0 % sc
            q0 = fc0 // sc
            n_cols = (W - d + sc - 1) // sc  # columns of phase d inside the frame
            lo = max(0, -q0)
            hi = min(nc, n_cols - q0)
            if hi <= lo:
                continue
            for jj in range(nr):
                fr = start[1] + jj * step[1] + offsets[m, 1] - frame_rows[j]
                if fr < 0 or fr >= H:
                    continue
                row = bits[j, d, fr]
                dst = out[i, jj]
                # A word at a time: load it once, shift it along the run's candidates.
                q = lo
                while q < hi:
                    b = q0 + q
                    word = row[b >> 6] >> np.uint64(b & 63)
                    end = min(hi, q + 64 - (b & 63))
                    while q < end:
                        dst[q] += 1 + 512 * np.int32(word & one)
                        word >>= one
                        q += 1
    return out


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


def frame_levels(images: NDArray[np.uint8], noise_floor: bool = False) -> Array:
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
    levels = frame_levels(images, noise_floor)
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


@numba.njit(cache=True, nogil=True, boundscheck=False)
def cap_weights(
    frames, levels, nearest, frame_rows, frame_cols, ks, rs, cs, dz2, dy2, dx2, lo2, hi2
):  # pragma: no cover - compiled
    """Weights (len(ks), len(rs), len(cs)) of the cap refinement: grey level minus its
    brightness level (:func:`frame_levels`) where positive and the voxel lies in the shell
    band (squared distances ``lo2 ≤ dz2 + dy2 + dx2 ≤ hi2``), else 0. Compiled: one pass
    instead of the several full-block NumPy passes it replaces (≈ 4× faster)."""
    H, W = frames.shape[1], frames.shape[2]
    out = np.zeros((ks.shape[0], rs.shape[0], cs.shape[0]))
    for a in range(ks.shape[0]):
        j = nearest[ks[a]]
        for b in range(rs.shape[0]):
            fr = rs[b] - frame_rows[j]
            if fr < 0 or fr >= H:
                continue
            row = frames[j, fr]
            level = levels[j, fr]
            dzy = dz2[a] + dy2[b]
            for c in range(cs.shape[0]):
                fc = cs[c] - frame_cols[j]
                if fc < 0 or fc >= W:
                    continue
                d2 = dzy + dx2[c]
                if d2 < lo2 or d2 > hi2:
                    continue
                v = row[fc] - level
                if v > 0:
                    out[a, b, c] = v
    return out
