"""Threshold-free sphere localization (paper, "Threshold-Free Sphere Localization").

Per sweep:

1. **Adaptive brightness.** A pixel is bright when it is above the mean of its own frame
   (no user-chosen intensity cut-off).
2. **Sweep volume.** The frames are stacked at the robot-measured spacing; once a
   ``T_ee_us`` is known they are re-stacked into the sweep's reference frame (the centre
   frame's ``us`` frame), which removes the shear a wrong calibration puts into the stack.
3. **Count-based exhaustive search.** Candidate centres on a 1 mm grid over the sweep,
   starting one radius below the face. Each candidate samples a proximal shell at radius R
   (Fibonacci directions) and the proximal half-ball (volume-distributed points); each
   sample takes its nearest voxel and asks whether it is bright. Samples outside the
   acquired volume count in neither numerator nor denominator. The score is
   ``f_shell − f_interior``; its argmax is the seed.
4. **Radial-band refinement.** Around the current centres, the bright fraction on proximal
   hemispheres of trial radius, averaged over all sweeps of the sphere and normalised to its
   peak, gives a radial profile: the interior extends to its first rising 0.25 crossing, the
   shell band lies between its 0.75 crossings. Those bands replace the initial samples for
   the refinement passes.

``method="paper"`` stops there (grid-point centres). ``method="refined"`` differs in
seven ways, each for a failure of the paper's score measured on the twin (a bright plate
or floor taken for the sphere in ≈ 10-60 % of sweeps at low gain, a small sphere or a deep
target; a biased centre where the cap saturates):

- *Brightness above the noise floor.* A pixel must also stand above its depth's noise
  floor (each image row's median plus two robust σ over the sweep, see
  :func:`frame_levels`): where the gain lifts electronic noise above the frame mean, half
  the water would otherwise be "bright" and a clearly visible cap would fail the
  confinement test; a laterally uniform band (ring-down, a plate) stands out less.
- *The plan's window.* With ``expected_depth_mm`` (the protocol's target depth) the
  search covers only ± ``expected_window_mm`` about it and about the centre line, where
  the plan put the sphere: where the cap sinks into the noise floor, the plate under
  the sphere (the same spot from every view, so the siblings agree on it) is not there
  to be found.
- *Hypotheses.* The exhaustive search keeps the grid's ``_HYPOTHESES`` best maxima more
  than R apart and looks at each on a grid twice as fine: a faint thin cap straddled by
  the 1 mm grid recovers its contrast there, a flat reflector does not.
- *Confinement.* Each is judged by ``f_shell − max(f_interior, f_outer)``, ``f_outer`` the
  bright share in the band ``_OUTER_BAND`` × R outside the sphere on the probe side: water
  for a sphere, more of the reflector for a plate. A detection whose cap does not stand
  out from that band by ``min_score`` is rejected with its reason.
- *The specular arc.* Where nothing with a sphere's whole cap is found (an attenuating
  gel, a deep target at low gain: the flanks sink below the noise and only the cap about
  normal incidence echoes), a cone of the shell within ``_ARC_DEG`` of the beam axis is
  searched the same way, confined by the band above it and by its tangent plane (where
  a flat reflector lies and a sphere has no echo).
- *The other sweeps as evidence* (with a calibration, ``consensus=True``): the centres of
  one sphere must agree in the robot base. A seed that disagrees with the densest
  cluster is searched again about it; a centre that still disagrees is rejected with the
  distance, and where no three centres agree none is confirmed (see ``_consensus``,
  ``_reject_disagreeing``).
- *Sub-voxel centre* from the moments of the cap's echo (see ``_refine_centre``), its
  elevation from a least-squares parabola through the cap's peak grey level per slice,
  slices clipped at 255 left out (``_elevation_vertex``); a centre whose elevation that
  fit gives only to worse than ``_MAX_ELEVATION_SIGMA`` (1 σ) is rejected with it.

Frames of one sweep share their orientation (a linear sweep); the re-stack applies each
frame's in-plane and elevational offset and treats the frames as parallel (the residual
rotation between frames of a sweep is the robot's repeatability, micro-radians).
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numba
import numpy as np
from numpy.typing import NDArray

from . import se3
from .errors import LocalizationError
from .records import Sweep
from .robust import outlier_limit

__all__ = [
    "LocalizerConfig",
    "SphereProfile",
    "SweepLocalization",
    "SweepVolume",
    "fibonacci_hemisphere",
    "half_ball_samples",
    "localize_sphere",
    "score_candidates",
    "score_candidates_reference",
    "score_grid",
    "sphere_profile",
    "stack_sweep",
]

Array = NDArray[np.float64]

# Label values of the stacked volume (int16): a sample adds 1 to the valid count, and a
# bright one also _UNIT to the bright count, so one integer sum yields both (valid =
# sum % _UNIT, bright = sum // _UNIT) for up to _UNIT - 1 samples per set.
_UNIT = 512
_OUTSIDE, _DARK, _BRIGHT = 0, 1, 1 + _UNIT
MAX_SAMPLES = _UNIT - 1
_GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
_REFINE_ROUNDS = 4
# The confinement test's band (× the CAD radius) on the probe side: a sphere's echo ends
# at its surface, a flat reflector's (a plate, the tank floor) runs on past it.
_OUTER_BAND = (1.3, 1.8)
# Separate local maxima of the coarse grid searched finely (method "refined").
_HYPOTHESES = 4
# A centre whose elevation the cap's echo gives only to worse than this (1 σ, metres) is
# rejected: at 2 σ it could be a millimetre off.
_MAX_ELEVATION_SIGMA = 0.5e-3
_REFINE_TOL = 5e-6  # metres: a twentieth of a pixel
_MM = 1e-3


@dataclass(frozen=True)
class LocalizerConfig:
    """Threshold-free sphere localization (paper, "Threshold-Free Sphere Localization")."""

    method: Literal["paper", "refined", "fixed_threshold"] = field(
        default="refined",
        metadata={
            "doc": "'paper': grid-point centres exactly as published; 'refined': "
            "brightness also above each depth's noise floor, the grid's best separate "
            "maxima looked at finely, a sphere's echo required to stop at the CAD radius "
            "(a flat reflector's runs on), the specular arc alone where the whole cap is "
            "not seen, and a sub-voxel centre from the cap's echo; 'fixed_threshold': the "
            "baseline the paper argues against (one absolute grey-level threshold, "
            "largest bright set, least-squares sphere; calib/baseline.py)."
        },
    )
    fixed_threshold: int = field(
        default=120,
        metadata={
            "doc": "The fixed_threshold baseline's grey level (0-255), tuned once at the "
            "nominal gain and depth: the best of 60, 90, …, 240 by median error "
            "(scenarios/tune_fixed_threshold.yaml, seed 100); unused by the "
            "threshold-free methods.",
            "ge": 1,
            "le": 255,
        },
    )
    grid_mm: float = field(
        default=1.0,
        metadata={"doc": "Spacing of the exhaustive candidate-centre grid.", "gt": 0.05, "le": 5},
    )
    shell_samples: int = field(
        default=256,
        metadata={"doc": "Fibonacci directions on the proximal shell.", "ge": 8, "le": 511},
    )
    interior_samples: int = field(
        default=256, metadata={"doc": "Samples in the proximal half-ball.", "ge": 8, "le": 511}
    )
    refinement_passes: int = field(
        default=2, metadata={"doc": "Radial-band refinement passes.", "ge": 0, "le": 10}
    )
    profile_directions: int = field(
        default=64,
        metadata={
            "doc": "Fibonacci directions per trial radius of the radial brightness profile "
            "(averaged over all sweeps of the sphere, so a few dozen suffice).",
            "ge": 8,
            "le": 4096,
        },
    )
    refine_window_mm: float = field(
        default=2.0,
        metadata={
            "doc": "Refinement passes search ± this around the current centre.",
            "ge": 0,
            "le": 20,
        },
    )
    min_coverage: float = field(
        default=0.7,
        metadata={
            "doc": "A candidate needs at least this share of its shell and of its "
            "interior samples inside the acquired volume (partial caps are "
            "scored from their visible part; too small a part is noise).",
            "ge": 0,
            "le": 1,
        },
    )
    relocalize_window_mm: float = field(
        default=3.0,
        metadata={
            "doc": "After a calibration update, each sweep is re-stacked and searched ± "
            "this around its previous centre (the whole grid again when the best "
            "candidate lies on the window's edge, or the sweep had no centre).",
            "gt": 0,
            "le": 20,
        },
    )
    expected_depth_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Depth of the sphere centre the acquisition plan puts in the image. "
            "Method 'refined' searches only within ± expected_window_mm of it and of the "
            "image's centre line: a bright reflector elsewhere (the plate under the "
            "sphere, the tank floor) cannot win a sweep whose sphere is too faint to see. "
            "Unset in a scenario: protocol.target_depth_mm; `uscal calibrate` uses the "
            "depth a dataset recorded (the whole image if it recorded none).",
            "gt": 0,
            "le": 200,
        },
    )
    expected_window_mm: float = field(
        default=10.0,
        metadata={
            "doc": "Half-width of that window, laterally and in depth: it must cover the "
            "plan's in-plane offsets (protocol.translation_mm) and how far the taught "
            "pose may miss the target (3 × protocol.teaching_error_mm).",
            "gt": 0,
            "le": 200,
        },
    )
    min_score: float = field(
        default=0.2,
        metadata={
            "doc": "Detection confidence: a sweep whose best score (a difference of "
            "bright fractions, not an intensity) stays below this is rejected.",
            "ge": 0,
            "le": 1,
        },
    )


# ----------------------------------------------------------------------------- samples


def fibonacci_hemisphere(n: int) -> Array:
    """``n`` near-uniform unit directions (n, 3) on the proximal hemisphere (y < 0: towards
    the transducer face, which looks along +y)."""
    i = np.arange(n) + 0.5
    y = -i / n  # uniform in (-1, 0): equal areas on the hemisphere
    r = np.sqrt(1.0 - y**2)
    phi = i * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), y, r * np.sin(phi)])


def half_ball_samples(n: int, radius: float, inner: float = 0.0) -> Array:
    """``n`` deterministic volume-distributed points (n, 3) in the proximal half-shell
    ``inner ≤ r ≤ radius`` (a half-ball for ``inner = 0``), y ≤ 0."""
    i = np.arange(n) + 0.5
    u = (i * 0.7548776662466927) % 1.0  # R2 sequence, second coordinate: radius
    r = np.cbrt(inner**3 + u * (radius**3 - inner**3))
    return fibonacci_hemisphere(n) * r[:, None]


# ----------------------------------------------------------------------------- stacking


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


def frame_offsets(sweep: Sweep, T_ee_us: Array | None) -> Array:
    """Each frame's origin in the sweep's reference frame, (n, 3) metres.

    Without ``T_ee_us`` the frames sit on the elevational axis at the robot-measured
    distances along the sweep; with it, at their full offsets (in-plane shift included).
    """
    T = sweep.T_base_ee
    ref = sweep.reference_index
    if T_ee_us is None:
        t = T[:, :3, 3]
        direction = t[-1] - t[0]
        direction /= np.linalg.norm(direction)
        z = (t - t[ref]) @ direction
        return np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    T_base_us = T @ T_ee_us
    return se3.apply(se3.invert(T_base_us[ref]), T_base_us[:, :3, 3])


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
def _grid_sums(
    bits, nearest, frame_rows, frame_cols, H, W, start, step, count, offsets
):  # pragma: no cover - compiled
    """Encoded label sums (valid + _UNIT · bright) of every grid candidate.

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
    # every shifted frame.
    shift_c = np.rint(offsets[:, 0] / sx).astype(np.int64)
    shift_r = np.rint(offsets[:, 1] / sy).astype(np.int64)
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
    )


