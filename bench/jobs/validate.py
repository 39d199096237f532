"""``uscal validate DATASET --calibration FILE``: any calibration checked on another
dataset with the same detection uscal calibrates with.

The calibration is uscal's ``calibration.yaml`` or PLUS's own (a fCal results file, or
a device set configuration whose ``CoordinateDefinitions`` hold ``Image`` → ``Probe``):
read as PLUS's ``ImageToProbe`` (pixel → probe mm, spacing included), the one form every
tool writes.

- **N-wire datasets**: every frame's wires found as ``uscal calibrate`` finds them, each
  diagonal-wire point mapped through the calibration and the frame's pose, and its
  distance to where the phantom says it is: PLUS's 3-D reprojection error (mean and SD
  below the 95th percentile). Without a tracked phantom pose (a robot rig) the pose is
  fitted to this dataset with the calibration held (Kabsch): the figure then measures the
  calibration's consistency, not its absolute position.
- **Sphere datasets**: each sphere localized in each sweep with the calibration (the
  localizer of the settings, stacking the frames through it), the centres mapped to the
  base: their scatter about each sphere's centroid (the paper's precision) and, with the
  phantom's CAD centres in the dataset, the distances between the spheres' centroids
  against the CAD distances (a calibration error shows as a layout that does not fit).
- **Single-wire datasets**: each frame's dot as ``uscal calibrate`` finds it; the wire's
  pose fitted with the calibration held (across the wire: along and about itself it is
  not seen); each dot's distance from the wire across it, stated as PLUS states its
  error. The wire's fitted pose absorbs part of a calibration's error: a mount 1 mm off
  shows as 0.12–0.21 mm, one turned 1° as 0.01–0.09 mm (synthetic frames turned ±15°).
  Cone-tip datasets are refused: a lone point's constraints are all its own position's
  fit takes.
"""

from __future__ import annotations

import itertools
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib import se3
from calib.calibration.nwire import (
    dataset_frames,
    dataset_spacing_m,
    image_points_in_base,
    observations_of,
    observe_nwires,
    plus_error_mm,
    reprojection_errors_mm,
)
from calib.calibration.targets import fit_phantom_pose, wire_starts
from calib.errors import DatasetError, UscalError
from calib.files.dataset import read_dataset
from calib.files.plus_config import read_plus_config, read_plus_results, us_of_image_to_probe
from calib.localize import localize_sphere
from calib.localize.nwire import detect_wire
from calib.pipeline import axial_scale
from calib.targets import TargetObservations, WireTarget

from ..config.scenario import Scenario

__all__ = ["GivenCalibration", "Validation", "read_calibration", "validate_dataset"]

_MM = 1e3


@dataclass(frozen=True)
class GivenCalibration:
    """A calibration to check: PLUS's ``ImageToProbe`` (4, 4; pixel → probe mm) and
    where it came from."""

    path: Path
    image_to_probe_mm: np.ndarray
    source: str


