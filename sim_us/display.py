"""The scanner's display chain: electronic noise, TGC and gain, log compression, 8 bits.

Envelope intensity → + electronic noise (complex Gaussian, added before detection, so
its intensity is exponential) → TGC (dB per cm of depth) and overall gain (dB) → log
compression over the dynamic range, 0 dB (white) at the echo of a perfect reflector at
the elevation focus at zero gain → ``uint8`` grey levels, as a frame grabber captures
them. A gain of +G dB raises every unsaturated grey level by ``G · 255 / DR``.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from .probe import ProbeConfig

__all__ = ["NoiseSource", "gain_profile_db", "to_bmode"]

_TINY = np.float32(1e-30)  # a float32 exponential draw can be exactly 0, and so can an echo


def gain_profile_db(probe: ProbeConfig, n_rows: int) -> NDArray[np.float32]:
    """Total gain (dB) per row: overall gain plus TGC at the row's depth."""
    depth_cm = np.arange(n_rows) * probe.pixel_spacing_mm[1] / 10.0
    return (probe.gain_db + probe.tgc_db_per_cm * depth_cm).astype(np.float32)


class NoiseSource:
    """Electronic noise intensities (unit mean, exponential) for the frames.

    Drawing 150 000 exponentials per frame costs more than the rest of the display chain,
    so a pool of ``pool_frames`` frames' worth is drawn once and each frame takes a
    contiguous window at a random offset: every frame's noise is new to the eye and the
    statistics are exact, at a fraction of the cost. The pool's log-compressed levels are
    kept too (per noise power): where no echo reaches a pixel, its grey level is the
    noise's alone, and most of a frame in water is such pixels.
    """

    def __init__(self, rng: np.random.Generator, frame_size: int, pool_frames: int = 8) -> None:
        self._rng = rng
        self._size = frame_size
        self._pool = rng.standard_exponential(frame_size * pool_frames, dtype=np.float32)
        self._levels: tuple[float, float, NDArray[np.float32]] | None = None

    def frame(
        self, power: np.float32, gain: np.float32
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """One frame's noise (frame_size,): its intensities at unit mean and its
        compressed levels ``gain · ln(power · noise)`` (before the rows' offsets, as
        :func:`_compress` takes them for a pixel without echo); views into the pools."""
        if self._levels is None or self._levels[:2] != (power, gain):
            levels = np.empty_like(self._pool)
            _log_levels(self._pool, power, gain, levels)
            self._levels = (power, gain, levels)
        o = int(self._rng.integers(0, len(self._pool) - self._size))
        window = slice(o, o + self._size)
        return self._pool[window], self._levels[2][window]


def to_bmode(
    intensity: NDArray[np.float32], probe: ProbeConfig, noise: NoiseSource | None
) -> NDArray[np.uint8]:
    """B-mode frames (n, H, W) uint8 from envelope intensities (n, H, W).

    ``noise`` supplies the electronic noise (new in every frame, like a real scanner's);
    None renders without noise.
    """
    intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    n, H, W = intensity.shape
    size = H * W
    dr = np.float32(probe.dynamic_range_db)
    scale = np.float32(255.0) / dr
    # grey = (10 log10 I + gain(row) + DR) · 255 / DR, rounded, clipped to 0..255; with
    # 10 log10 I = (10 / ln 10) ln I (numpy's natural log is several times faster).
    gain = np.float32(10.0 / np.log(10.0)) * scale
    offset = (gain_profile_db(probe, H) + dr) * scale + np.float32(0.5)
    out = np.empty((n, H, W), dtype=np.uint8)
    flat = intensity.reshape(n, size)
    index = np.empty(size, dtype=np.int64)
    value = np.empty(size, dtype=np.float32)
    # Without noise every pixel without echo is at the floor, and the echoes add to 0.
    power = np.float32(0.0 if noise is None else 10.0 ** (probe.noise_db / 10.0))
    quiet = (np.zeros(size, np.float32), np.full(size, gain * np.log(_TINY), np.float32))
    for f in range(n):
        noise_f, levels = quiet if noise is None else noise.frame(power, gain)
        # Pixels without echo take the noise's level; those with one are gathered, their
        # logarithm taken by numpy (vectorized), and put back.
        m = _gather_echoes(flat[f], noise_f, power, index, value)
        np.log(value[:m], out=value[:m])
        _compress(levels, index[:m], value[:m], gain, offset, W, out[f].reshape(-1))
    return out


# Written by hand and compiled with numba: the numpy chain made six passes over each frame
# and took the logarithm of every pixel; most pixels of a frame in water hold no echo,
# and their level is the noise's, already compressed in the pool (NoiseSource.levels).
@numba.njit(cache=True, nogil=True, boundscheck=False)
def _log_levels(noise, power, gain, out):  # pragma: no cover - compiled
    for i in range(noise.shape[0]):
        out[i] = gain * np.log(max(power * noise[i], _TINY))


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _gather_echoes(intensity, noise, power, index, value):  # pragma: no cover - compiled
    """The pixels with an echo: their flat index and ``power · noise + intensity`` (at
    least the smallest level), in ``index`` / ``value``; returns how many."""
    m = 0
    for i in range(intensity.shape[0]):
        v = intensity[i]
        if v != 0.0:
            index[m] = i
            value[m] = max(power * noise[i] + v, _TINY)
            m += 1
    return m


@numba.njit(cache=True, nogil=True, boundscheck=False)
def _compress(levels, index, log_value, gain, offset, W, out):  # pragma: no cover
    """One frame's grey levels: ``clip(level + offset[row])`` as uint8 (offset holds the
    rounding's + ½), the level the noise's own (``levels``) except at the gathered
    pixels ``index``, where it is ``gain · log_value``."""
    H = levels.shape[0] // W
    for r in range(H):
        off = offset[r]
        for i in range(r * W, (r + 1) * W):
            out[i] = np.uint8(min(max(levels[i] + off, np.float32(0.0)), np.float32(255.0)))
    r, end = 0, W  # index is ascending: walk the rows along (no division per pixel)
    for j in range(index.shape[0]):
        i = index[j]
        while i >= end:
            r += 1
            end += W
        level = gain * log_value[j] + offset[r]
        out[i] = np.uint8(min(max(level, np.float32(0.0)), np.float32(255.0)))