# ----------------------------------------------------------------------------- scoring


def _offsets_vox(vol: SweepVolume, P: Array) -> NDArray[np.int64]:
    """Sample offsets (m, 3) in metres → integer voxel offsets (m, 3) as (k, r, c), in
    memory order (consecutive lookups then touch neighbouring cache lines)."""
    dx, dy, dz = vol.spacing
    o = np.column_stack(
        [np.rint(P[:, 2] / dz), np.rint(P[:, 1] / dy), np.rint(P[:, 0] / dx)]
    ).astype(np.int64)
    return o[np.lexsort((o[:, 2], o[:, 1], o[:, 0]))]


def _bright_fraction(sums: NDArray[np.integer], n_samples: int, min_coverage: float) -> Array:
    """Bright share of the valid samples from encoded label sums; NaN where fewer than
    ``min_coverage`` of the ``n_samples`` (or none) were inside the volume."""
    valid, bright = sums % _UNIT, sums // _UNIT
    enough = (valid > 0) & (valid >= min_coverage * n_samples)
    return np.where(enough, bright / np.maximum(valid, 1), np.nan)


def _contrast(fractions: dict[str, Array]) -> tuple[Array, Array, Array]:
    """(score, f_shell, f_interior): score = f_shell − f_interior, −inf where undefined."""
    score = fractions["shell"] - fractions["interior"]
    return np.where(np.isnan(score), -np.inf, score), fractions["shell"], fractions["interior"]


def score_candidates(
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
    min_coverage: float = 0.0,
) -> tuple[Array, Array, Array]:
    """Scores of candidate centres (voxel indices (N, 3) as (k, r, c)).

    Returns ``(score, f_shell, f_interior)``, each (N,); candidates with fewer than
    ``min_coverage`` of their shell or interior samples inside the volume (or none) score
    −inf. Samples take the voxel at candidate + rounded offset, so a candidate on the
    voxel grid sees exactly the voxels the reference implementation looks up one by one.
    """
    fractions = {
        "shell": _fractions(vol, candidates, shell, min_coverage),
        "interior": _fractions(vol, candidates, interior, min_coverage),
    }
    return _contrast(fractions)


def _fractions(
    vol: SweepVolume, candidates: NDArray[np.int64], P: Array, min_coverage: float
) -> Array:
    """Bright share of the samples ``P`` (m, 3) about each candidate voxel (N, 3), NaN
    where fewer than ``min_coverage`` of them lie inside the volume."""
    o = _offsets_vox(vol, P)
    sums = np.empty(len(candidates), dtype=np.int64)
    for s in range(0, len(candidates), 2048):
        idx = candidates[s : s + 2048, None, :] + o[None, :, :]
        block = vol.label_at(idx[..., 0], idx[..., 1], idx[..., 2])
        sums[s : s + 2048] = block.sum(axis=1, dtype=np.int64)
    return _bright_fraction(sums, len(o), min_coverage)