def read_calibration(path: str | os.PathLike[str]) -> GivenCalibration:
    """Read uscal's ``calibration.yaml``, a PLUS results file or a PLUS device set
    configuration with ``Image`` → ``Probe``; one line when it is none of them."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"--calibration {path}: no such file")
    if path.suffix.lower() == ".xml":
        root_tag = _xml_root(path)
        if root_tag == "ProbeCalibrationResult":
            A = read_plus_results(path).image_to_probe.copy()
            A[:3, :] *= _MM  # metres (its output) back to PLUS's millimetres
            return GivenCalibration(path, A, "PLUS calibration result")
        config = read_plus_config(path, phantom=False)
        A = config.transform("Image", "Probe").copy()
        A[:3, :] *= _MM
        return GivenCalibration(path, A, "PLUS configuration")
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise DatasetError(f"--calibration {path}: not YAML ({e})") from None
    matrix = (doc or {}).get("plus_ImageToProbe", {}) if isinstance(doc, dict) else {}
    A = np.array(matrix.get("matrix", []) if isinstance(matrix, dict) else [], dtype=float)
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        raise DatasetError(
            f"--calibration {path}: not a uscal calibration.yaml (no plus_ImageToProbe "
            "matrix), a PLUS results file or a PLUS configuration"
        )
    return GivenCalibration(path, A, "uscal calibration")


def _xml_root(path: Path) -> str:
    try:
        return ET.parse(path).getroot().tag
    except ET.ParseError as e:
        raise DatasetError(f"--calibration {path}: not XML ({e})") from None


@dataclass(frozen=True)
class Validation:
    """What ``uscal validate`` measured: ``metrics`` (for a file) and ``lines`` (for the
    console), the last of which is the machine-readable summary."""

    metrics: dict[str, Any]
    lines: list[str]


def validate_dataset(
    directory: str | os.PathLike[str], calibration: GivenCalibration, settings: Scenario
) -> Validation:
    """Check ``calibration`` on the dataset at ``directory`` (see the module doc)."""
    dataset, info = read_dataset(directory)
    if info.nwire is not None:
        return _validate_nwire(dataset, info, calibration)
    if info.wire is not None:
        return _validate_wire(dataset, info, calibration)
    if info.cone_tip is not None:
        raise UscalError(
            f"{directory}: a cone-tip dataset; validate checks calibrations on N-wire, "
            "single-wire and sphere datasets (a lone point's three constraints per sweep "
            "are all the fit of the cone's position takes: nothing is left to score)"
        )
    return _validate_spheres(dataset, info, calibration, settings)


def _validate_nwire(dataset, info, calibration: GivenCalibration) -> Validation:
    images, poses = dataset_frames(dataset)
    spacing = dataset_spacing_m(dataset, info)
    spacing_mm = (spacing[0] * _MM, spacing[1] * _MM)
    obs = observe_nwires(images, info.nwire.patterns, spacing_mm)
    if obs.frames_used == 0:
        why = obs.refusals().most_common(1)
        raise DatasetError(
            f"{dataset.name}: no frame shows every wire pattern"
            + (f" (most frames: {why[0][0]})" if why else "")
        )
    A = calibration.image_to_probe_mm
    # Either side of the image may be the marked one: the reading the calibration
    # agrees with is kept (:func:`calib.calibration.nwire.calibrate_either_side`).
    best = None
    for mirrored in (False, True):
        o = observations_of(obs.detections, info.nwire.patterns, spacing_mm, mirrored=mirrored)
        errors, fitted = _nwire_errors(o, poses, A, info.nwire.T_base_phantom)
        if best is None or np.median(errors) < np.median(best[0]):
            best = (errors, fitted, o)
    assert best is not None
    errors, fitted, obs = best
    mean, sd = plus_error_mm(errors)
    metrics = {
        "dataset": dataset.name,
        "target": "nwire",
        "calibration": {"path": str(calibration.path), "source": calibration.source},
        "frames": len(images),
        "frames_found": obs.frames_used,
        "points": len(errors),
        "phantom_pose": "fitted to this dataset" if fitted else "tracked",
        "reprojection_3d_mm": {
            "plus_mean": mean,
            "plus_sd": sd,
            "median": float(np.median(errors)),
            "p95": float(np.percentile(errors, 95)),
        },
    }
    lines = [
        f"{dataset.name}: {len(images)} frames, every pattern found in {obs.frames_used} "
        f"({len(errors)} wire points); phantom pose {metrics['phantom_pose']}",
        f"calibration: {calibration.source} ({calibration.path})",
        f"3-D reprojection error (PLUS's definition, below the 95th percentile): {mean:.3f} ± "
        f"{sd:.3f} mm; median {np.median(errors):.3f}, 95th percentile "
        f"{np.percentile(errors, 95):.3f} mm",
        f"reprojection_mm={mean:.4f} sd_mm={sd:.4f}",
    ]
    return Validation(metrics, lines)


def _validate_wire(dataset, info, calibration: GivenCalibration) -> Validation:
    """A single wire: its dot in every frame as ``uscal calibrate`` finds it, the wire's
    pose fitted to this dataset with the calibration held (its two visible directions
    across the wire and two turns; along and about itself it is not seen), and each
    dot's distance from the wire across it."""
    images, poses = dataset_frames(dataset)
    spacing = dataset_spacing_m(dataset, info)
    detections = [detect_wire(f, (spacing[0] * _MM, spacing[1] * _MM)) for f in images]
    found = [k for k, d in enumerate(detections) if d.ok]
    if len(found) < 3:
        raise DatasetError(f"{dataset.name}: the wire is found in {len(found)} frames")
    wire = info.wire.wire
    target = WireTarget(wire.name, wire.front, wire.back)
    obs = TargetObservations.of(
        found, np.zeros(len(found)), [detections[k].points["wire"] for k in found],
        np.tile(np.asarray(wire.front, dtype=float), (len(found), 1)),
    )  # fmt: skip
    W = images.shape[2]
    T_ee_us, given_spacing = us_of_image_to_probe(calibration.image_to_probe_mm, W)
    errors = None
    for start in wire_starts(obs, target, poses, T_ee_us, W, given_spacing):
        _, e = fit_phantom_pose(
            obs, [target], poses, T_ee_us=T_ee_us, spacing_m=given_spacing, width_px=W,
            start=start,
        )  # fmt: skip
        if errors is None or np.median(e) < np.median(errors):
            errors = e
    assert errors is not None
    mean, sd = plus_error_mm(errors)
    metrics = {
        "dataset": dataset.name,
        "target": "wire",
        "calibration": {"path": str(calibration.path), "source": calibration.source},
        "frames": len(images),
        "frames_found": len(found),
        "points": len(errors),
        "phantom_pose": "fitted to this dataset (across the wire)",
        "reprojection_3d_mm": {
            "plus_mean": mean,
            "plus_sd": sd,
            "median": float(np.median(errors)),
            "p95": float(np.percentile(errors, 95)),
            "note": "each dot's distance from the wire across it",
        },
    }
    lines = [
        f"{dataset.name}: {len(images)} frames, the wire found in {len(found)}; its pose "
        "fitted to this dataset with the calibration held",
        f"calibration: {calibration.source} ({calibration.path})",
        f"error across the wire (below the 95th percentile): {mean:.3f} ± {sd:.3f} mm; "
        f"median {np.median(errors):.3f}, 95th percentile {np.percentile(errors, 95):.3f} mm",
        f"reprojection_mm={mean:.4f} sd_mm={sd:.4f}",
    ]
    return Validation(metrics, lines)


