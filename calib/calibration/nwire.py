"""Calibration from N-wire phantoms (issue "N-wire and wire targets", item 3): the field's
standard phantom through the same questions the sphere method answers — what ``T_ee_us``
is, how sure we are of it, and whether to use it.

Each frame in which :func:`calib.localize.nwire.detect_nwires` finds every pattern gives one
point per pattern whose position is known in two frames: in the image (the diagonal
wire's dot, pixels) and in the phantom (where the image plane cuts the diagonal,
:func:`calib.localize.nwire.middle_wire_point`, from the ratio of the dots' distances along
their line). With the probe's pose ``T_base_ee`` per frame (a tracker's
``ProbeToReference``, or a robot's flange pose) the calibration solves, over every such
point ``i`` of frame ``k``,

    T_base_ee[k] · T_ee_us · s(u_i)  =  T_base_phantom · p_i

for ``T_ee_us`` (PLUS's ``ImageToProbe`` without the pixel spacing), the pixel scale
``s`` (optional: a spacing the scanner reports wrong, or a speed of sound off, is the same
unknown) and, on a robot, the phantom's pose ``T_base_phantom`` (as the three-marker fit
estimates the layout's; a tracker measures it, PLUS's ``Phantom`` → ``Reference``).

1. **Closed form.** The equation is linear in the entries of the affine map
   ``M = [k_x r_1, k_y r_2, t]`` from nominal image coordinates to the probe frame (and, on
   a robot, in those of ``T_base_phantom``): linear least squares, then the nearest
   rotations. No initial guess is needed.
2. **Refinement.** Robust least squares of the 3-D distances (soft-L1, then Cauchy at three
   times that scale), at the scale of the residuals' own median absolute deviation: no
   threshold.
3. **Error.** The 3-D reprojection error of each point (the distance above, mm) — what
   PLUS reports — and its summary as PLUS states it (mean and SD below the 95th
   percentile, its ``ErrorConfidenceLevel``).
4. **Bounds and verdict.** A delete-group jackknife over blocks of consecutive frames,
   each twice as long as the residuals stay correlated (neighbouring frames share the
   tracker's and the phantom's pose-dependent errors: on PLUS's fCal recording the two
   halves' answers differ by 1.2 mm over the image, which blocks of ten frames would
   call impossible) against the first-order covariance, the larger in every direction,
   Student-t widened; the 95 % bounds of rotation, translation and the mean error over
   the image; and a verdict as :mod:`calib.calibration.verdict` gives the sphere method's.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..errors import CalibrationError
from ..files.dataset import AcquisitionInfo
from ..files.plus_config import NWirePattern
from ..localize.nwire import NWireDetection, detect_nwires, middle_wire_point
from ..pipeline import axial_scale
from ..records import Dataset
from ..targets import NWireTarget, TargetObservations
from .targets import (
    MIN_FRAMES,
    OUTLIER_FLOOR_MM,
    Declared,
    TargetCalibration,
    TargetModel,
    calibrate_targets,
    correlation_frames,
)

__all__ = [
    "MIN_FRAMES",
    "OUTLIER_FLOOR_MM",
    "NWireCalibration",
    "NWireObservations",
    "calibrate_either_side",
    "calibrate_nwire",
    "correlation_frames",
    "dataset_frames",
    "dataset_spacing_m",
    "image_points_in_base",
    "observations_of",
    "observe_nwires",
    "plus_error_mm",
    "reprojection_errors_mm",
    "target_observations",
]

Array = NDArray[np.float64]
_MM = 1e3
#: PLUS's ErrorConfidenceLevel: its 3-D error is stated below this percentile.
PLUS_CONFIDENCE = 95.0


@dataclass(frozen=True)
class NWireObservations:
    """The diagonal-wire points of the frames where every pattern was found.

    ``frame`` (n,) index into the frames; ``pattern`` (n,) into the phantom's patterns;
    ``pixel`` (n, 2) the diagonal dot (column, row); ``phantom_point`` (n, 3) where the
    plane cuts the diagonal (phantom frame, metres); ``detections`` every frame's result
    (reasons for those not used); ``outer`` the outer dots the point was read with (for
    the phantom's tolerance in the bounds)."""

    frame: NDArray[np.int_]
    pattern: NDArray[np.int_]
    pixel: Array
    phantom_point: Array
    detections: tuple[NWireDetection, ...]
    outer: Array | None = None  # (n, 2, 2): the outer dots (first, last) as read, pixels
    skew: Array | None = None  # (n,): the diagonal dot's centre below its peak, rows

    @property
    def frames_used(self) -> int:
        return len(np.unique(self.frame))

    def subset(self, keep: NDArray[np.bool_]) -> NWireObservations:
        """The points where ``keep`` holds (frame indices unchanged)."""
        return NWireObservations(
            self.frame[keep],
            self.pattern[keep],
            self.pixel[keep],
            self.phantom_point[keep],
            self.detections,
            None if self.outer is None else self.outer[keep],
            None if self.skew is None else self.skew[keep],
        )

    def refusals(self) -> Counter[str]:
        """Why frames were not used: reason → count."""
        return Counter(d.reason for d in self.detections if not d.ok)


def observe_nwires(
    frames: NDArray[np.uint8],
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
) -> NWireObservations:
    """Detect the N patterns in every frame and turn each found pattern into its
    diagonal-wire point (image and phantom)."""
    detections = tuple(detect_nwires(f, patterns, spacing_mm) for f in frames)
    return observations_of(detections, patterns, spacing_mm)


def observations_of(
    detections: Sequence[NWireDetection],
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
    *,
    mirrored: bool = False,
) -> NWireObservations:
    """The diagonal-wire points of detections; ``mirrored``: each line's outer dots
    taken the other way round (the image's marked side showing the pattern's last wire
    first: a probe turned half a turn about its axis)."""
    sx, sy = spacing_mm
    mm = np.array([sx, sy])
    rows_f, rows_p, pix, pts, outer, skew = [], [], [], [], [], []
    for k, det in enumerate(detections):
        if not det.ok:
            continue
        for j, pattern in enumerate(patterns):
            a, m, b = (np.array(det.points[w.name]) for w in pattern.wires)
            if mirrored:
                a, b = b, a
            rows_f.append(k)
            rows_p.append(j)
            pix.append(m)
            outer.append((a, b))
            skew.append(det.skew.get(pattern.wires[1].name, 0.0))
            pts.append(middle_wire_point(pattern, a * mm, m * mm, b * mm))
    return NWireObservations(
        np.array(rows_f, dtype=int),
        np.array(rows_p, dtype=int),
        np.array(pix, dtype=float).reshape(-1, 2),
        np.array(pts, dtype=float).reshape(-1, 3),
        tuple(detections),
        np.array(outer, dtype=float).reshape(-1, 2, 2),
        np.array(skew, dtype=float),
    )


#: An N-wire calibration is a calibration from targets (:mod:`calib.calibration.targets`).
NWireCalibration = TargetCalibration


def plus_error_mm(errors_mm: Array) -> tuple[float, float]:
    """The 3-D reprojection error as PLUS states it: mean and SD of the errors at or
    below their 95th percentile (vtkProbeCalibrationAlgo's ``ErrorConfidenceLevel``)."""
    e = np.asarray(errors_mm, dtype=float)
    kept = e[e <= np.percentile(e, PLUS_CONFIDENCE)]
    return float(kept.mean()), float(kept.std())


def _tolerance_columns(obs: NWireObservations, patterns, spacing_m, tolerance) -> Declared:
    """The build tolerance as a declared error: the residuals' response (mm) to every
    coordinate of every wire end at its 1 σ (the diagonal point is read through the
    pattern's geometry)."""

    def columns(model: TargetModel, x: Array) -> Array | None:
        if tolerance <= 0 or patterns is None or obs.outer is None:
            return None
        mm = np.array(spacing_m) * _MM
        cols = []
        for j, pattern in enumerate(patterns):
            rows = np.flatnonzero(obs.pattern == j)
            a, b = obs.outer[rows, 0] * mm, obs.outer[rows, 1] * mm
            m = obs.pixel[rows] * mm
            base = middle_wire_point(pattern, a, m, b)
            for w in range(3):
                for end in ("front", "back"):
                    for axis in range(3):
                        wires = list(pattern.wires)
                        point = getattr(wires[w], end).copy()
                        point[axis] += tolerance
                        wires[w] = replace(wires[w], **{end: point})
                        moved = NWirePattern(tuple(wires))  # type: ignore[arg-type]
                        delta = np.zeros((len(obs.frame), 3))
                        delta[rows] = middle_wire_point(moved, a, m, b) - base
                        cols.append(model.shift_columns(x, delta))
        return np.column_stack(cols)

    return columns


def target_observations(
    obs: NWireObservations, patterns: Sequence[NWirePattern]
) -> tuple[TargetObservations, list[NWireTarget]]:
    """The N-wire points as observations of targets (one per pattern)."""
    targets = [NWireTarget(f"pattern_{j + 1}", p) for j, p in enumerate(patterns)]
    skew = obs.skew if obs.skew is not None else np.zeros(len(obs.frame))
    return (
        TargetObservations(
            obs.frame, obs.pattern, obs.pixel, obs.phantom_point, skew, obs.refusals()
        ),
        targets,
    )


def calibrate_nwire(
    obs: NWireObservations,
    T_base_ee: Array,
    *,
    width_px: int,
    height_px: int,
    spacing_m: tuple[float, float],
    T_base_phantom: Array | None = None,
    estimate_scale: bool = True,
    n_draws: int = 4000,
    patterns: Sequence[NWirePattern] | None = None,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
    mount_sigma_m: float = 0.0,
    mount_sigma_rad: float = 0.0,
    groups_of_frames: NDArray[np.int_] | None = None,
) -> NWireCalibration:
    """``T_ee_us`` (and the pixel scale, and the phantom's pose when ``T_base_phantom``
    is None) from the N-wire observations of frames taken at poses ``T_base_ee`` (one per
    frame): :func:`calib.calibration.targets.calibrate_targets` of the diagonal points.
    One :class:`~calib.errors.CalibrationError` when the frames cannot determine it (too
    few frames with every pattern, orientations too alike).

    The bounds add two declared errors every frame shares, which no residual shows:
    the phantom's build tolerance (``wire_tolerance_m``, 1 σ per axis of each wire's
    ends, with the ``patterns`` the points were read with) and a bias of the echoes'
    depth (``axial_bias_m``, 1 σ: the echo comes from the wire's front surface, drawn by
    a pulse; at least the rms distance between the dots' centres and their echoes'
    peaks, which a comet tail lengthens), each propagated to first order through the
    fit; and the rig's own error of the mount that no view shows (``mount_sigma_m``,
    ``mount_sigma_rad``, declared). ``groups_of_frames`` (one per frame): the
    jackknife's groups (a robot's views); without, blocks of consecutive frames."""
    if obs.frames_used < MIN_FRAMES:
        why = obs.refusals().most_common(1)
        raise CalibrationError(
            f"{obs.frames_used} frames show every wire pattern; the calibration needs at "
            f"least {MIN_FRAMES}" + (f" (most frames: {why[0][0]}, {why[0][1]}×)" if why else "")
        )
    n_patterns = int(obs.pattern.max()) + 1 if len(obs.pattern) else 0
    targets_obs, targets = target_observations(
        obs,
        patterns if patterns is not None else [NWirePattern(()) for _ in range(n_patterns)],  # type: ignore[arg-type]
    )
    return calibrate_targets(
        targets_obs,
        targets,
        T_base_ee,
        width_px=width_px,
        height_px=height_px,
        spacing_m=spacing_m,
        T_base_phantom=T_base_phantom,
        estimate_scale=estimate_scale,
        declared=_tolerance_columns(obs, patterns, spacing_m, wire_tolerance_m),
        axial_bias_m=axial_bias_m,
        mount_sigma_m=mount_sigma_m,
        mount_sigma_rad=mount_sigma_rad,
        n_draws=n_draws,
        groups=None if groups_of_frames is None else np.asarray(groups_of_frames)[obs.frame],
    )


def dataset_frames(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of the dataset's sequences, in order, and its pose ``T_base_ee``."""
    images = np.concatenate([s.images for s in dataset.sweeps])
    poses = np.concatenate([s.T_base_ee for s in dataset.sweeps])
    return images, poses


def dataset_spacing_m(dataset: Dataset, info: AcquisitionInfo) -> tuple[float, float]:
    """The images' pixel spacing (columns, rows; m), the axial one corrected for the
    medium's speed of sound when the dataset asks for it."""
    sx, sy = dataset.sweeps[0].spacing
    return float(sx), float(sy) * axial_scale(info)


def calibrate_either_side(
    obs: NWireObservations,
    patterns: Sequence[NWirePattern],
    spacing_mm: tuple[float, float],
    T_base_ee: Array,
    **kwargs: Any,
) -> tuple[NWireCalibration, NWireObservations, bool]:
    """:func:`calibrate_nwire` with the image's marked side unknown: the wires read from
    either side (:func:`observations_of`), each fitted, the one whose points agree best
    (the smaller robust scatter) kept. A probe mounted the other way round swaps which
    outer wire each line shows first; the wrong reading puts every diagonal point at the
    other end of its diagonal, and the poses cannot agree with it. Returns (calibration,
    the observations it rests on, whether they are mirrored)."""
    best: tuple[NWireCalibration, NWireObservations, bool] | None = None
    for mirrored in (False, True):
        o = observations_of(obs.detections, patterns, spacing_mm, mirrored=mirrored)
        try:
            cal = calibrate_nwire(o, T_base_ee, patterns=patterns, **kwargs)
        except CalibrationError:
            if mirrored and best is None:
                raise
            continue
        if best is None or cal.sigma_mm < best[0].sigma_mm:
            best = (cal, o, mirrored)
    assert best is not None
    return best


def reprojection_errors_mm(
    obs: NWireObservations,
    T_base_ee: Array,
    image_to_probe_mm: Array,
    T_base_phantom: Array,
) -> Array:
    """Each point's 3-D reprojection error (mm) under a calibration given as PLUS's
    ``ImageToProbe`` (pixel → probe mm, its pixel spacing included): uscal's own, or any
    other tool's."""
    image = image_points_in_base(obs, T_base_ee, image_to_probe_mm)
    wire = se3.apply(T_base_phantom, obs.phantom_point)
    return np.linalg.norm(image - wire, axis=1) * _MM


def image_points_in_base(
    obs: NWireObservations, T_base_ee: Array, image_to_probe_mm: Array
) -> Array:
    """The diagonal dots (n, 3) mapped to the base frame (metres) through a calibration
    given as PLUS's ``ImageToProbe`` and each frame's pose."""
    A = np.asarray(image_to_probe_mm, dtype=float)
    uv = np.column_stack([obs.pixel, np.zeros(len(obs.pixel)), np.ones(len(obs.pixel))])
    P_ee = (uv @ A.T)[:, :3] * 1e-3
    T_k = np.asarray(T_base_ee, dtype=float)[obs.frame]
    return np.einsum("nij,nj->ni", T_k[:, :3, :3], P_ee) + T_k[:, :3, 3]
