"""Dataset files: what an acquisition recorded, on disk, shareable between labs.

A dataset is a directory:

``dataset.yaml``
    The manifest: format and version, the acquisition settings a reader needs (image
    spacing, medium temperature, the speed of sound the scanner assumes, the phantom's
    CAD landmarks, the holder's coarse ``T_ee_us``, the stylus), the sweeps in
    acquisition order (file, target, pose id, frame count), the touches, and whether
    the acquisition is complete.
``sweeps/<target>_pose<NN>.mha``
    One PLUS sequence metafile per sweep (opens in 3D Slicer's Sequences module and in
    PLUS): the frames as one ``MET_UCHAR`` volume (columns, rows, frames), the pixel
    spacing in millimetres, ``UltrasoundImageOrientation = MFA`` (columns toward the
    transducer's marked side, rows away from it; the third letter PLUS writes for a
    sequence), ``Kinds = domain domain list`` and per frame ``EEToBaseTransform`` (the
    controller's flange pose ``T_base_ee``, row-major, millimetres, as PLUS writes its
    ``<From>To<To>Transform`` fields), its status, a timestamp and, from a robot, the
    reported joint angles (``JointAnglesRad``, radians; absent for a tracked probe).

Writing is atomic per file (write to a temporary name, then rename), and the manifest
is rewritten after each sweep: a crash loses at most the sweep in progress, and an
interrupted acquisition resumes from the sweeps the manifest lists.

Reading never executes or unpickles anything: the manifest is read with YAML's safe
loader, a metafile is a text header of ``key = value`` lines and raw bytes (optionally
zlib-compressed, as PLUS writes them). Every check that fails raises one
:class:`DatasetError` naming the file and what is wrong.
"""

from __future__ import annotations

import contextlib
import os
import re
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..errors import DatasetError
from ..records import Dataset, Sweep, Touch
from .metafile import (
    atomic_file,
    checked_rigid,
    metres_of,
    mm_decimal,
    read_sequence,
    write_sequence,
)
from .plus_config import NWire, NWirePhantom

__all__ = [
    "FORMAT",
    "VERSION",
    "AcquisitionInfo",
    "ConeTipPhantom",
    "DatasetWriter",
    "WirePhantom",
    "dataset_kind",
    "read_dataset",
]

Array = NDArray[np.float64]

FORMAT = "uscal-dataset"
VERSION = 1
MANIFEST = "dataset.yaml"
_NUMBER = (int, float, Decimal)


# ------------------------------------------------------------------------- manifest


@dataclass(frozen=True)
class WirePhantom:
    """A single straight wire in a dataset (the twin's single-wire phantom, or a rig's):
    its ends in the phantom frame (metres); the phantom's pose in the base is unknown and
    estimated with ``T_ee_us`` as far as a line tells it."""

    wire: NWire

    def to_yaml(self) -> dict[str, Any]:
        """The manifest's ``acquisition.phantom`` (millimetres)."""
        w = self.wire
        return {
            "kind": "wire",
            "wire": {
                "name": w.name,
                "front_mm": [round(float(v) * 1e3, 6) for v in w.front],
                "back_mm": [round(float(v) * 1e3, 6) for v in w.back],
            },
        }

    @classmethod
    def from_yaml(cls, path: Path, doc: Any) -> WirePhantom:
        """Read :meth:`to_yaml`'s mapping; one line naming what is wrong."""
        where = "acquisition.phantom.wire"
        w = doc.get("wire") if isinstance(doc, dict) else None
        if not isinstance(w, dict):
            raise DatasetError(f"{path}: {where} must be a mapping with front_mm and back_mm")
        front = _vector(path, f"{where}.front_mm", w.get("front_mm"), 3) * 1e-3
        back = _vector(path, f"{where}.back_mm", w.get("back_mm"), 3) * 1e-3
        if np.linalg.norm(back - front) < 1e-3:
            raise DatasetError(f"{path}: {where}: the wire's ends are less than 1 mm apart")
        return cls(NWire(str(w.get("name", "wire")), front, back))


