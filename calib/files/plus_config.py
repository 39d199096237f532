"""PLUS's own files about a calibration: the device set configuration (its
``CoordinateDefinitions`` and the N-wire phantom's ``PhantomDefinition``) and fCal's
results file (``ImageToProbe``, the 3-D and 2-D reprojection errors, and the wire points
its segmentation found in each frame).

These are read to calibrate from PLUS's real N-wire recordings and to compare with PLUS's
answer on PLUS's data (issue "N-wire and wire targets"); nothing here depends on the
twin. Lengths are turned from PLUS's millimetres to metres; image points stay in pixels
(PLUS's image frame: column, row). XML is read with the standard library's parser (no
entity expansion beyond expat's limits, no network, no schema); every problem is one
:class:`~calib.errors.DatasetError` naming the file and what is wrong.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..errors import DatasetError

__all__ = [
    "NWire",
    "NWirePattern",
    "NWirePhantom",
    "PlusConfig",
    "PlusFrameSegmentation",
    "PlusResults",
    "image_to_probe_mm",
    "read_plus_config",
    "read_plus_results",
    "us_of_image_to_probe",
]

Array = NDArray[np.float64]
_MM = 1e-3
#: The outer wires of an N pattern are parallel, the three in one plane: to this much.
_PARALLEL_DEG = 1.0
_COPLANAR_MM = 0.5


@dataclass(frozen=True)
class NWire:
    """One wire of the phantom: its name and its end points (phantom frame, metres)."""

    name: str
    front: Array
    back: Array

    @property
    def direction(self) -> Array:
        d = self.back - self.front
        return d / np.linalg.norm(d)


@dataclass(frozen=True)
class NWirePattern:
    """An N: two parallel outer wires and the diagonal between them, in one plane."""

    wires: tuple[NWire, NWire, NWire]


@dataclass(frozen=True)
class NWirePhantom:
    """An N-wire phantom in a dataset: its patterns (phantom frame, metres) and, when a
    tracker measured it, its pose in the base frame (a tracked probe's ``Reference``:
    PLUS's ``Phantom`` → ``Reference``); None: unknown, estimated with ``T_ee_us`` (a
    robot rig)."""

    patterns: tuple[NWirePattern, ...]
    T_base_phantom: Array | None = None

    def to_yaml(self) -> dict[str, Any]:
        """The manifest's ``acquisition.phantom`` (millimetres)."""
        out: dict[str, Any] = {
            "kind": "nwire",
            "patterns": [
                [
                    {
                        "name": w.name,
                        "front_mm": [round(float(v) / _MM, 6) for v in w.front],
                        "back_mm": [round(float(v) / _MM, 6) for v in w.back],
                    }
                    for w in p.wires
                ]
                for p in self.patterns
            ],
        }
        if self.T_base_phantom is not None:
            T = np.array(self.T_base_phantom, dtype=float)
            T[:3, 3] /= _MM
            out["T_base_phantom_mm"] = np.round(T, 9).tolist()
        return out

    @classmethod
    def from_yaml(cls, path: Path, doc: Any) -> NWirePhantom:
        """Read :meth:`to_yaml`'s mapping; one line naming what is wrong."""
        where = "acquisition.phantom"
        if not isinstance(doc, dict) or doc.get("kind") != "nwire":
            raise DatasetError(f"{path}: {where} must be a mapping with kind: nwire")
        patterns = doc.get("patterns")
        if not isinstance(patterns, list) or not patterns:
            raise DatasetError(f"{path}: {where}.patterns must list the N patterns")
        read = []
        for k, p in enumerate(patterns):
            if not isinstance(p, list) or not all(isinstance(w, dict) for w in p):
                raise DatasetError(f"{path}: {where}.patterns[{k}] must list wires")
            wires = [
                (str(w.get("name", "")), _text(w.get("front_mm")), _text(w.get("back_mm")))
                for w in p
            ]
            read.append(_pattern(path, f"{where}.patterns[{k}]", wires))
        T = doc.get("T_base_phantom_mm")
        T_m = None
        if T is not None:
            rows = T if isinstance(T, list) and all(isinstance(r, list) for r in T) else []
            T_m = _matrix_m(
                path, f"{where}.T_base_phantom_mm", " ".join(_text(r) for r in rows) or repr(T)
            )
        return cls(tuple(read), T_m)


