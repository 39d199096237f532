"""PLUS recordings as uscal datasets: the method on a tracked probe.

A PLUS sequence metafile holds B-mode frames and, per frame, the transforms PLUS
recorded (``ProbeToTrackerTransform`` …: row-major, millimetres, each with a status).
The method needs one pose per frame that maps the probe's rigid body into a fixed frame;
it does not care whether a robot or a tracker measured it. With a tracked probe the
pose transform is ``ProbeToTrackerTransform`` (``T_tracker_probe``): the tracker plays the
robot base, the probe's marker body plays the flange, and the calibration is
``T_probe_image`` (PLUS's ``ImageToProbe`` without the pixel spacing).

Each sweep is one file, or each run of ``frames_per_sweep`` frames of a file: a linear
sweep at a fixed orientation, as the method localizes a sphere from the section radius
along the sweep. A sweep that turns more than ``max_turn_deg`` or does not move is
refused with one line naming it. Frames whose pose or image status is not ``OK`` are
skipped and counted. Writing goes to a temporary sibling directory renamed at the end:
a failed import leaves nothing behind.
"""

from __future__ import annotations

import os
import re
import shutil
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..errors import DatasetError
from ..records import Sweep
from .dataset import AcquisitionInfo, DatasetWriter
from .metafile import Metafile, read_metafile
from .plus_config import NWirePhantom, PlusConfig

__all__ = [
    "NWIRE_TARGET",
    "PLUS_CALIBRATION_POSE",
    "ImportSummary",
    "PlusFrames",
    "import_plus",
    "plus_frames",
]

Array = NDArray[np.float64]

#: The pose PLUS's freehand calibration uses: the probe in the phantom's reference body.
PLUS_CALIBRATION_POSE = "ProbeToReferenceTransform"
#: The target name of an N-wire phantom's frames in a dataset.
NWIRE_TARGET = "nwire"
#: A sweep needs enough frames to follow the section radius across the sphere.
MIN_FRAMES_PER_SWEEP = 5
#: PLUS's default ElementSpacing: PLUS keeps the pixel spacing in ImageToProbe instead.
_PLUS_DEFAULT_SPACING = (1.0, 1.0)


@dataclass(frozen=True)
class PlusFrames:
    """The usable frames of one file: images (MF), poses (metres) of the transform
    ``pose_name``, timestamps (s), the file's pixel spacing (None: PLUS's default, not
    the image's) and how many frames were skipped for which reason."""

    path: Path
    pose_name: str
    images: NDArray[np.uint8]
    T_base_probe: Array
    timestamps: Array
    spacing_mm: tuple[float, float] | None
    skipped: Counter[str] = field(default_factory=Counter)


_LINK = re.compile(r"^([A-Z][A-Za-z0-9]*?)To([A-Z][A-Za-z0-9]*)Transform$")


def _transform_chain(meta: Metafile, name: str) -> list[tuple[str, bool]]:
    """``name`` (``ProbeToReference`` or ``ProbeToReferenceTransform``) as the per-frame
    transforms the file records, composed as PLUS's transform repository composes them:
    (field, inverted) links from the ``From`` frame to the ``To`` frame, e.g.
    ``ProbeToReference`` = ``ReferenceToTracker``⁻¹ · ``ProbeToTracker``. One line listing
    the file's transforms when no chain connects the two."""
    full = _full(name)
    names = [n for n in meta.frame_names() if n.endswith("Transform")]
    if full in names:
        return [(full, False)]
    wanted = _LINK.match(full)
    # Edges between coordinate frames, both ways (a link read backwards is inverted).
    edges: dict[str, list[tuple[str, str, bool]]] = {}
    for n in names:
        m = _LINK.match(n)
        if m:
            a, b = m.groups()
            edges.setdefault(a, []).append((b, n, False))
            edges.setdefault(b, []).append((a, n, True))
    if wanted:
        start, goal = wanted.groups()
        previous: dict[str, tuple[str, str, bool] | None] = {start: None}
        queue = [start]
        while queue and goal not in previous:
            here = queue.pop(0)
            for there, field_name, inverted in edges.get(here, []):
                if there not in previous:
                    previous[there] = (here, field_name, inverted)
                    queue.append(there)
        if goal in previous and goal != start:
            chain = []
            node = goal
            while previous[node] is not None:
                here, field_name, inverted = previous[node]  # type: ignore[misc]
                chain.append((field_name, inverted))
                node = here
            return chain[::-1]
    raise DatasetError(
        f"{meta.path}: no per-frame transform {full!r}, nor a chain of them from "
        + (f"{wanted.group(1)} to {wanted.group(2)}" if wanted else "one frame to another")
        + "; the file records "
        + (", ".join(sorted(names)) if names else "none")
    )