@dataclass(frozen=True)
class ConeTipPhantom:
    """A cone whose tip is the target (the paper's printed cone): its apex in the
    phantom frame (metres); the phantom's pose in the base is unknown and estimated with
    ``T_ee_us`` as far as a point tells it."""

    apex: Array

    def to_yaml(self) -> dict[str, Any]:
        """The manifest's ``acquisition.phantom`` (millimetres)."""
        return {"kind": "cone_tip", "apex_mm": [round(float(v) * 1e3, 6) for v in self.apex]}

    @classmethod
    def from_yaml(cls, path: Path, doc: Any) -> ConeTipPhantom:
        """Read :meth:`to_yaml`'s mapping; one line naming what is wrong."""
        apex = doc.get("apex_mm") if isinstance(doc, dict) else None
        return cls(_vector(path, "acquisition.phantom.apex_mm", apex, 3) * 1e-3)


@dataclass(frozen=True)
class AcquisitionInfo:
    """What a reader needs besides the frames and poses (the manifest's settings).

    ``T_ee_us_coarse`` (4, 4) metres: the holder's CAD estimate (None: none known, as
    for an imported tracked probe; the calibration's closed-form start needs none);
    ``landmarks`` name ->
    (3,) metres in the phantom's CAD frame (``sphere_i``, ``vertex_j``);
    ``sphere_radius_mm`` the CAD radius; ``temperature_c`` the medium's;
    ``assumed_speed_m_s`` the scanner's; ``sound_speed_correction`` whether the axial
    spacing is to be rescaled; ``stylus_tip_cad_mm`` the stylus tip in the flange
    frame (touches only); ``source`` "twin" or "hardware"; ``target_depth_mm`` the depth
    at which the plan put each sphere in the image (the localizer searches about it; None:
    not recorded, the whole image); ``extra`` anything else.
    """

    T_ee_us_coarse: Array | None
    landmarks: dict[str, Array]
    sphere_radius_mm: float
    temperature_c: float
    assumed_speed_m_s: float
    sound_speed_correction: bool = True
    medium: str = "water"
    stylus_tip_cad_mm: tuple[float, float, float] | None = None
    source: str = "hardware"
    target_depth_mm: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    nwire: NWirePhantom | None = None
    wire: WirePhantom | None = None
    cone_tip: ConeTipPhantom | None = None

    def to_yaml(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "source": self.source,
            "medium": self.medium,
            "temperature_c": float(self.temperature_c),
            "assumed_speed_m_s": float(self.assumed_speed_m_s),
            "sound_speed_correction": bool(self.sound_speed_correction),
        }
        if self.nwire is not None:
            out["phantom"] = self.nwire.to_yaml()
        elif self.wire is not None:
            out["phantom"] = self.wire.to_yaml()
        elif self.cone_tip is not None:
            out["phantom"] = self.cone_tip.to_yaml()
        else:
            out["sphere_radius_mm"] = float(self.sphere_radius_mm)
        if self.T_ee_us_coarse is not None:
            out["T_ee_us_coarse_mm"] = _matrix_mm(self.T_ee_us_coarse)
        out["landmarks_mm"] = {k: [mm_decimal(x) for x in v] for k, v in self.landmarks.items()}
        if self.stylus_tip_cad_mm is not None:
            out["stylus_tip_cad_mm"] = [float(v) for v in self.stylus_tip_cad_mm]
        if self.target_depth_mm is not None:
            out["target_depth_mm"] = float(self.target_depth_mm)
        if self.extra:
            out["extra"] = self.extra
        return out


def _matrix_mm(T: Array) -> list[list[float | Decimal]]:
    T = np.asarray(T, dtype=float)
    return [
        [mm_decimal(T[i, j]) if j == 3 and i < 3 else float(T[i, j]) for j in range(4)]
        for i in range(4)
    ]


def _sweep_file(target: str, pose_id: int) -> str:
    safe = re.sub(r"[^A-Za-z0-9_-]", "_", target)
    return f"sweeps/{safe}_pose{pose_id:02d}.mha"