@dataclass(frozen=True)
class PlusConfig:
    """What a PLUS device set configuration says of a calibration: its coordinate
    definitions (``(From, To)`` → ``T_To_From``, metres; pixels in and out of the image
    frames) and its N-wire patterns; the
    sequence file its simulation mode replays, when it names one."""

    path: Path
    transforms: dict[tuple[str, str], Array]
    patterns: tuple[NWirePattern, ...]
    sequence_file: str | None

    def transform(self, source: str, target: str) -> Array:
        """``T_target_source``: a coordinate definition, or the inverse of the one the
        other way; one line listing the definitions when there is neither."""
        if (source, target) in self.transforms:
            return self.transforms[(source, target)]
        if (target, source) in self.transforms:
            return np.linalg.inv(self.transforms[(target, source)])
        known = ", ".join(f"{a}To{b}" for a, b in self.transforms)
        raise DatasetError(
            f"{self.path}: no coordinate definition {source}To{target}; it defines {known}"
        )

    def pixel_spacing_mm(self) -> tuple[float, float]:
        """The image's pixel spacing (columns, rows; mm) as PLUS's
        ``TransducerOriginPixel`` → ``TransducerOrigin`` definition gives it."""
        S = self.transform("TransducerOriginPixel", "TransducerOrigin")
        return float(np.linalg.norm(S[:3, 0])) * 1e3, float(np.linalg.norm(S[:3, 1])) * 1e3


@dataclass(frozen=True)
class PlusFrameSegmentation:
    """fCal's segmentation of one frame: ``ok``, the wire points it found (wire name →
    (column, row) in pixels) and the frame's tracked transforms as the results file
    records them (``ProbeToTrackerTransform`` → 4 × 4 in metres; only those with status
    OK)."""

    index: int
    ok: bool
    points: dict[str, tuple[float, float]]
    transforms: dict[str, Array] = field(default_factory=dict)

    def transform(self, name: str) -> Array:
        """A recorded transform, or the one composed from two through their common frame
        (``ProbeToReference`` = ``ReferenceToTracker``⁻¹ · ``ProbeToTracker``); one line
        when the frame has neither."""
        source, _, target = name.removesuffix("Transform").partition("To")
        if f"{source}To{target}Transform" in self.transforms:
            return self.transforms[f"{source}To{target}Transform"]
        for key, T in self.transforms.items():
            a, _, via = key.removesuffix("Transform").partition("To")
            other = self.transforms.get(f"{target}To{via}Transform")
            if a == source and other is not None:
                return np.linalg.inv(other) @ T
        raise DatasetError(
            f"frame {self.index}: no {name}, nor two transforms composing it, among "
            + (", ".join(sorted(self.transforms)) or "none with status OK")
        )


@dataclass(frozen=True)
class PlusResults:
    """fCal's result: ``image_to_probe`` maps image pixels (column, row, 0, 1) to the
    probe frame in metres (PLUS's ``ImageToProbe``, pixel spacing included); the mean and
    SD of its 3-D reprojection error (mm) on the calibration and validation frames; the
    2-D error per wire (pixels); its segmentation of every frame of both sets."""

    path: Path
    image_to_probe: Array
    reprojection_3d_mm: dict[str, float]
    reprojection_2d_px: dict[str, dict[str, tuple[float, float]]]
    calibration: tuple[PlusFrameSegmentation, ...]
    validation: tuple[PlusFrameSegmentation, ...]


def _parse(path: str | os.PathLike[str], what: str) -> tuple[Path, ET.Element]:
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except OSError as e:
        raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
    except ET.ParseError as e:
        raise DatasetError(f"{path}: not {what} (not XML: {e})") from None
    return path, root


def _numbers(path: Path, where: str, text: str | None, n: int) -> Array:
    try:
        v = np.array([float(x) for x in (text or "").split()])
    except ValueError:
        v = np.array([])
    if len(v) != n or not np.all(np.isfinite(v)):
        raise DatasetError(f"{path}: {where} must be {n} numbers, got {(text or '')[:60]!r}")
    return v


def _is_pixel(frame: str) -> bool:
    """PLUS's frames in pixels: the image and those named ``...Pixel``."""
    return frame == "Image" or frame.endswith("Pixel")


