"""Backscatter speckle that belongs to the medium, not to the frame.

Scatterers sit on a fixed grid of the scene frame (cell ``cell_m``), each with a complex
Gaussian amplitude drawn from a counter-based hash of its grid index and a key. So the
same pose gives the same image, neighbouring frames share scatterers, and frames
decorrelate as the probe moves out of the slice — with no stored volume, for any extent.

Summed coherently over the elevation beam and blurred with the PSF this gives fully
developed speckle: Rayleigh envelope (mean/std ≈ 1.91), log-domain std ≈ 5.57 dB.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["scatterer_field"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_PRIMES = (np.uint64(0x8DA6B343), np.uint64(0xD8163841), np.uint64(0xCB1AB31F))


def _splitmix64(x: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64 finaliser (Steele et al. 2014): a well-mixed 64-bit hash of ``x``."""
    x = x + _GOLDEN
    x = (x ^ (x >> np.uint64(30))) * _MIX1
    x = (x ^ (x >> np.uint64(27))) * _MIX2
    return x ^ (x >> np.uint64(31))


def scatterer_field(P_scene: NDArray[np.float64], cell_m: float, key: int) -> NDArray[np.complex64]:
    """Unit-variance complex Gaussian scatterer amplitude at points (..., 3), metres.

    Points in the same grid cell share a scatterer (nearest-cell lookup).
    """
    idx = np.floor(P_scene / cell_m).astype(np.int64).view(np.uint64)
    with np.errstate(over="ignore"):
        h = (idx[..., 0] * _PRIMES[0]) ^ (idx[..., 1] * _PRIMES[1]) ^ (idx[..., 2] * _PRIMES[2])
        h = _splitmix64(h ^ np.uint64(key & 0xFFFFFFFFFFFFFFFF))
    # Two 32-bit uniforms in (0, 1] and [0, 1) → Box–Muller.
    u1 = ((h >> np.uint64(32)).astype(np.float64) + 1.0) / 2.0**32
    u2 = (h & np.uint64(0xFFFFFFFF)).astype(np.float64) / 2.0**32
    radius = np.sqrt(-np.log(u1))  # |z|² ~ Exp(1): unit variance
    return (radius * np.exp(2j * np.pi * u2)).astype(np.complex64)