def plus_frames(path: str | os.PathLike[str], pose_transform: str) -> PlusFrames:
    """Read one PLUS file's frames with the per-frame transform ``pose_transform`` as
    the probe's pose (recorded, or composed from the transforms recorded:
    :func:`_transform_chain`); frames whose pose (any link of it) or image status is not
    OK are skipped. A file without timestamps (PLUS writes none for a single image, and
    some recordings have none) numbers its frames instead."""
    meta = read_metafile(path)
    chain = _transform_chain(meta, pose_transform)
    keep, poses, times = [], [], []
    skipped: Counter[str] = Counter()
    for j in range(len(meta.images)):
        image_status = meta.frame_field(j, "ImageStatus", default="OK")
        if str(image_status).upper() != "OK":
            skipped[f"ImageStatus {image_status}"] += 1
            continue
        bad = [
            (link, status)
            for link, _ in chain
            if str(status := meta.frame_field(j, f"{link}Status", default="OK")).upper() != "OK"
        ]
        if bad:
            skipped[f"{bad[0][0]}Status {bad[0][1]}"] += 1
            continue
        T = np.eye(4)
        for link, inverted in chain:
            L = meta.transform(j, link)
            T = (se3.invert(L) if inverted else L) @ T
        poses.append(T)
        times.append(meta.timestamp(j))
        keep.append(j)
    spacing = meta.spacing_mm()
    t = np.array(times, dtype=float)
    if np.isnan(t).any():
        t = np.array(keep, dtype=float)  # no timestamps: the frames in order
    return PlusFrames(
        meta.path,
        _full(pose_transform),
        meta.images[keep],
        np.array(poses).reshape(-1, 4, 4),
        t,
        None if spacing == _PLUS_DEFAULT_SPACING else spacing,
        skipped,
    )


def _full(name: str) -> str:
    return name if name.endswith("Transform") else name + "Transform"


@dataclass(frozen=True)
class ImportSummary:
    """What an import wrote: the dataset, its sweeps and frames, the frames skipped (by
    reason) and each sweep's length and turn."""

    directory: Path
    sweeps: int
    frames: int
    skipped: Counter[str]
    sweep_lines: list[str]
    nwire: bool = False


def _check_sweep(label: str, T: Array, max_turn_deg: float) -> tuple[float, float]:
    """The sweep's length (mm) and largest turn (°) from its first frame; one line if it
    is not a linear sweep at a fixed orientation."""
    if len(T) < MIN_FRAMES_PER_SWEEP:
        raise DatasetError(
            f"{label}: {len(T)} usable frames; a sweep needs at least {MIN_FRAMES_PER_SWEEP}"
        )
    turn = float(np.degrees(max(se3.rotation_angle(T[0], Tj) for Tj in T)))
    if turn > max_turn_deg:
        raise DatasetError(
            f"{label}: the probe turns by {turn:.2f}° within the sweep; the method needs a "
            f"linear sweep at a fixed orientation (at most --max-turn-deg {max_turn_deg:g}°)"
        )
    length_mm = 1e3 * float(np.linalg.norm(T[-1, :3, 3] - T[0, :3, 3]))
    if length_mm < 1.0:
        raise DatasetError(
            f"{label}: the probe moves {length_mm:.2f} mm from the first frame to the last; "
            "a sweep must pass through the sphere"
        )
    return length_mm, turn