def score_grid(
    vol: SweepVolume,
    start: tuple[int, int, int],
    step: tuple[int, int, int],
    count: tuple[int, int, int],
    shell: Array,
    interior: Array,
    min_coverage: float = 0.0,
) -> tuple[Array, Array, Array]:
    """:func:`score_candidates` for a regular grid of candidates, (count) shaped."""
    if step[2] != vol.column_step:
        vol = vol.with_column_step(step[2])
    H, W = vol._frames.shape[1:]
    fractions = {}
    for name, P in (("shell", shell), ("interior", interior)):
        o = _offsets_vox(vol, P)
        sums = _grid_sums(
            vol.bits,
            vol._nearest,
            vol._frame_rows,
            vol._frame_cols,
            H,
            W,
            np.asarray(start, dtype=np.int64),
            np.asarray(step, dtype=np.int64),
            np.asarray(count, dtype=np.int64),
            o,
        )
        fractions[name] = _bright_fraction(sums, len(o), min_coverage)
    return _contrast(fractions)


def score_candidates_reference(
    sweep: Sweep,
    T_ee_us: Array | None,
    axial_scale: float,
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
) -> Array:
    """The same scores computed the obvious way, one sample at a time, from the frames.

    For each sample: its voxel (candidate + rounded offset), that voxel's position in the
    reference frame, the nearest frame in elevation, the pixel of that frame under the
    voxel (through the frame's offset), and the comparison with that frame's mean. Slow;
    the test oracle of :func:`score_candidates`.
    """
    offsets = frame_offsets(sweep, T_ee_us)
    n, H, W = sweep.images.shape
    sx, sy = sweep.spacing[0], sweep.spacing[1] * axial_scale
    means = sweep.images.reshape(n, -1).mean(axis=1)
    slice_z = vol.z0 + np.arange(vol.shape[0]) * vol.spacing[2]
    out = np.empty(len(candidates))
    for i, cand in enumerate(candidates):
        fractions = []
        for P in (shell, interior):
            bright = valid = 0
            for o in _offsets_vox(vol, P):
                k, r, c = cand + o
                if not 0 <= k < len(slice_z):
                    continue  # outside the swept elevations
                j = int(np.argmin(np.abs(slice_z[k] - offsets[:, 2])))
                x, y, _ = vol.position(np.float64(k), np.float64(r), np.float64(c))
                # The pixel of frame j under the voxel, through the frame's offset.
                col = int(np.rint((x - offsets[j, 0]) / sx + (W - 1) / 2))
                row = int(np.rint((y - offsets[j, 1]) / sy))
                if not (0 <= row < H and 0 <= col < W):
                    continue
                valid += 1
                bright += int(sweep.images[j, row, col] > means[j])
            fractions.append(bright / valid if valid else np.nan)
        s = fractions[0] - fractions[1]
        out[i] = -np.inf if np.isnan(s) else s
    return out


# ----------------------------------------------------------------------------- search


@dataclass(frozen=True)
class SweepLocalization:
    """Result for one sweep.

    ``centre`` (3,) metres in the sweep's reference frame (NaN when rejected); ``score`` the
    peak score; ``f_shell``/``f_interior`` its two fractions (their difference is the
    contrast; with ``method="refined"`` the score is the confined contrast ``f_shell −
    max(f_interior, f_outer)``); ``accepted`` and, if not, ``reason``.
    """

    target: str
    pose_id: int
    centre: Array
    score: float
    f_shell: float
    f_interior: float
    accepted: bool
    reason: str = ""
    f_outer: float = float("nan")  # bright share outside the sphere, probe side ("refined")


