"""What the report and the recording show of a localization: the first accepted sweep's
frames of a sphere with the sections found (and, in the twin, the true ones), and the
sphere's radial profile over its sweeps."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calib.image import sphere_section, us_to_pixel
from calib.localize import SphereProfile, SweepLocalization, frame_offsets, sphere_profile
from calib.records import Sweep

__all__ = ["Circle3", "LocalizationSnapshot", "dataset_snapshot", "localization_snapshot"]
Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class LocalizationSnapshot:
    """What the report shows of one sweep's localization (small enough to return from a
    worker): a few frames across the sphere with the section the localizer found (red)
    and, in simulation, the true one (green), in pixels; and the sphere's radial profile.
    """

    title: str
    frames: NDArray[np.uint8]  # (k, H, W)
    elevation_mm: Array  # (k,) each frame's offset from the sweep's reference frame
    detected: list[Circle3 | None]
    true: list[Circle3 | None]
    profile: SphereProfile
    radius: float  # metres (the CAD radius)


def _circle_px(centre_us: Array, radius: float, width: int, spacing) -> Circle3 | None:
    section = sphere_section(centre_us, radius)
    if section is None:
        return None
    x, y, r = section
    rows, cols = us_to_pixel(np.array([x, y, 0.0]), width, spacing)
    return float(cols), float(rows), r / spacing[0]


def dataset_snapshot(
    dataset,
    alt,
    radius: float,
    cfg,
    axial_scale: float,
    true_centres: Callable[[str, Sweep], Array] | None = None,
) -> LocalizationSnapshot | None:
    """The report's look at the first sphere an alternation localized: its first
    accepted sweep's frames with the sections found (and, ``true_centres(target, sweep)``
    giving the true centre in each frame's us frame, the true ones), and the sphere's
    radial profile over its sweeps. None when no sweep was accepted."""
    target = next(iter(alt.localizations))
    sweeps = dataset.of(target)
    locs = alt.localizations[target]
    T = alt.result.T_ee_us
    i = next((i for i, loc in enumerate(locs) if loc.accepted), None)
    if i is None:
        return None
    truth = true_centres(target, sweeps[i]) if true_centres is not None else None
    profile = sphere_profile(sweeps, locs, T, radius, cfg, axial_scale=axial_scale)
    return localization_snapshot(sweeps[i], locs[i], T, radius, axial_scale, profile, truth)


def localization_snapshot(
    sweep: Sweep,
    localization: SweepLocalization,
    T_ee_us: Array,
    radius: float,
    axial_scale: float,
    profile: SphereProfile,
    true_centres: Array | None = None,
    n_frames: int = 8,
) -> LocalizationSnapshot:
    """Up to ``n_frames`` frames of ``sweep`` spread over those the found sphere cuts,
    with its section and (``true_centres`` (n, 3): the true centre in each frame's us
    frame) the true one."""
    offsets = frame_offsets(sweep, T_ee_us)
    centre = localization.centre
    cut = [j for j in range(sweep.n_frames) if abs(centre[2] - offsets[j, 2]) < radius]
    picks = cut or list(range(sweep.n_frames))
    chosen = sorted({picks[int(i)] for i in np.linspace(0, len(picks) - 1, n_frames).round()})
    W = sweep.images.shape[2]
    spacing = (sweep.spacing[0], sweep.spacing[1] * axial_scale)
    return LocalizationSnapshot(
        f"{sweep.target}, sweep {sweep.pose_id}",
        sweep.images[chosen].copy(),
        (offsets[chosen, 2] - offsets[sweep.reference_index, 2]) * 1e3,
        [_circle_px(centre - offsets[j], radius, W, spacing) for j in chosen],
        [
            _circle_px(true_centres[j], radius, W, spacing) if true_centres is not None else None
            for j in chosen
        ],
        profile,
        radius,
    )


Circle3 = tuple[float, float, float]  # (column, row, radius) in pixels
