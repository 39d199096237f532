"""The scanner's display chain: electronic noise, TGC and gain, log compression, 8 bits.

Envelope intensity → + electronic noise (complex Gaussian, added before detection, so
its intensity is exponential) → TGC (dB per cm of depth) and overall gain (dB) → log
compression over the dynamic range, 0 dB (white) at the echo of a perfect reflector at
zero gain → ``uint8`` grey levels, as a frame grabber captures them. A gain of +G dB
raises every unsaturated grey level by ``G · 255 / DR``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .probe import ProbeConfig

__all__ = ["NoiseSource", "gain_profile_db", "to_bmode"]


def gain_profile_db(probe: ProbeConfig, n_rows: int) -> NDArray[np.float32]:
    """Total gain (dB) per row: overall gain plus TGC at the row's depth."""
    depth_cm = np.arange(n_rows) * probe.pixel_spacing_mm[1] / 10.0
    return (probe.gain_db + probe.tgc_db_per_cm * depth_cm).astype(np.float32)


class NoiseSource:
    """Electronic noise intensities (unit mean, exponential) for the frames.

    Drawing 150 000 exponentials per frame costs more than the rest of the display chain,
    so a pool of ``pool_frames`` frames' worth is drawn once and each frame takes a
    contiguous window at a random offset: every frame's noise is new to the eye and the
    statistics are exact, at a fraction of the cost.
    """

    def __init__(self, rng: np.random.Generator, frame_size: int, pool_frames: int = 8) -> None:
        self._rng = rng
        self._size = frame_size
        self._pool = rng.standard_exponential(frame_size * pool_frames, dtype=np.float32)

    def frame(self) -> NDArray[np.float32]:
        """One frame's noise intensities (frame_size,), a view into the pool."""
        offset = int(self._rng.integers(0, len(self._pool) - self._size))
        return self._pool[offset : offset + self._size]


def to_bmode(
    intensity: NDArray[np.float32], probe: ProbeConfig, noise: NoiseSource | None
) -> NDArray[np.uint8]:
    """B-mode frames (n, H, W) uint8 from envelope intensities (n, H, W).

    ``noise`` supplies the electronic noise (new in every frame, like a real scanner's);
    None renders without noise.
    """
    intensity = np.asarray(intensity, dtype=np.float32)
    n, H, W = intensity.shape
    dr = np.float32(probe.dynamic_range_db)
    scale = np.float32(255.0) / dr
    # grey = (10 log10 I + gain(row) + DR) · 255 / DR, rounded, clipped to 0..255.
    offset = ((gain_profile_db(probe, H) + dr) * scale + np.float32(0.5))[:, None]
    noise_power = np.float32(10.0 ** (probe.noise_db / 10.0))
    out = np.empty((n, H, W), dtype=np.uint8)
    buf = np.empty((H, W), dtype=np.float32)
    # Frame by frame, in place: the buffer stays in cache across the passes.
    for f in range(n):
        if noise is not None:
            np.multiply(noise.frame(), noise_power, out=buf.reshape(-1))
            buf += intensity[f]
            # A float32 exponential draw can be exactly 0; in a shadow the echo is 0 too.
            np.maximum(buf, np.float32(1e-30), out=buf)
        else:
            np.maximum(intensity[f], np.float32(1e-30), out=buf)
        np.log10(buf, out=buf)
        buf *= np.float32(10.0) * scale
        buf += offset
        np.clip(buf, 0.0, 255.0, out=buf)
        out[f] = buf
    return out