def _candidate_grid(
    vol: SweepVolume, radius: float, grid: float, cfg: LocalizerConfig | None = None
) -> tuple[tuple[int, int, int], tuple[int, int, int], tuple[int, int, int]]:
    """(start, step, count) in voxels of the 1 mm candidate grid over the sweep, starting
    one radius below the face; with method "refined" and an expected depth, only within
    the plan's window (``expected_window_mm`` about the expected depth and the centre
    line)."""
    dx, dy = vol.spacing[:2]
    K, H, W = vol.shape
    step = candidate_step(vol.spacing, grid)
    lo = [0, max(int(np.ceil(radius / dy)) - vol.row0, 0), 0]
    hi = [K, H, W]  # exclusive
    if cfg is not None and cfg.method == "refined" and cfg.expected_depth_mm is not None:
        half = cfg.expected_window_mm * _MM
        depth = cfg.expected_depth_mm * _MM
        centre_col = (vol.width - 1) / 2 - vol.col0
        lo[1] = max(lo[1], int(np.ceil((depth - half) / dy)) - vol.row0)
        hi[1] = min(hi[1], int(np.floor((depth + half) / dy)) - vol.row0 + 1)
        lo[2] = max(lo[2], int(np.ceil(centre_col - half / dx)))
        hi[2] = min(hi[2], int(np.floor(centre_col + half / dx)) + 1)
    start = tuple(lo)
    count = tuple(max(0, -(-(n - s0) // st)) for n, s0, st in zip(hi, start, step, strict=True))
    return start, step, count


def _best_on_grid(vol, start, step, count, shell, interior, min_coverage):
    """(centre voxel, score, f_shell, f_interior) of the best candidate of a grid; score
    −inf for a grid without candidates (a window wholly outside the volume)."""
    if min(count) <= 0:
        return np.array(start), -np.inf, float("nan"), float("nan")
    score, fs, fi = score_grid(vol, start, step, count, shell, interior, min_coverage)
    i = np.unravel_index(int(np.argmax(score)), score.shape)
    cv = np.array(start) + np.array(step) * np.array(i)
    return cv, float(score[i]), float(fs[i]), float(fi[i])


@dataclass(frozen=True)
class _Hypothesis:
    """A candidate centre (voxel) with its confined contrast ``f_shell − max(f_interior,
    f_outer)`` and the three fractions."""

    voxel: NDArray[np.int64]
    score: float
    f_shell: float
    f_interior: float
    f_outer: float


def _outer_samples(n: int, radius: float) -> Array:
    """The confinement band's samples: the probe-side half-shell ``_OUTER_BAND`` × R."""
    return half_ball_samples(n, _OUTER_BAND[1] * radius, _OUTER_BAND[0] * radius)


def _best_nearby(
    vol: SweepVolume,
    candidates: NDArray[np.int64],
    shell: Array,
    interior: Array,
    outers: Sequence[Array],
    min_coverage: float,
) -> _Hypothesis:
    """The candidate the paper's contrast ``f_shell − f_interior`` prefers, with its
    confined contrast: its cap must stand out from the inside of the sphere *and* from
    each set of ``outers`` just outside it (the water on the probe side, the tangent
    plane), where a sphere has no echo and a flat reflector (plate, floor) does. A set
    wholly outside the image is no evidence either way."""
    fs = _fractions(vol, candidates, shell, min_coverage)
    fi = _fractions(vol, candidates, interior, min_coverage)
    paper = np.where(np.isnan(fs - fi), -np.inf, fs - fi)
    i = int(np.argmax(paper))
    fo = float(np.fmax.reduce([_fractions(vol, candidates[i : i + 1], P, 0.0)[0] for P in outers]))
    confined = fs[i] - np.fmax(fi[i], fo)
    return _Hypothesis(
        candidates[i],
        float(confined) if np.isfinite(confined) else -np.inf,
        float(fs[i]),
        float(fi[i]),
        fo,
    )


def _local_maxima(vol, start, step, count, score, radius, k: int) -> list[NDArray[np.int64]]:
    """Up to ``k`` best grid candidates more than ``radius`` apart (greedy, best first)."""
    flat = score.ravel()
    order = np.argsort(-flat, kind="stable")[:4096]
    chosen: list[NDArray[np.int64]] = []
    where: list[Array] = []
    for i in order:
        if not np.isfinite(flat[i]):
            break
        v = np.array(start) + np.array(step) * np.array(np.unravel_index(i, score.shape))
        p = vol.position(*v.astype(float))
        if all(np.linalg.norm(p - q) > radius for q in where):
            chosen.append(v)
            where.append(p)
            if len(chosen) == k:
                break
    return chosen


def _fine_candidates(vol: SweepVolume, voxel: NDArray[np.int64], grid: float) -> NDArray[np.int64]:
    """Candidates within one coarse grid step of ``voxel`` at half its spacing, inside the
    volume: the coarse grid can miss a thin cap's shell by up to half a step."""
    half = candidate_step(vol.spacing, grid)
    fine = candidate_step(vol.spacing, grid / 2)
    axes = [
        np.arange(max(v - h, 0), min(v + h, n - 1) + 1, f)
        for v, h, f, n in zip(voxel, half, fine, vol.shape, strict=True)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int64)


def _hypothesis_search(
    vol: SweepVolume, radius: float, grid: float, shell: Array, interior: Array, cfg
) -> list[tuple[NDArray[np.int64], float, float, float]]:
    """The whole candidate grid scored as the paper scores it, then its ``_HYPOTHESES``
    best separate maxima searched finely and judged by their confined contrast there;
    best first, each as (grid voxel, score, f_shell, f_interior) of the grid point. A
    faint thin cap that the coarse grid straddles scores below a strong flat reflector
    there, and recovers its contrast on the fine grid, where the reflector
    gains little (it looks the same from any nearby point)."""
    start, step, count = _candidate_grid(vol, radius, grid, cfg)
    if min(count) <= 0:
        return []
    score, fs, fi = score_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
    outer = _outer_samples(len(shell), radius)
    found = []
    for voxel in _local_maxima(vol, start, step, count, score, radius, _HYPOTHESES):
        fine = _fine_candidates(vol, voxel, grid)
        h = _best_nearby(vol, fine, shell, interior, (outer,), cfg.min_coverage)
        found.append((h.score, voxel))
    # Ranked by the confined contrast found nearby; each seed stays the coarse grid
    # point (the paper's seed whenever its best maximum wins).
    out = []
    for _, voxel in sorted(found, key=lambda f: -f[0]):
        i = tuple((voxel - np.array(start)) // np.array(step))
        out.append((voxel, float(score[i]), float(fs[i]), float(fi[i])))
    return out


# The specular arc (method "refined"): where the sphere's flanks are lost below the noise
# floor (an attenuating gel, a deep target at low gain) only the cap about normal
# incidence echoes, within _ARC_DEG of the beam axis (a mirror tilted by θ deflects the
# echo by 2θ, out of the receive aperture beyond ≈ 7-13°; the echo stays visible a little
# further). Its confinement: the tangent plane at the top, _TANGENT_BAND × R from the
# touching point, where a sphere has no echo and a flat reflector lies.
_ARC_DEG = 20.0
_TANGENT_BAND = (0.6, 1.4)


def _arc_samples(n: int, radius: float) -> Array:
    """Shell directions within ``_ARC_DEG`` of the beam axis (towards the face), × R."""
    d = fibonacci_hemisphere(int(np.ceil(n / (1.0 - np.cos(np.radians(_ARC_DEG))))))
    return d[-d[:, 1] >= np.cos(np.radians(_ARC_DEG))][:n] * radius


def _tangent_samples(n: int, radius: float) -> Array:
    """Points of the plane touching the sphere's top, ``_TANGENT_BAND`` × R from it
    (golden-angle spiral, uniform in area)."""
    i = np.arange(n) + 0.5
    lo, hi = _TANGENT_BAND
    r = radius * np.sqrt(lo**2 + (i / n) * (hi**2 - lo**2))
    phi = i * _GOLDEN_ANGLE
    return np.column_stack([r * np.cos(phi), np.full(n, -radius), r * np.sin(phi)])


def _arc_search(
    vol: SweepVolume, radius: float, grid: float, cfg: LocalizerConfig
) -> _Hypothesis | None:
    """The best candidate whose specular arc stands out from the sphere's inside, from the
    water or gel just above it and from its tangent plane, among the plan window's
    ``_HYPOTHESES`` best separate maxima of the arc's contrast, each searched finely."""
    start, step, count = _candidate_grid(vol, radius, grid, cfg)
    if min(count) <= 0:
        return None
    arc = _arc_samples(cfg.shell_samples, radius)
    interior = half_ball_samples(cfg.interior_samples, radius)
    above = arc * (0.5 * sum(_OUTER_BAND))  # the outer band straight above the arc
    tangent = _tangent_samples(cfg.shell_samples, radius)
    score, _, _ = score_grid(vol, start, step, count, arc, interior, cfg.min_coverage)
    best = None
    for voxel in _local_maxima(vol, start, step, count, score, radius, _HYPOTHESES):
        fine = _fine_candidates(vol, voxel, grid)
        h = _best_nearby(vol, fine, arc, interior, (above, tangent), cfg.min_coverage)
        if best is None or h.score > best.score:
            best = h
    return best


def _local_window(
    centre_vox: Array, vol: SweepVolume, window: float, grid: float
) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """(start, step, count) of the candidate grid within ± ``window`` of a centre voxel,
    clipped to the volume."""
    step = candidate_step(vol.spacing, grid)
    start, count = [], []
    for centre, s, st, size in zip(centre_vox, vol.spacing[::-1], step, vol.shape, strict=True):
        half = int(np.rint(window / s))
        ax = np.arange(centre - half, centre + half + 1, st)
        ax = ax[(ax >= 0) & (ax < size)]
        start.append(int(ax[0]) if len(ax) else 0)
        count.append(len(ax))
    return tuple(start), step, tuple(count)


def radial_profile(
    vols: Sequence[SweepVolume], centres_vox: Sequence[Array], radii: Array, n_dirs: int
) -> Array:
    """Peak-normalised bright fraction on proximal hemispheres of trial radius, averaged
    over sweeps; (len(radii),)."""
    dirs = fibonacci_hemisphere(n_dirs)
    total = np.zeros(len(radii))
    count = np.zeros(len(radii))
    for vol, cv in zip(vols, centres_vox, strict=True):
        centre = vol.position(*np.asarray(cv, dtype=float))
        P = centre[None, None, :] + radii[:, None, None] * dirs[None, :, :]
        k, r, c = vol.index(P)
        lab = vol.label_at(k, r, c)
        valid = (lab > 0).sum(axis=1)
        bright = (lab == _BRIGHT).sum(axis=1)
        ok = valid > 0
        total[ok] += bright[ok] / valid[ok]
        count[ok] += 1
    profile = np.where(count > 0, total / np.maximum(count, 1), 0.0)
    peak = profile.max()
    return profile / peak if peak > 0 else profile


def profile_crossings(
    radii: Array, profile: Array
) -> tuple[float | None, float | None, float | None]:
    """(first rising 0.25 crossing, rising and falling 0.75 crossings around the peak) of
    a peak-normalised radial profile, linearly interpolated; None where it has none."""
    peak = int(np.argmax(profile))

    def crossing(level: float, rising: bool) -> float | None:
        idx = range(1, peak + 1) if rising else range(peak + 1, len(profile))
        for i in idx:
            a, b = profile[i - 1], profile[i]
            if (a < level <= b) if rising else (a >= level > b):
                return float(radii[i - 1] + (level - a) / (b - a) * (radii[i] - radii[i - 1]))
        return None

    return crossing(0.25, True), crossing(0.75, True), crossing(0.75, False)


def profile_bands(radii: Array, profile: Array, radius: float) -> tuple[float, float, float]:
    """(interior limit, shell inner, shell outer) from a peak-normalised radial profile:
    first rising 0.25 crossing; rising and falling 0.75 crossings around the peak. Falls
    back to (0.8 R, 0.9 R, 1.1 R) pieces when a crossing is missing, and to all three
    when the bands are not a shell outside an interior (a profile that peaks at the
    centre, e.g. from sweeps too sparse to resolve the cap, would otherwise turn the
    shell inside out and lose every sweep)."""
    inner, rise, fall = profile_crossings(radii, profile)
    bands = (
        inner if inner is not None else 0.8 * radius,
        rise if rise is not None else 0.9 * radius,
        fall if fall is not None else 1.1 * radius,
    )
    if not bands[0] <= bands[2] or not bands[1] < bands[2]:
        return 0.8 * radius, 0.9 * radius, 1.1 * radius
    return bands


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _cap_weights(
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


def _refine_centre(vol: SweepVolume, centre: Array, radius: float) -> tuple[Array, float]:
    """Sub-voxel centre from the moments of the cap's echo, and the standard error of its
    elevation (0 where not estimated; see :func:`_elevation_vertex`).

    The probe-facing cap is mirror-symmetric about the centre's lateral and elevational
    coordinates, so the echo-weighted means of x and z over the cap give them; the top of
    the cap (normal incidence, the strongest echo, seen in every nearby frame through the
    slice thickness) lies one radius above the centre, so its echo-weighted depth plus R
    gives y. A least-squares sphere fit would be pulled upwards instead: the elevation beam
    smears that top echo over neighbouring frames and flattens the stacked cap. Weights are
    grey levels above their brightness level (the frame mean, and the depth's noise floor
    with method "refined"); a few rounds re-centre the windows.
    """
    dx, dy, dz = vol.spacing
    seed = np.asarray(centre, dtype=float)
    current = seed
    z_sigma = 0.0
    K, H, W = vol.shape
    for _ in range(_REFINE_ROUNDS):
        x_c, y_c, z_c = current
        k0, _, c0 = (int(v) for v in vol.index(current))
        # Cap window: ±R laterally and in elevation, a band of ±R/2 about the cap's depth.
        ks = np.arange(max(k0 - int(radius / dz) - 1, 0), min(k0 + int(radius / dz) + 2, K))
        rs = np.arange(
            max(int((y_c - 1.5 * radius) / dy) - vol.row0, 0),
            min(int((y_c - 0.5 * radius) / dy) - vol.row0 + 1, H),
        )
        cs = np.arange(max(c0 - int(radius / dx) - 1, 0), min(c0 + int(radius / dx) + 2, W))
        if not (len(ks) and len(rs) and len(cs)):
            break
        # Coordinates are separable on the grid: keep them as three axes.
        zs = vol.z0 + ks * dz
        ys = (rs + vol.row0) * dy
        xs = (cs + vol.col0 - (vol.width - 1) / 2) * dx
        # Echo above its level, inside the shell band |d − R| ≤ R/2.
        w = _cap_weights(
            vol._frames,
            vol._levels,
            vol._nearest,
            vol._frame_rows,
            vol._frame_cols,
            ks,
            rs,
            cs,
            (zs - z_c) ** 2,
            (ys - y_c) ** 2,
            (xs - x_c) ** 2,
            (0.5 * radius) ** 2,
            (1.5 * radius) ** 2,
        )
        total = w.sum()
        if total <= 0:
            break
        x_new = float(w.sum(axis=(0, 1)) @ xs / total)
        z_mean = float(w.sum(axis=(1, 2)) @ zs / total)
        # Elevation from the top of the cap only (where the echo stands far above noise).
        near_x = np.abs(xs - x_new) <= 0.5 * _MM
        near_y = np.abs(ys - (y_c - radius)) <= 0.75 * _MM
        # Elevation from the top of the cap only (where the echo stands far above noise),
        # over every slice: beyond the elevation focus the beam is wider than a small
        # sphere and its echo of the top follows the beam profile well past ± R.
        # One brightness level for every slice: the vertex of the profile must not move
        # with the level. Each frame's level follows its own rows, and where the sphere's
        # echoes raise the depth's noise floor about the cap, the frames' in-plane drift
        # along the sweep (its axis a little off the image normal) slides the cap across
        # that bump: a level varying linearly with elevation tilts the profile and moved
        # the vertex by up to 0.15 mm at 45 mm.
        ks_all = np.arange(K)
        frame_of = vol._nearest[ks_all]
        rows = np.clip(
            rs[near_y][None, :] - vol._frame_rows[frame_of][:, None], 0, vol._frames.shape[1] - 1
        )
        level = 0.0
        if rows.size:
            level = float(
                np.median(np.take_along_axis(vol._levels[frame_of], rows, axis=1).max(axis=1))
            )
        top = np.maximum(vol.intensity(ks_all, rs[near_y], cs[near_x], level), 0.0)
        # A slice's top at a grey level of 255 is saturated.
        clip = np.full(K, 255.0 - level)
        zs_all = vol.z0 + ks_all * dz
        z_new, z_sigma = _elevation_vertex(
            top, zs_all, z_mean, dz, clip, np.abs(zs_all - z_mean) <= radius
        )
        # Top of the cap: the column under (x, z) in the nearest frames.
        col = np.abs(xs - x_new) <= max(dx, 0.25 * _MM)
        frames = np.abs(zs - z_new) <= 0.75 * dz
        wt = w[frames][:, :, col].sum(axis=(0, 2))
        if wt.sum() <= 0:
            break
        y_top = _axial_peak(vol.intensity(ks[frames], rs, cs[col], level), 255.0 - level, ys, wt)
        new = np.array([x_new, y_top + radius, z_new])
        moved = np.linalg.norm(new - current)
        current = new
        if moved < _REFINE_TOL:
            break
    # A refinement that wanders far from the grid seed is not trusted.
    if np.linalg.norm(current - seed) > 3.0 * max(dx, dy, dz, _MM):
        return seed, 0.0
    return current, z_sigma


def _axial_peak(grey: Array, clip: float, ys: Array, w: Array) -> float:
    """Depth of the cap's top echo: the vertex of the parabola through the brightest row
    of the column's grey levels (``grey`` (slices, rows, columns), less one level, at
    ``clip`` where saturated; rows at depths ``ys``) and its two neighbours.

    The echo of the top is not symmetric in depth: the rest of the cap within the slice
    thickness lies deeper (e²/2R at elevation e), so the echo rises sharply and trails
    off below. Its peak is the top; a weighted mean over the echo lies in its tail, and
    by how much depends on where the brightness level cuts the tail, i.e. on the gain
    (0.08 mm deeper at −10 dB than at 0 dB, 45 mm deep). Where the peak is saturated or
    on the band's edge, the mean of the weights ``w`` (rows) over the echo."""
    profile = grey.sum(axis=(0, 2))
    i = int(np.argmax(profile))
    saturated = (grey[:, max(i - 1, 0) : i + 2] >= clip - 0.5).any()
    if 0 < i < len(profile) - 1 and not saturated:
        g_m, g_0, g_p = profile[i - 1 : i + 2]
        curvature = g_m - 2.0 * g_0 + g_p
        if curvature < 0:
            return float(ys[i] + 0.5 * (g_m - g_p) / curvature * (ys[1] - ys[0]))
    return float(w @ ys / w.sum())


def _elevation_vertex(
    w: Array,
    zs: Array,
    z_mean: float,
    dz: float,
    clip: Array | None = None,
    search: NDArray[np.bool_] | None = None,
) -> tuple[float, float]:
    """Sub-slice elevation of the cap and its standard error (0 where not estimated) from
    its peak grey level per slice (``w`` is
    (slices, ...), ``zs`` the slices' elevations, ``clip`` each slice's ``w`` at a grey
    level of 255, ``search`` the slices where the brightest is looked for).

    The peak grey level per slice is log-compressed (dB), in which a Gaussian beam profile
    is a parabola; its vertex is unbiased where a weighted mean over slices is biased by
    where the centre falls between frames. The parabola is fitted by least squares to the
    contiguous run of slices above half the maximum: three slices where the beam is thin
    (its vertex through them), more where it is wide beyond the elevation focus (there the
    three-slice vertex is a difference of nearly equal noisy peaks). Slices clipped at 255
    (high gain) are left out: the flanks on both sides still fix the vertex of a symmetric
    profile. Without a usable fit, the midpoint of the half-maximum crossings.
    """
    if w.size == 0:
        return z_mean, 0.0
    peaks = w.reshape(len(w), -1).max(axis=1)
    k = int(np.argmax(np.where(search, peaks, -np.inf) if search is not None else peaks))
    if peaks[k] <= 0:
        return z_mean, 0.0
    half = 0.5 * peaks[k]
    lo = hi = k
    while lo > 0 and peaks[lo - 1] >= half:
        lo -= 1
    while hi < len(peaks) - 1 and peaks[hi + 1] >= half:
        hi += 1
    # One slice beyond the run on each side: the parabola needs the fall on both sides.
    lo, hi = max(lo - 1, 0), min(hi + 1, len(peaks) - 1)
    run = np.arange(lo, hi + 1)
    clipped = peaks[run] >= clip[run] - 0.5 if clip is not None else np.zeros(len(run), dtype=bool)
    use = run[~clipped & (peaks[run] > 0)]
    # Slices on both sides of the peak, or on both sides of a clipped top.
    if len(use) >= 3 and (use[0] < k < use[-1] or clipped.any()):
        u = (zs[use] - zs[k]) / dz
        fit = _parabola_vertex(u, peaks[use])
        if fit is not None and u[0] <= fit[0] <= u[-1]:
            return float(zs[k] + fit[0] * dz), fit[1] * dz
    top = run[clipped] if clipped.any() else np.array([k])
    return _half_maximum_midpoint(peaks, zs, int(top[0]), int(top[-1]), z_mean), 0.0


def _parabola_vertex(u: Array, y: Array) -> tuple[float, float] | None:
    """Vertex of the least-squares parabola through (u, y) and its standard error (from
    the fit's residuals by the delta method; 0 where fewer than 5 points leave no honest
    estimate of them); None unless it opens downwards."""
    coef, unscaled = np.polyfit(u, y, 2, cov="unscaled")  # unscaled: (AᵀA)⁻¹
    a, b = coef[0], coef[1]
    if a >= 0:
        return None
    vertex = -b / (2 * a)
    dof = len(u) - 3
    if dof < 2:
        return float(vertex), 0.0
    s2 = float(np.sum((np.polyval(coef, u) - y) ** 2)) / dof
    cov = s2 * unscaled[:2, :2]
    g = np.array([b / (2 * a * a), -1 / (2 * a)])  # ∂vertex / ∂(a, b)
    return float(vertex), float(np.sqrt(max(g @ cov @ g, 0.0)))


def _half_maximum_midpoint(
    peaks: Array, zs: Array, first: int, last: int, fallback: float
) -> float:
    """Midpoint of the elevations where ``peaks`` crosses half its maximum below slice
    ``first`` and above slice ``last`` (linearly interpolated); ``fallback`` when the
    profile does not fall to half on both sides."""
    half = 0.5 * peaks[first : last + 1].max()

    def crossing(inner: int, step: int) -> float | None:
        i = inner
        while 0 <= i + step < len(peaks):
            a, b = peaks[i], peaks[i + step]
            if b < half <= a:
                return float(zs[i] + (a - half) / (a - b) * (zs[i + step] - zs[i]))
            i += step
        return None

    lo, hi = crossing(first, -1), crossing(last, +1)
    return fallback if lo is None or hi is None else 0.5 * (lo + hi)


def _on_window_edge(index: tuple[int, ...], start, count, full_start, full_count, step) -> bool:
    """Whether a window's best candidate lies on an edge of the window that is not also an
    edge of the whole candidate grid (the peak may then lie outside the window)."""
    for i, s0, n, fs, fn, st in zip(index, start, count, full_start, full_count, step, strict=True):
        last = s0 + st * (n - 1)
        if i == 0 and s0 - st >= fs:
            return True
        if i == n - 1 and last + st <= fs + st * (fn - 1):
            return True
    return False


def _seed_search(vol, radius, grid, shell, interior, cfg, previous, expected=None):
    """The exhaustive search, or around a previous centre when there is one, or only
    around an expected centre when one is given."""
    full_start, step, full_count = _candidate_grid(vol, radius, grid, cfg)
    if expected is not None:
        k, r, c = (int(v) for v in vol.index(np.asarray(expected, dtype=float)))
        start, step, count = _local_window((k, r, c), vol, cfg.relocalize_window_mm * _MM, grid)
        start = tuple(max(s0, fs) for s0, fs in zip(start, full_start, strict=True))
        return _best_on_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
    if previous is not None and previous.accepted:
        k, r, c = (int(v) for v in vol.index(previous.centre))
        start, step, count = _local_window((k, r, c), vol, cfg.relocalize_window_mm * _MM, grid)
        start = tuple(max(s0, fs) for s0, fs in zip(start, full_start, strict=True))
        if all(n > 0 for n in count):
            best = _best_on_grid(vol, start, step, count, shell, interior, cfg.min_coverage)
            index = tuple(int(v) for v in (best[0] - np.array(start)) // np.array(step))
            if np.isfinite(best[1]) and not _on_window_edge(
                index, start, count, full_start, full_count, step
            ):
                return best
    if cfg.method == "refined":
        hyps = _hypothesis_search(vol, radius, grid, shell, interior, cfg)
        if hyps:
            return hyps[0]
    return _best_on_grid(vol, full_start, step, full_count, shell, interior, cfg.min_coverage)


# Consensus of one sphere's sweeps in the base frame: centres within _CLUSTER_MM of
# each other form a cluster; a centre agrees with the densest cluster within
# max(_AGREE_FLOOR_MM, a robust 3σ of the cluster's spread).
_CLUSTER_MM = 2.0
_AGREE_FLOOR_MM = 1.0
_MIN_CLUSTER = 3  # centres that agree before any is confirmed
_MIN_SWEEPS_SEEN = 6  # sweeps of a sphere before its share of detections is judged


def _agreeing(base: Array, found: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], Array, float]:
    """(agree, consensus, limit_mm): which of the found centres (n, 3, base frame) agree
    with the densest cluster of them, its mean, and the distance limit. The densest
    cluster, not the mean of all: wrong candidates scatter (a plate offers one anywhere
    along it) while right ones agree, even when they are fewer than half."""
    idx = np.flatnonzero(found)
    pts = base[idx]
    if len(idx) == 0:
        return found.copy(), np.full(3, np.nan), float("inf")
    near = np.linalg.norm(pts[:, None] - pts[None], axis=-1) < _CLUSTER_MM * _MM
    cluster = near[int(np.argmax(near.sum(axis=1)))]
    if cluster.sum() < _MIN_CLUSTER:
        return found.copy(), np.full(3, np.nan), float("inf")
    consensus = pts[cluster].mean(axis=0)
    d = np.linalg.norm(base - consensus, axis=1) / _MM
    limit = outlier_limit(d[idx][cluster], _AGREE_FLOOR_MM)
    return found & (d <= limit), consensus, limit


def _in_base(sweeps, centres, T_ee_us) -> tuple[list[Array], Array]:
    """Each sweep's reference pose ``T_base_ee[ref] @ T_ee_us`` and its centre (3, in that
    frame) in the base frame, (n, 3)."""
    T_ref = [s.T_base_ee[s.reference_index] @ np.asarray(T_ee_us) for s in sweeps]
    return T_ref, np.array([se3.apply(T, c) for T, c in zip(T_ref, centres, strict=True)])


def _consensus(sweeps, vols, results, T_ee_us, radius, grid, shell, interior, cfg):
    """With a calibration every sweep's centre maps into the robot base, where all of one
    sphere's must agree: a sweep whose seed disagrees with its siblings' (a plate or a
    reverberation won its whole grid) or that found nothing is searched again only
    within ``relocalize_window_mm`` of their consensus mapped into its frame."""
    centres = [
        v.position(*np.asarray(r[0], dtype=float)) for v, r in zip(vols, results, strict=True)
    ]
    T_ref, base = _in_base(sweeps, centres, T_ee_us)
    found = np.array([r[1] >= cfg.min_score for r in results])
    agree, consensus, limit = _agreeing(base, found)
    notes: dict[int, str] = {}
    if not np.isfinite(consensus).all():
        return results, notes
    out = list(results)
    for i in np.flatnonzero(~agree):
        expected = se3.apply(se3.invert(T_ref[i]), consensus)
        out[i] = _seed_search(vols[i], radius, grid, shell, interior, cfg, None, expected)
        if found[i]:
            d = float(np.linalg.norm(base[i] - consensus) / _MM)
            notes[i] = (
                f"disagrees with the sphere's other sweeps: its best candidate lay {d:.2f} mm "
                f"from their consensus (limit {limit:.2f} mm), and nothing near the "
                f"consensus looks like the sphere"
            )
    return out, notes


def localize_sphere(
    sweeps: Sequence[Sweep],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    axial_scale: float = 1.0,
    previous: Sequence[SweepLocalization | None] | None = None,
    expected: Sequence[Array | None] | None = None,
    consensus: bool = True,
) -> list[SweepLocalization]:
    """Localize one sphere in each of its sweeps (centres in each sweep's reference frame).

    Parameters
    ----------
    sweeps : the sweeps of one sphere
    T_ee_us : (4, 4) float or None
        Current calibration for re-stacking; None stacks at the robot-measured spacing.
    radius : float, metres
        The sphere radius: the only geometric prior.
    axial_scale : float
        c_medium / c_assumed (1 when the speed-of-sound correction is off).
    previous : the sweeps' localizations before this re-stack, if any
        Each sweep with one is then searched within ``relocalize_window_mm`` of its
        previous centre (falling back to the whole grid as described there); None entries
        get the whole grid.
    expected : a predicted centre (3,) per sweep, or None, in its reference frame (e.g. its
        siblings' consensus through the current calibration): the sweep is searched only
        within ``relocalize_window_mm`` of it (its whole grid found something else). It
        takes precedence over ``previous``.
    consensus : with ``T_ee_us`` (and a method other than "paper"), use the sphere's other
        sweeps as evidence: seeds that disagree with their consensus in the base frame
        are searched again about it, centres that still disagree are rejected. For a
        trusted calibration; the alternation turns it off (its estimate may still be far
        off, and the calibration's own outlier stage does the same about its consensus).
    """
    if cfg.method == "fixed_threshold":
        from .baseline import localize_sphere_fixed_threshold

        return localize_sphere_fixed_threshold(sweeps, T_ee_us, radius, cfg, axial_scale)
    grid = cfg.grid_mm * 1e-3
    shell = fibonacci_hemisphere(cfg.shell_samples) * radius
    interior = half_ball_samples(cfg.interior_samples, radius)
    if previous is not None and len(previous) != len(sweeps):
        raise ValueError(f"{len(previous)} previous localizations for {len(sweeps)} sweeps")
    if expected is not None and len(expected) != len(sweeps):
        raise ValueError(f"{len(expected)} expected centres for {len(sweeps)} sweeps")
    vols = []
    for s in sweeps:
        column_step = candidate_step((s.spacing[0], s.spacing[1], 1.0), grid)[2]
        vols.append(stack_sweep(s, T_ee_us, axial_scale, column_step, cfg.method == "refined"))
    results = [
        _seed_search(
            vol,
            radius,
            grid,
            shell,
            interior,
            cfg,
            previous[i] if previous else None,
            expected[i] if expected else None,
        )
        for i, vol in enumerate(vols)
    ]
    notes: dict[int, str] = {}
    use_consensus = consensus and T_ee_us is not None and cfg.method != "paper"
    if use_consensus:
        results, notes = _consensus(
            sweeps, vols, results, T_ee_us, radius, grid, shell, interior, cfg
        )
    radii = np.arange(0.0, 1.6 * radius, min(vols[0].spacing[:2]))
    for _ in range(cfg.refinement_passes):
        ok = [i for i, r in enumerate(results) if r[1] >= cfg.min_score]
        if not ok:
            break
        profile = radial_profile(
            [vols[i] for i in ok], [results[i][0] for i in ok], radii, cfg.profile_directions
        )
        inner, rise, fall = profile_bands(radii, profile, radius)
        shell_p = half_ball_samples(cfg.shell_samples, fall, rise)
        interior_p = half_ball_samples(cfg.interior_samples, inner)
        results = [
            _best_on_grid(
                vol,
                *_local_window(res[0], vol, cfg.refine_window_mm * 1e-3, grid),
                shell_p,
                interior_p,
                cfg.min_coverage,
            )
            for vol, res in zip(vols, results, strict=True)
        ]
    out = []
    outer = _outer_samples(len(shell), radius)
    for i, (sweep, vol, (cv, score, fs, fi)) in enumerate(zip(sweeps, vols, results, strict=True)):
        centre = vol.position(*np.asarray(cv, dtype=float))
        fo = float("nan")
        z_sigma = 0.0
        accepted = bool(score >= cfg.min_score)
        reason = "" if accepted else notes.get(i, _not_found(score, cfg))
        if accepted and cfg.method == "refined":
            # Evidence beyond the score that picked it: the CAD sphere's cap must stand
            # out from the water just outside it as well (a flat reflector does not).
            fine = _fine_candidates(vol, np.asarray(cv, dtype=np.int64), grid)
            h = _best_nearby(vol, fine, shell, interior, (outer,), 0.0)
            fo = h.f_outer
            if h.f_shell - h.f_outer < cfg.min_score:
                accepted = False
                reason = (
                    f"not a sphere: its echo runs on outside the CAD radius (bright share "
                    f"{h.f_shell:.2f} on the sphere, {h.f_outer:.2f} at "
                    f"{_OUTER_BAND[0]:g}-{_OUTER_BAND[1]:g} R; a flat reflector?)"
                )
            else:
                centre, z_sigma = _refine_centre(vol, centre, radius)
        elif cfg.method == "refined" and i not in notes:
            # Nothing with a sphere's whole cap: perhaps only its specular arc echoes.
            arc = _arc_search(vol, radius, grid, cfg)
            if arc is not None and arc.score >= cfg.min_score:
                accepted, reason = True, ""
                score, fs, fi, fo = arc.score, arc.f_shell, arc.f_interior, arc.f_outer
                seed = vol.position(*arc.voxel.astype(float))
                centre, z_sigma = _refine_centre(vol, seed, radius)
        if accepted and z_sigma > _MAX_ELEVATION_SIGMA:
            # The cap's echo is about as bright in many frames (a weak echo in a beam
            # wider than the sphere): its elevation is not measured well enough.
            accepted = False
            reason = (
                f"elevation not measured: the cap's echo across the frames gives it to "
                f"± {z_sigma / _MM:.2f} mm (1 σ; at most {_MAX_ELEVATION_SIGMA / _MM:g})"
            )
        out.append(
            SweepLocalization(
                sweep.target,
                sweep.pose_id,
                centre if accepted else np.full(3, np.nan),
                score,
                fs,
                fi,
                accepted,
                reason,
                fo,
            )
        )
    if use_consensus:
        out = _reject_disagreeing(sweeps, out, T_ee_us)
    if cfg.method == "refined":
        out = _reject_if_rarely_seen(out)
    return out


def _reject_if_rarely_seen(locs: list[SweepLocalization]) -> list[SweepLocalization]:
    """The plan keeps the sphere in view in every sweep: a sphere whose echo stands out
    in fewer than half of them is at the noise floor (an attenuating gel too deep, a low
    gain), where the few detections are the ones noise happened to shape; none of them
    is accepted, each with that reason."""
    n = len(locs)
    found = sum(r.accepted for r in locs)
    if n < _MIN_SWEEPS_SEEN or 2 * found >= n:
        return locs
    reason = (
        f"sphere at the noise floor: found in only {found} of its {n} sweeps (a sphere "
        f"in view is found in most; at least half needed to trust any)"
    )
    return [
        replace(r, accepted=False, centre=np.full(3, np.nan), reason=reason) if r.accepted else r
        for r in locs
    ]


def _not_found(score: float, cfg: LocalizerConfig) -> str:
    if np.isfinite(score):
        return f"no sphere found: best score {score:.2f} < {cfg.min_score:.2f}"
    where = (
        f"within {cfg.expected_window_mm:g} mm of the plan's target depth "
        f"{cfg.expected_depth_mm:g} mm and the centre line"
        if cfg.method == "refined" and cfg.expected_depth_mm is not None
        else "in the sweep"
    )
    return f"no sphere found: no candidate centre {where} lies in the image"


def _reject_disagreeing(sweeps, locs, T_ee_us) -> list[SweepLocalization]:
    """Evidence from the siblings: an accepted centre that disagrees with the consensus of
    the sphere's other sweeps (base frame, through the calibration) is rejected with the
    distance and the limit. Where no three accepted centres agree (the sphere at the
    noise floor: a few caps and a few spots of the plate, scattered), none is
    confirmed, and none is accepted."""
    _, base = _in_base(sweeps, [loc.centre for loc in locs], T_ee_us)
    found = np.array([loc.accepted for loc in locs])
    agree, consensus, limit = _agreeing(base, found)
    unconfirmed = len(locs) >= _MIN_CLUSTER and not np.isfinite(consensus).all()
    out = []
    for i, loc in enumerate(locs):
        reason = ""
        if loc.accepted and unconfirmed:
            reason = (
                f"unconfirmed: fewer than {_MIN_CLUSTER - 1} other sweeps of the sphere "
                f"put its centre within {_CLUSTER_MM:g} mm of this one's ({int(found.sum())} "
                f"of {len(locs)} sweeps found a candidate)"
            )
        elif loc.accepted and not agree[i]:
            d = float(np.linalg.norm(base[i] - consensus) / _MM)
            reason = (
                f"disagrees with the sphere's other sweeps: {d:.2f} mm from their "
                f"consensus (limit {limit:.2f} mm)"
            )
        if reason:
            loc = replace(loc, centre=np.full(3, np.nan), accepted=False, reason=reason)
        out.append(loc)
    return out


@dataclass(frozen=True)
class SphereProfile:
    """The radial brightness profile of a sphere's sweeps about their localized centres
    (peak-normalised, averaged over the accepted sweeps) and the bands the localizer reads
    off it: ``interior`` (first rising 0.25 crossing), ``shell`` (rising and falling 0.75
    crossings); ``crossed`` says which of the three the profile has (the others are
    :func:`profile_bands`'s fall-backs, e.g. no 0.25 crossing when speckle keeps the
    interior above a quarter of the peak). Radii in metres."""

    radii: Array
    profile: Array
    interior: float
    shell: tuple[float, float]
    n_sweeps: int
    crossed: tuple[bool, bool, bool] = (True, True, True)


def sphere_profile(
    sweeps: Sequence[Sweep],
    localizations: Sequence[SweepLocalization],
    T_ee_us: Array | None,
    radius: float,
    cfg: LocalizerConfig,
    axial_scale: float = 1.0,
) -> SphereProfile:
    """:func:`radial_profile` and :func:`profile_bands` of localized sweeps, for showing
    what the localizer saw (the stacks are rebuilt under ``T_ee_us``, as the localization
    that produced the centres used)."""
    if len(localizations) != len(sweeps):
        raise ValueError(f"{len(localizations)} localizations for {len(sweeps)} sweeps")
    grid = cfg.grid_mm * 1e-3
    vols, centres = [], []
    for sweep, loc in zip(sweeps, localizations, strict=True):
        if loc.accepted:
            # The localizer's column step: the sweep's bright bits are then the ones it
            # already memoised (no second copy of them).
            step = candidate_step((sweep.spacing[0], sweep.spacing[1], 1.0), grid)[2]
            vol = stack_sweep(sweep, T_ee_us, axial_scale, step, cfg.method == "refined")
            vols.append(vol)
            centres.append(np.array(vol.index(loc.centre), dtype=float))
    if not vols:
        empty = np.zeros(0)
        return SphereProfile(empty, empty, float("nan"), (float("nan"),) * 2, 0)
    radii = np.arange(0.0, 1.6 * radius, min(vols[0].spacing[:2]))
    profile = radial_profile(vols, centres, radii, cfg.profile_directions)
    inner, rise, fall = profile_bands(radii, profile, radius)
    crossed = tuple(c is not None for c in profile_crossings(radii, profile))
    return SphereProfile(radii, profile, inner, (rise, fall), len(vols), crossed)