def _matrix_m(
    path: Path, where: str, text: str | None, source: str = "", target: str = ""
) -> Array:
    """A PLUS ``Matrix`` attribute (16 numbers, row-major, mm) in metres: its output in
    metres unless the ``target`` frame is in pixels; a pixel ``source`` frame mapped to a
    metric one has its scale (mm per pixel) in metres per pixel too."""
    T = _numbers(path, where, text, 16).reshape(4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise DatasetError(f"{path}: {where} is not a homogeneous transform (last row)")
    if not _is_pixel(target):
        T[:3, 3] *= _MM
        if _is_pixel(source):
            T[:3, :3] *= _MM
    return T


def _text(v: Any) -> str:
    """A list of numbers from YAML as the space-separated text PLUS's XML holds."""
    return " ".join(str(x) for x in v) if isinstance(v, list) else ""


def _pattern(
    path: Path, where: str, read: Sequence[tuple[str, str | None, str | None]]
) -> NWirePattern:
    """One N pattern from its wires' (name, front, back) as text (millimetres)."""
    wires = []
    for name, front_text, back_text in read:
        name = name or f"wire {len(wires) + 1}"
        front = _numbers(path, f"{where} {name} EndPointFront", front_text, 3)
        back = _numbers(path, f"{where} {name} EndPointBack", back_text, 3)
        if np.linalg.norm(back - front) < 1.0:
            raise DatasetError(f"{path}: {where}: wire {name} has no length")
        wires.append(NWire(name, front * _MM, back * _MM))
    if len(wires) != 3:
        raise DatasetError(
            f"{path}: {where} has {len(wires)} wires; an N pattern has three (two parallel "
            "outer wires and the diagonal between them)"
        )
    a, m, b = wires
    angle = np.degrees(np.arccos(min(abs(float(a.direction @ b.direction)), 1.0)))
    diagonal = np.degrees(np.arccos(min(abs(float(a.direction @ m.direction)), 1.0)))
    normal = np.cross(a.direction, b.front - a.front)
    if angle > _PARALLEL_DEG or diagonal <= _PARALLEL_DEG or np.linalg.norm(normal) == 0:
        raise DatasetError(
            f"{path}: {where} ({a.name}, {m.name}, {b.name}) is not an N: its outer wires "
            f"are {angle:.1f}° apart and its middle wire {diagonal:.1f}° off them (outer "
            f"wires parallel within {_PARALLEL_DEG:g}°, the middle one across them)"
        )
    normal /= np.linalg.norm(normal)
    off = max(abs(float(normal @ (p - a.front))) for p in (m.front, m.back, b.back)) / _MM
    if off > _COPLANAR_MM:
        raise DatasetError(
            f"{path}: {where} is not an N: its wires are {off:.2f} mm out of one plane"
        )
    return NWirePattern((a, m, b))


def read_plus_config(path: str | os.PathLike[str], *, phantom: bool = True) -> PlusConfig:
    """Read a PLUS device set configuration: its coordinate definitions and N-wire
    phantom (``PhantomDefinition/Geometry/Pattern Type="NWire"``; with ``phantom``
    False, a configuration without one reads too, for its transforms)."""
    path, root = _parse(path, "a PLUS configuration")
    if root.tag != "PlusConfiguration":
        raise DatasetError(
            f"{path}: not a PLUS configuration (its root element is <{root.tag}>, not "
            "<PlusConfiguration>)"
        )
    transforms = {}
    for t in root.findall("CoordinateDefinitions/Transform"):
        source, target = t.get("From"), t.get("To")
        if not source or not target:
            raise DatasetError(f"{path}: a CoordinateDefinitions transform without From/To")
        transforms[(source, target)] = _matrix_m(
            path, f"CoordinateDefinitions {source}To{target}", t.get("Matrix"), source, target
        )
    geometry = root.find("PhantomDefinition/Geometry")
    if geometry is None and not phantom:
        return PlusConfig(path, transforms, (), None)
    if geometry is None:
        raise DatasetError(
            f"{path}: no PhantomDefinition/Geometry: the configuration defines no phantom "
            "to calibrate with"
        )
    found = [p for p in geometry.findall("Pattern") if p.get("Type") == "NWire"]
    if not found:
        raise DatasetError(f"{path}: the PhantomDefinition has no NWire pattern")
    patterns = tuple(
        _pattern(
            path,
            f"PhantomDefinition pattern {k + 1}",
            [
                (w.get("Name") or "", w.get("EndPointFront"), w.get("EndPointBack"))
                for w in p.findall("Wire")
            ],
        )
        for k, p in enumerate(found)
    )
    device = root.find(".//Device[@SequenceFile]")
    return PlusConfig(
        path, transforms, patterns, None if device is None else device.get("SequenceFile")
    )


def _frames(path: Path, element: ET.Element | None) -> tuple[PlusFrameSegmentation, ...]:
    if element is None:
        return ()
    out = []
    for f in element.findall("Frame"):
        index = int(_numbers(path, "a Frame's Index", f.get("Index"), 1)[0])
        points = {}
        for p in f.findall("SegmentedPoints/Point"):
            name = p.get("WireName") or ""
            x, y, _ = _numbers(path, f"frame {index} point {name}", p.get("Position"), 3)
            points[name] = (float(x), float(y))
        fields = {c.get("Name"): c.get("Value") for c in f.findall("TrackedFrame/CustomFrameField")}
        transforms = {
            name: _matrix_m(path, f"frame {index} {name}", value, "x", "y")
            for name, value in fields.items()
            if name
            and name.endswith("Transform")
            and str(fields.get(name + "Status", "OK")).upper() == "OK"
        }
        out.append(
            PlusFrameSegmentation(index, f.get("SegmentationStatus") == "OK", points, transforms)
        )
    return tuple(out)


def read_plus_results(path: str | os.PathLike[str]) -> PlusResults:
    """Read fCal's calibration results file (``ProbeCalibrationResult``)."""
    path, root = _parse(path, "a PLUS calibration result")
    if root.tag != "ProbeCalibrationResult":
        raise DatasetError(
            f"{path}: not a PLUS calibration result (its root element is <{root.tag}>)"
        )
    result = root.find("CalibrationResults/Transform[@From='Image'][@To='Probe']")
    if result is None:
        raise DatasetError(f"{path}: no Image → Probe transform in its CalibrationResults")
    T = _matrix_m(path, "ImageToProbe", result.get("Matrix"), "Image", "Probe")
    stats = root.find("ErrorReport/ReprojectionError3DStatistics")
    keys = {
        "calibration_mean_mm": "CalibrationMeanMm",
        "calibration_sd_mm": "CalibrationStdDevMm",
        "validation_mean_mm": "ValidationMeanMm",
        "validation_sd_mm": "ValidationStdDevMm",
    }
    errors_3d = {}
    if stats is not None:
        for key, attr in keys.items():
            if stats.get(attr) is not None:
                errors_3d[key] = float(_numbers(path, attr, stats.get(attr), 1)[0])
    errors_2d = {}
    for w in root.findall("ErrorReport/ReprojectionError2DStatistics/Wire"):
        errors_2d[w.get("Name") or ""] = {
            key: tuple(float(v) for v in _numbers(path, f"{w.get('Name')} {attr}", w.get(attr), 2))
            for key, attr in (("calibration_mean_px", "CalibrationMeanPx"),
                              ("validation_mean_px", "ValidationMeanPx"))
            if w.get(attr) is not None
        }  # fmt: skip
    report = root.find("ErrorReport")
    return PlusResults(
        path,
        T,
        errors_3d,
        errors_2d,
        _frames(path, None if report is None else report.find("CalibrationData")),
        _frames(path, None if report is None else report.find("ValidationData")),
    )


def image_to_probe_mm(T_ee_us: Array, width_px: int, spacing_m: tuple[float, float]) -> Array:
    """PLUS's ``ImageToProbe``: pixel (i = column, j = row, 0, 1) → probe (ee) millimetres.

    PLUS keeps the pixel spacing in this transform, not in the image: it is
    ``T_ee_us`` (in mm) times the pixel-to-``us`` map of :mod:`calib.image`
    (x = (i − (W − 1)/2)·sx, y = j·sy); :func:`us_of_image_to_probe` inverts it."""
    sx, sy = (float(s) / _MM for s in spacing_m)
    S = np.array(
        [[sx, 0.0, 0.0, -(width_px - 1) / 2 * sx], [0.0, sy, 0.0, 0.0], [0, 0, 1, 0], [0, 0, 0, 1]]
    )
    T = np.asarray(T_ee_us, dtype=float).copy()
    T[:3, 3] /= _MM
    return T @ S


def us_of_image_to_probe(
    image_to_probe_mm: Array, width_px: int
) -> tuple[Array, tuple[float, float]]:
    """``T_ee_us`` (metres) and the pixel spacing (columns, rows; metres) a PLUS
    ``ImageToProbe`` (pixel → probe mm, spacing included) holds, for images ``width_px``
    wide: the inverse of writing one (uscal's ``us`` frame has its origin at the centre of
    the top row, x along the columns, y along the rows). PLUS's matrix need not be
    exactly a scaled rotation; its columns are orthonormalized (nearest rotation)."""
    A = np.asarray(image_to_probe_mm, dtype=float)
    sx, sy = float(np.linalg.norm(A[:3, 0])), float(np.linalg.norm(A[:3, 1]))
    if not (sx > 0 and sy > 0):
        raise DatasetError("ImageToProbe has a zero column: not an image-to-probe transform")
    x, y = A[:3, 0] / sx, A[:3, 1] / sy
    R = se3.nearest_rotation(np.column_stack([x, y, np.cross(x, y)]))
    origin = (A @ np.array([(width_px - 1) / 2, 0.0, 0.0, 1.0]))[:3]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, origin * _MM
    return T, (sx * _MM, sy * _MM)