def _nwire_errors(obs, poses, A, T_phantom):
    """The 3-D errors of the observations under ``A`` (ImageToProbe, mm) and whether the
    phantom's pose was fitted (no tracked pose: Kabsch, the calibration held)."""
    fitted = T_phantom is None
    if fitted:
        P_base = image_points_in_base(obs, poses, A)
        # Kabsch, refitted without the points far beyond the rest (a wrong dot must not
        # move the phantom for every other point).
        keep = np.ones(len(P_base), dtype=bool)
        for _ in range(3):
            T_phantom = se3.kabsch(obs.phantom_point[keep], P_base[keep])
            d = np.linalg.norm(se3.apply(T_phantom, obs.phantom_point) - P_base, axis=1)
            keep = d <= 3.0 * 1.4826 * np.median(d) + 1e-9
    return reprojection_errors_mm(obs, poses, A, T_phantom), fitted


def _validate_spheres(dataset, info, calibration: GivenCalibration, settings) -> Validation:
    width = dataset.sweeps[0].images.shape[2]
    T_ee_us, spacing_cal = us_of_image_to_probe(calibration.image_to_probe_mm, width)
    spacing = tuple(float(v) for v in dataset.sweeps[0].spacing)
    off = max(abs(a / b - 1) for a, b in zip(spacing_cal, spacing, strict=True))
    if off > 0.005:
        raise DatasetError(
            f"--calibration {calibration.path}: made for a pixel spacing of "
            f"{spacing_cal[0] * _MM:.5f} × {spacing_cal[1] * _MM:.5f} mm; {dataset.name}'s "
            f"images have {spacing[0] * _MM:.5f} × {spacing[1] * _MM:.5f} mm"
        )
    radius = info.sphere_radius_mm / _MM
    scale = axial_scale(info)
    by_target: dict[str, list] = {}
    for s in dataset.sweeps:
        by_target.setdefault(s.target, []).append(s)
    centroids, precision, counts = {}, {}, {}
    for target, sweeps in by_target.items():
        locs = localize_sphere(sweeps, T_ee_us, radius, settings.localization, axial_scale=scale)
        P = np.array(
            [
                se3.apply(s.T_base_ee[s.reference_index] @ T_ee_us, loc.centre)
                for s, loc in zip(sweeps, locs, strict=True)
                if loc.accepted
            ]
        ).reshape(-1, 3)
        counts[target] = (len(P), len(sweeps))
        if len(P) >= 2:
            centroids[target] = P.mean(axis=0)
            precision[target] = float(np.mean(np.linalg.norm(P - P.mean(axis=0), axis=1))) * _MM
    if not precision:
        raise DatasetError(
            f"{dataset.name}: no sphere localized in two sweeps or more with this calibration"
        )
    layout = []
    for a, b in itertools.combinations(sorted(centroids), 2):
        if a in info.landmarks and b in info.landmarks:
            seen = np.linalg.norm(centroids[a] - centroids[b])
            cad = np.linalg.norm(info.landmarks[a] - info.landmarks[b])
            layout.append(abs(seen - cad) * _MM)
    mean_precision = float(np.mean(list(precision.values())))
    metrics = {
        "dataset": dataset.name,
        "target": "spheres",
        "calibration": {"path": str(calibration.path), "source": calibration.source},
        "precision_mm": precision,
        "localized": {t: {"accepted": n, "sweeps": m} for t, (n, m) in counts.items()},
        "layout_error_mm": float(np.mean(layout)) if layout else None,
    }
    lines = [f"calibration: {calibration.source} ({calibration.path})"]
    for t, p in precision.items():
        n, m = counts[t]
        lines.append(f"{t}: {n} of {m} sweeps localized, centres {p:.3f} mm about their centroid")
    if layout:
        lines.append(
            f"distances between the spheres' centroids against the CAD layout: mean "
            f"{np.mean(layout):.3f} mm off ({len(layout)} pairs)"
        )
    lines.append(
        f"precision_mm={mean_precision:.4f}"
        + (f" layout_mm={np.mean(layout):.4f}" if layout else "")
    )
    return Validation(metrics, lines)
