"""The obvious implementation of the localizer's score, one sample at a time: the test
oracle of :func:`calib.localize.score_candidates` (``tests/test_localize.py``) and the
reference ``benchmarks/localize.py`` times against it (≈ 24 000× slower on a sweep)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from calib.image import us_to_pixel
from calib.localize import SweepVolume, frame_offsets
from calib.localize.search import _offsets_vox
from calib.records import Sweep

__all__ = ["score_candidates_reference"]

Array = NDArray[np.float64]


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
    the test oracle of :func:`calib.localize.score_candidates`.
    """
    offsets = frame_offsets(sweep, T_ee_us)
    n, H, W = sweep.images.shape
    spacing = (sweep.spacing[0], sweep.spacing[1] * axial_scale)
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
                rows, cols = us_to_pixel([x - offsets[j, 0], y - offsets[j, 1], 0.0], W, spacing)
                row, col = int(np.rint(rows)), int(np.rint(cols))
                if not (0 <= row < H and 0 <= col < W):
                    continue
                valid += 1
                bright += int(sweep.images[j, row, col] > means[j])
            fractions.append(bright / valid if valid else np.nan)
        s = fractions[0] - fractions[1]
        out[i] = -np.inf if np.isnan(s) else s
    return out
