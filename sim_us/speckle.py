"""Backscatter speckle that belongs to the medium, not to the frame.

Scatterers sit on a fixed grid of the scene frame (cell ``cell_m``); each cell's complex
Gaussian amplitude is picked by a counter-based hash of its grid index and a key from a
table of unit-variance complex Gaussians. So the same pose gives the same image,
neighbouring frames share scatterers, and frames decorrelate as the probe moves out of
the slice — with no stored volume, for any extent.

Summed coherently over the elevation beam and blurred with the PSF this gives fully
developed speckle: Rayleigh envelope (mean/std ≈ 1.91), log-domain std ≈ 5.57 dB.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["ScattererField"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_PRIMES = (np.uint64(0x8DA6B343), np.uint64(0xD8163841), np.uint64(0xCB1AB31F))
_TABLE_BITS = 16  # 65 536 amplitudes (fits the CPU cache); the hash scatters them
_TABLE_SHIFT = np.uint64(64 - _TABLE_BITS)


@numba.njit(cache=True, nogil=True)
def _cell_slot(i0, i1, i2, key):  # pragma: no cover - compiled
    """Table slot of grid cell (i0, i1, i2): the cell's coordinates mixed by odd
    constants, then the SplitMix64 finaliser (Steele et al. 2014), a well-mixed 64-bit
    hash; its top bits pick the slot."""
    h = (np.uint64(i0) * _PRIMES[0]) ^ (np.uint64(i1) * _PRIMES[1]) ^ (np.uint64(i2) * _PRIMES[2])
    h = (h ^ key) + _GOLDEN
    h = (h ^ (h >> np.uint64(30))) * _MIX1
    h = (h ^ (h >> np.uint64(27))) * _MIX2
    h = h ^ (h >> np.uint64(31))
    return np.intp(h >> _TABLE_SHIFT)


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _values_at_cells(idx, table, key, out):  # pragma: no cover - compiled
    for i in range(idx.shape[0]):
        out[i] = table[_cell_slot(idx[i, 0], idx[i, 1], idx[i, 2], key)]


class ScattererField:
    """The medium's scatterers: a complex amplitude for every grid cell of the scene.

    Parameters
    ----------
    cell_m : float
        Grid cell (metres); keep ≤ a third of the PSF so a resolution cell holds ≥ 10.
    key : int
        Identity of this medium's scatterers.
    """

    def __init__(self, cell_m: float, key: int) -> None:
        self.cell_m = float(cell_m)
        self.key = np.uint64(key & 0xFFFFFFFFFFFFFFFF)
        table_rng = np.random.default_rng(np.random.SeedSequence(int(self.key)))
        n = 1 << _TABLE_BITS
        # Unit variance: E|a|² = 1.
        self.table = (
            (table_rng.standard_normal(n) + 1j * table_rng.standard_normal(n)) / np.sqrt(2)
        ).astype(np.complex64)

    def at_cells(self, idx: NDArray[np.int64]) -> NDArray[np.complex64]:
        """Amplitudes of integer grid cells (..., 3)."""
        idx = np.asarray(idx, dtype=np.int64)
        flat = np.ascontiguousarray(idx.reshape(-1, 3))
        out = np.empty(len(flat), dtype=np.complex64)
        _values_at_cells(flat, self.table, self.key, out)
        return out.reshape(idx.shape[:-1])

    def at(self, P_scene: NDArray[np.floating]) -> NDArray[np.complex64]:
        """Amplitudes at points (..., 3), metres (nearest-cell lookup)."""
        return self.at_cells(np.floor(np.asarray(P_scene) / self.cell_m).astype(np.int64))

    def add_lattice_lines(
        self,
        acc: NDArray[np.complex64],
        rows: NDArray[np.float32],
        cols: NDArray[np.float32],
        offsets: NDArray[np.float32],
        weights: NDArray[np.float64],
        depth: NDArray[np.float64],
        medium_end: NDArray[np.float64],
        plane_of_line: NDArray[np.int64],
    ) -> None:
        """Add, in place, the scatterers of lattice lines to the pixels (H, W) of ``acc``.

        Line j's scatterer at pixel (r, c) is the cell ``floor(rows[r] + (cols[c] +
        offsets[j]))`` (cell units, float32, as :meth:`at_cells` takes them), weighted by
        ``weights[j, r]`` where the pixel's ``depth[r]`` lies before the medium's end along
        its column in sub-plane ``plane_of_line[j]`` (``medium_end[k, c]``), and not at all
        where the weight is 0. The same sums as building each line's cell indices and
        calling :meth:`at_cells` (in single precision: the weights are rounded to float32
        and the sums kept in complex64), in one compiled pass: the numpy version built
        five (H, W, 3) temporaries per line, ≈ 150 ms a frame in gel.
        """
        _add_lattice_lines(
            acc,
            rows,
            cols,
            offsets,
            weights,
            depth,
            medium_end,
            plane_of_line,
            self.table,
            self.key,
        )

    def smooth_at(self, P_scene: NDArray[np.floating]) -> NDArray[np.complex64]:
        """Amplitudes at points (n, 3), metres, varying continuously with the point: the
        trilinear interpolation of the eight surrounding cells, divided by the root of its
        weights' sum of squares so that every point keeps unit variance (a sum of
        independent complex Gaussians is one, of variance Σ w²).

        For scatterers found by rays that move with the probe (a surface's hit points): a
        nearest-cell lookup would change whenever a hit crosses a cell border, so a
        probe moved by a fraction of a cell would see a new speckle pattern; this one
        changes on the scale of a cell, as real speckle decorrelates over a resolution cell.
        """
        u = np.ascontiguousarray(np.asarray(P_scene, dtype=float).reshape(-1, 3) / self.cell_m)
        out = np.empty(len(u), dtype=np.complex64)
        _smooth_values(u, self.table, self.key, out)
        return out


# Written by hand and compiled with numba: the eight corners' lookups and weights in numpy
# took ≈ 40 array passes over the points (a third of a frame's time with surface speckle).
# The corners' hashes are made in loops of their own over the points (integer arithmetic
# the compiler vectorizes, as in _add_lattice_lines): made point by point, eight at a
# time, they were most of a water frame's surface speckle (≈ 50 ns a point).
@numba.njit(cache=True, nogil=True, boundscheck=False)
def _smooth_values(u, table, key, out):  # pragma: no cover - compiled
    """Trilinear interpolation of the cells about points ``u`` (n, 3) in cell units,
    normalised to unit variance (see :meth:`ScattererField.smooth_at`)."""
    n = u.shape[0]
    cells = np.empty((3, n), dtype=np.int64)
    frac = np.empty((3, n))
    for i in range(n):
        for a in range(3):
            b = np.floor(u[i, a])
            cells[a, i] = np.int64(b)
            frac[a, i] = u[i, a] - b
    slots = np.empty((8, n), dtype=np.intp)
    c0, c1, c2 = cells[0], cells[1], cells[2]
    for corner in range(8):
        d0, d1, d2 = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
        s = slots[corner]
        for i in range(n):
            s[i] = _cell_slot(c0[i] + d0, c1[i] + d1, c2[i] + d2, key)
    for i in range(n):
        f0, f1, f2 = frac[0, i], frac[1, i], frac[2, i]
        acc = np.complex64(0.0)
        norm = 0.0
        for corner in range(8):
            d0, d1, d2 = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
            w = (f0 if d0 else 1.0 - f0) * (f1 if d1 else 1.0 - f1) * (f2 if d2 else 1.0 - f2)
            acc += table[slots[corner, i]] * np.float32(w)
            norm += w * w
        out[i] = acc / np.float32(np.sqrt(norm))


# Written by hand and compiled with numba: the speckle of a scattering medium hashes one
# scatterer per pixel and lattice line (millions a frame); fused here with the weighting
# and the sum, it touches each term once.
@numba.njit(cache=True, nogil=True, boundscheck=False)
def _add_lattice_lines(
    acc, rows, cols, offsets, weights, depth, medium_end, plane_of_line, table, key
):  # pragma: no cover - compiled
    H, W = acc.shape
    # Two passes per row: the cells' table slots first (a loop of integer arithmetic the
    # compiler vectorizes: 64-bit multiplies in SIMD lanes), then the table reads and the
    # sums. Fused in one loop the reads kept the hashing scalar: 1.75× slower in gel.
    shifted = np.empty((3, W), dtype=np.float32)
    slot = np.empty(W, dtype=np.uint64)
    for j in range(offsets.shape[0]):
        k = plane_of_line[j]
        # cols + offset first (float32, as the numpy sum rows + (cols + offset)).
        for c in range(W):
            for a in range(3):
                shifted[a, c] = cols[c, a] + offsets[j, a]
        s0, s1, s2 = shifted[0], shifted[1], shifted[2]
        for r in range(H):
            b = weights[j, r]
            if b == 0.0:
                continue
            r0, r1, r2 = rows[r, 0], rows[r, 1], rows[r, 2]
            for c in range(W):
                slot[c] = _cell_slot(
                    np.int64(np.floor(r0 + s0[c])),
                    np.int64(np.floor(r1 + s1[c])),
                    np.int64(np.floor(r2 + s2[c])),
                    key,
                )
            y = depth[r]
            # Single precision throughout: a double-precision product rounded back after
            # every line (the numpy sum's arithmetic) made this loop 1.4× slower, for
            # differences ≈ 1e-7 of a speckle amplitude.
            bf = np.float32(b)
            for c in range(W):
                if y < medium_end[k, c]:
                    acc[r, c] += table[slot[c]] * bf