class DatasetWriter:
    """Writes a dataset sweep by sweep; each call leaves a consistent dataset on disk.

    ``resume=True`` opens an existing, unfinished dataset and keeps its sweeps
    (:meth:`has`); otherwise the directory must not hold a dataset yet.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        name: str,
        info: AcquisitionInfo,
        image_meta: Mapping[str, Any] | None = None,
        resume: bool = False,
    ) -> None:
        import yaml  # the manifest: written here, read with the safe loader only

        self._yaml = yaml
        self.directory = Path(directory)
        manifest = self.directory / MANIFEST
        self._sweeps: list[dict[str, Any]] = []
        self._touches: list[dict[str, Any]] = []
        if manifest.exists():
            if not resume:
                raise DatasetError(
                    f"{self.directory}: already holds a dataset (resume it, or choose "
                    "another directory)"
                )
            old = _load_manifest(manifest)
            if old.get("complete"):
                raise DatasetError(f"{self.directory}: the dataset is already complete")
            self._sweeps = list(old.get("sweeps") or [])
            self._touches = list(old.get("touches") or [])
        elif self.directory.exists() and any(self.directory.iterdir()):
            raise DatasetError(f"{self.directory}: directory exists and is not a dataset")
        self._created = not self.directory.exists()
        (self.directory / "sweeps").mkdir(parents=True, exist_ok=True)
        self._head = {
            "format": FORMAT,
            "version": VERSION,
            "name": name,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "acquisition": info.to_yaml(),
            "image": dict(image_meta or {}),
        }
        self._complete = False
        self._write_manifest()

    def has(self, target: str, pose_id: int) -> bool:
        """Whether a sweep of the plan is already on disk (resume)."""
        return any(s["target"] == target and s["pose_id"] == pose_id for s in self._sweeps)

    def has_touch(self, vertex: str, index: int) -> bool:
        """Whether a touch of the plan is already recorded (resume)."""
        return any(t["vertex"] == vertex and t["index"] == index for t in self._touches)

    @property
    def n_sweeps(self) -> int:
        return len(self._sweeps)

    def add_sweep(self, sweep: Sweep, *, timestamps: Array | None = None) -> Path:
        """Write one sweep's metafile, then list it in the manifest."""
        rel = _sweep_file(sweep.target, int(sweep.pose_id))
        t = np.arange(sweep.n_frames, dtype=float) if timestamps is None else timestamps
        write_sequence(self.directory / rel, sweep, t)
        self._sweeps = [
            s for s in self._sweeps if (s["target"], s["pose_id"]) != (sweep.target, sweep.pose_id)
        ]
        self._sweeps.append(
            {
                "file": rel,
                "target": sweep.target,
                "pose_id": int(sweep.pose_id),
                "frames": int(sweep.n_frames),
            }
        )
        self._write_manifest()
        return self.directory / rel

    def add_touches(self, touches: Sequence[Touch]) -> None:
        """List touches (vertex, index, joint angles in radians, flange pose in mm)."""
        for t in touches:
            self._touches.append(
                {
                    "vertex": t.vertex,
                    "index": int(t.index),
                    "q_rad": [float(v) for v in t.q],
                    "T_base_ee_mm": _matrix_mm(t.T_base_ee),
                }
            )
        self._write_manifest()

    def discard_if_empty(self) -> None:
        """Remove the dataset again if it holds no sweep and no touch yet and this writer
        created its directory (an acquisition refused before its first sweep leaves
        nothing behind)."""
        if self._sweeps or self._touches or not self._created:
            return
        (self.directory / MANIFEST).unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            (self.directory / "sweeps").rmdir()
            self.directory.rmdir()

    def finish(self) -> None:
        """Mark the acquisition complete."""
        self._complete = True
        self._write_manifest()

    def _write_manifest(self) -> None:
        doc = {
            **self._head,
            "complete": self._complete,
            "sweeps": self._sweeps,
            "touches": self._touches,
        }
        yaml = self._yaml

        class Dumper(yaml.SafeDumper):
            """Lists of numbers in flow style: a 4 × 4 matrix reads as four rows."""

        def flow_flat(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
            flat = all(not isinstance(v, (list, dict)) for v in data)
            return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)

        def exact(dumper: yaml.SafeDumper, data: Decimal) -> yaml.Node:
            text = format(data, "f")
            return dumper.represent_scalar(
                "tag:yaml.org,2002:float", text if "." in text else text + ".0"
            )

        Dumper.add_representer(list, flow_flat)
        Dumper.add_representer(Decimal, exact)
        path = self.directory / MANIFEST
        with atomic_file(path) as tmp:
            text = yaml.dump(doc, Dumper=Dumper, sort_keys=False, width=120, allow_unicode=True)
            tmp.write_text(text, encoding="utf-8")