def import_plus(
    files: Sequence[str | os.PathLike[str]],
    *,
    pose_transform: str | None,
    target: str,
    out: str | os.PathLike[str],
    radius_mm: float | None,
    temperature_c: float | None,
    spacing_mm: tuple[float, float] | None = None,
    frames_per_sweep: int | None = None,
    max_turn_deg: float = 1.0,
    assumed_speed_m_s: float = 1540.0,
    config: PlusConfig | None = None,
) -> ImportSummary:
    """Turn PLUS recordings into a uscal dataset at ``out`` (which must not exist).

    Spheres (no ``config``): ``radius_mm`` the sphere's; each file (or run of
    ``frames_per_sweep`` frames) a linear sweep. An N-wire phantom (``config``, a PLUS
    device set with its ``PhantomDefinition``): each file's frames as recorded (freehand,
    no sweep shape asked), the phantom's patterns and its pose in the pose transform's
    base frame (``Phantom`` → ``Reference`` for PLUS's default ``ProbeToReference``) in
    the manifest, the pixel spacing from the configuration's ``TransducerOriginPixel`` →
    ``TransducerOrigin`` when the files hold none.

    ``temperature_c``: the water's (the axial spacing is corrected from the scanner's
    ``assumed_speed_m_s``); None: no correction (the medium matches the scanner).
    ``spacing_mm`` overrides the files' pixel spacing (needed when they hold PLUS's
    default 1 × 1, the spacing then being in PLUS's ImageToProbe).
    """
    out = Path(out)
    if pose_transform is None:
        if config is None:
            raise DatasetError("--pose-transform: name the per-frame transform of the probe")
        pose_transform = PLUS_CALIBRATION_POSE
    if config is None and radius_mm is None:
        raise DatasetError(
            "--radius-mm: the sphere's CAD radius is needed (or --config PLUS_CONFIG.xml "
            "for an N-wire phantom)"
        )
    if temperature_c is not None and not 0.0 <= temperature_c <= 60.0:
        raise DatasetError(
            f"--temperature-c {temperature_c:g}: the water's temperature in °C, 0 to 60"
        )
    if out.exists():
        raise DatasetError(f"{out}: already exists; choose a new dataset directory")
    if not files:
        raise DatasetError("no PLUS files to import")
    read = [plus_frames(f, pose_transform) for f in files]
    shape = read[0].images.shape[1:]
    for r in read[1:]:
        if r.images.shape[1:] != shape:
            raise DatasetError(
                f"{r.path}: frames of {r.images.shape[2]} × {r.images.shape[1]} px; "
                f"{read[0].path} has {shape[1]} × {shape[0]}"
            )
    spacing = spacing_mm
    if spacing is None:
        found = {r.spacing_mm for r in read}
        if found == {None} and config is not None:
            found = {config.pixel_spacing_mm()}
        if None in found or len(found) != 1:
            raise DatasetError(
                f"{read[0].path}: the pixel spacing is not in the files (ElementSpacing is "
                "PLUS's default 1 1, or differs between files): give --spacing-mm SX SY"
            )
        spacing = found.pop()
    phantom = None
    if config is not None:
        base = _LINK.match(_full(pose_transform))
        phantom = NWirePhantom(
            config.patterns, config.transform("Phantom", base.group(2) if base else "")
        )
        target = NWIRE_TARGET
    sweeps: list[tuple[Sweep, Array]] = []
    lines = []
    for r in read:
        n = len(r.images)
        if phantom is not None:  # freehand frames of the N-wire phantom, as recorded
            if n == 0:
                raise DatasetError(f"{r.path}: no usable frames ({dict(r.skipped)})")
            sweeps.append(
                (
                    Sweep(
                        target,
                        len(sweeps),
                        r.images,
                        (spacing[0] * 1e-3, spacing[1] * 1e-3),
                        np.full((n, 6), np.nan),
                        r.T_base_probe,
                    ),
                    r.timestamps,
                )
            )
            lines.append(f"sequence {len(sweeps) - 1}: {r.path}, {n} frames")
            continue
        step = frames_per_sweep or max(n, 1)
        for start in range(0, max(n, 1), step):
            sl = slice(start, start + step)
            part = f" frames {start}–{min(n, start + step) - 1}" if step < n else ""
            label = f"{r.path}{part}"
            length, turn = _check_sweep(label, r.T_base_probe[sl], max_turn_deg)
            pose_id = len(sweeps)
            images = r.images[sl]
            sweeps.append(
                (
                    Sweep(
                        target,
                        pose_id,
                        images,
                        (spacing[0] * 1e-3, spacing[1] * 1e-3),
                        np.full((len(images), 6), np.nan),
                        r.T_base_probe[sl],
                    ),
                    r.timestamps[sl],
                )
            )
            lines.append(
                f"sweep {pose_id}: {label}, {len(images)} frames, {length:.1f} mm, turn {turn:.2f}°"
            )
    info = AcquisitionInfo(
        T_ee_us_coarse=None,
        landmarks={},
        sphere_radius_mm=float("nan") if radius_mm is None else radius_mm,
        temperature_c=20.0 if temperature_c is None else temperature_c,
        assumed_speed_m_s=assumed_speed_m_s,
        sound_speed_correction=temperature_c is not None,
        source="plus",
        extra={
            "imported_from": [str(Path(f)) for f in files],
            "pose_transform": read[0].pose_name,
            **({"plus_config": str(config.path)} if config is not None else {}),
        },
        nwire=phantom,
    )
    tmp = out.with_name(f".{out.name}.importing-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        writer = DatasetWriter(tmp, out.name, info, {"spacing_mm": list(spacing)})
        for sweep, t in sweeps:
            writer.add_sweep(sweep, timestamps=t)
        writer.finish()
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    skipped: Counter[str] = Counter()
    for r in read:
        skipped.update(r.skipped)
    return ImportSummary(
        out, len(sweeps), sum(len(s.images) for s, _ in sweeps), skipped, lines, phantom is not None
    )