def _load_manifest(path: Path) -> dict[str, Any]:
    import yaml

    class Loader(yaml.SafeLoader):
        """The safe loader, with decimal numbers kept as written (mm → m exactly)."""

    def decimal(loader: yaml.SafeLoader, node: yaml.Node) -> Decimal | float:
        try:
            return Decimal(loader.construct_scalar(node))
        except ArithmeticError:  # .inf, .nan
            return yaml.SafeLoader.construct_yaml_float(loader, node)

    Loader.add_constructor("tag:yaml.org,2002:float", decimal)
    try:
        doc = yaml.load(path.read_text(encoding="utf-8"), Loader=Loader)
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror})") from None
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a uscal dataset manifest (format: {FORMAT})")
    if doc.get("version") != VERSION:
        raise DatasetError(
            f"{path}: dataset version {doc.get('version')!r}; this reader reads {VERSION}"
        )
    return doc


def _get(path: Path, doc: Mapping[str, Any], key: str, kind: type | tuple[type, ...]) -> Any:
    if key not in doc:
        raise DatasetError(f"{path}: missing {key}")
    value = doc[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
        raise DatasetError(f"{path}: {key} = {value!r} has the wrong type")
    return value


def _matrix(path: Path, key: str, value: Any) -> Array:
    try:
        T = np.array(value, dtype=float)
        T[:3, 3] = [metres_of(v) for v in np.array(value, dtype=object)[:3, 3]]
    except (TypeError, ValueError, IndexError, ArithmeticError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise DatasetError(f"{path}: {key} must be a 4 × 4 matrix of numbers")
    return checked_rigid(path, key, T)


def _vector(path: Path, key: str, value: Any, n: int, raw: bool = False) -> Any:
    """``n`` finite numbers as floats (``raw``: as read, after the same checks)."""
    try:
        v = np.array(value, dtype=float)
    except (TypeError, ValueError, ArithmeticError):
        v = np.zeros(0)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise DatasetError(f"{path}: {key} must be {n} numbers")
    return list(value) if raw else v


def _info(path: Path, acq: Any) -> AcquisitionInfo:
    if not isinstance(acq, dict):
        raise DatasetError(f"{path}: acquisition must be a mapping")
    landmarks = _get(path, acq, "landmarks_mm", dict)
    tip = acq.get("stylus_tip_cad_mm")
    nwire = wire = cone_tip = None
    if acq.get("phantom") is not None:
        doc = acq["phantom"]
        if isinstance(doc, dict) and doc.get("kind") == "wire":
            wire = WirePhantom.from_yaml(path, doc)
        elif isinstance(doc, dict) and doc.get("kind") == "cone_tip":
            cone_tip = ConeTipPhantom.from_yaml(path, doc)
        else:
            nwire = NWirePhantom.from_yaml(path, doc)
        radius = float("nan")  # no sphere
    else:
        radius = float(_get(path, acq, "sphere_radius_mm", _NUMBER))
        if not 0 < radius < 1000:
            raise DatasetError(f"{path}: acquisition.sphere_radius_mm = {radius} is out of range")
    depth = acq.get("target_depth_mm")
    if depth is not None:
        depth = float(_get(path, acq, "target_depth_mm", _NUMBER))
        if not 0 < depth <= 200:
            raise DatasetError(
                f"{path}: acquisition.target_depth_mm = {depth} is out of range (0, 200]"
            )
    coarse = acq.get("T_ee_us_coarse_mm")
    return AcquisitionInfo(
        T_ee_us_coarse=(
            None if coarse is None else _matrix(path, "acquisition.T_ee_us_coarse_mm", coarse)
        ),
        landmarks={
            str(k): np.array(
                [
                    metres_of(x)
                    for x in _vector(path, f"acquisition.landmarks_mm.{k}", v, 3, raw=True)
                ]
            )
            for k, v in landmarks.items()
        },
        sphere_radius_mm=radius,
        temperature_c=float(_get(path, acq, "temperature_c", _NUMBER)),
        assumed_speed_m_s=float(_get(path, acq, "assumed_speed_m_s", _NUMBER)),
        sound_speed_correction=bool(acq.get("sound_speed_correction", True)),
        medium=str(acq.get("medium", "water")),
        stylus_tip_cad_mm=(
            None
            if tip is None
            else tuple(float(v) for v in _vector(path, "acquisition.stylus_tip_cad_mm", tip, 3))
        ),
        source=str(acq.get("source", "hardware")),
        target_depth_mm=depth,
        extra=dict(acq.get("extra") or {}),
        nwire=nwire,
        wire=wire,
        cone_tip=cone_tip,
    )


def dataset_kind(directory: str | os.PathLike[str]) -> str:
    """``"nwire"`` for a dataset of an N-wire phantom, ``"wire"`` of a single wire,
    ``"cone_tip"`` of a cone's tip, ``"spheres"`` otherwise (from the manifest alone; a
    directory that is not a dataset reads as spheres and :func:`read_dataset` says what
    is wrong)."""
    manifest = Path(directory) / MANIFEST
    if not manifest.is_file():
        return "spheres"
    acq = _load_manifest(manifest).get("acquisition")
    phantom = acq.get("phantom") if isinstance(acq, dict) else None
    if phantom is None:
        return "spheres"
    kind = phantom.get("kind") if isinstance(phantom, dict) else None
    return kind if kind in ("wire", "cone_tip") else "nwire"


def read_dataset(
    directory: str | os.PathLike[str], *, allow_incomplete: bool = False
) -> tuple[Dataset, AcquisitionInfo]:
    """Read a dataset directory: its sweeps (in acquisition order), touches and settings.

    An unfinished acquisition (``complete: false``) is an error unless
    ``allow_incomplete``. Sweep files are checked against the manifest (target, pose id,
    frame count) and against each other (same image size and spacing).
    """
    directory = Path(directory)
    manifest = directory / MANIFEST
    if not directory.is_dir():
        raise DatasetError(f"{directory}: no such dataset directory")
    if not manifest.is_file():
        raise DatasetError(f"{directory}: not a dataset (no {MANIFEST})")
    doc = _load_manifest(manifest)
    if not doc.get("complete") and not allow_incomplete:
        raise DatasetError(
            f"{manifest}: the acquisition is not complete (resume it with `uscal acquire --resume`)"
        )
    info = _info(manifest, doc.get("acquisition"))
    entries = doc.get("sweeps") or []
    if not isinstance(entries, list) or not entries:
        raise DatasetError(f"{manifest}: lists no sweeps")
    sweeps: list[Sweep] = []
    root = directory.resolve()
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise DatasetError(f"{manifest}: sweeps[{i}] must be a mapping")
        rel = str(_get(manifest, e, "file", str))
        p = (directory / rel).resolve()
        # Files of the dataset only: a shared manifest must not point elsewhere.
        if root not in p.parents:
            raise DatasetError(f"{manifest}: sweeps[{i}].file {rel!r} lies outside the dataset")
        sweep, _ = read_sequence(p)
        target = str(_get(manifest, e, "target", str))
        pose_id = int(_get(manifest, e, "pose_id", int))
        frames = int(_get(manifest, e, "frames", int))
        if (sweep.target, sweep.pose_id, sweep.n_frames) != (target, pose_id, frames):
            raise DatasetError(
                f"{p}: holds {sweep.target} pose {sweep.pose_id} with {sweep.n_frames} "
                f"frames; the manifest lists {target} pose {pose_id} with {frames}"
            )
        if sweeps and (
            sweep.images.shape[1:] != sweeps[0].images.shape[1:]
            or not np.allclose(sweep.spacing, sweeps[0].spacing, rtol=1e-9)
        ):
            raise DatasetError(f"{p}: image size or spacing differs from {entries[0]['file']}")
        sweeps.append(sweep)
    touches = []
    for i, t in enumerate(doc.get("touches") or []):
        if not isinstance(t, dict):
            raise DatasetError(f"{manifest}: touches[{i}] must be a mapping")
        touches.append(
            Touch(
                str(_get(manifest, t, "vertex", str)),
                int(_get(manifest, t, "index", int)),
                _vector(manifest, f"touches[{i}].q_rad", t.get("q_rad"), 6),
                _matrix(manifest, f"touches[{i}].T_base_ee_mm", t.get("T_base_ee_mm")),
            )
        )
    if touches and info.stylus_tip_cad_mm is None:
        raise DatasetError(f"{manifest}: touches need acquisition.stylus_tip_cad_mm")
    meta = {"image": doc.get("image") or {}, "complete": bool(doc.get("complete"))}
    name = str(doc.get("name") or directory.name)
    return Dataset(name, tuple(sweeps), meta, tuple(touches)), info
