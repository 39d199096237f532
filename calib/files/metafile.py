"""PLUS sequence metafiles (``.mha``): one sweep's frames and, per frame, its flange pose,
status, timestamp and joint angles, as PLUS and 3D Slicer read and write them.

:func:`write_sequence` writes one sweep (atomically); :func:`read_metafile` is the one
reader of a metafile's header and frames (B-mode orientations MF/MN/UF/UN, zlib), under
:func:`read_sequence` (a sweep of a uscal dataset, :mod:`calib.files.dataset`) and the
PLUS import (:mod:`calib.files.plus_import`). Reading never executes anything: a text header
of ``key = value`` lines and raw bytes; every check that fails raises one
:class:`DatasetError` naming the file and what is wrong.

Lengths are written in millimetres exactly as decimal text (:func:`mm_decimal`), so a
dataset written from the twin reads back as the very doubles the twin used.
"""

from __future__ import annotations

import contextlib
import os
import re
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..errors import DatasetError, TransformError
from ..records import Sweep

__all__ = [
    "Metafile",
    "atomic_file",
    "checked_rigid",
    "metres_of",
    "mm_decimal",
    "mm_text",
    "read_metafile",
    "read_sequence",
    "write_sequence",
]

Array = NDArray[np.float64]

# A metafile header is a few kB per frame; anything far beyond is not a metafile.
_MAX_HEADER_BYTES = 64 * 2**20
_MAX_FRAMES = 100_000
_MAX_SIDE_PX = 16_384
# A flange pose's rotation part must be a rotation to this tolerance.
_ROTATION_TOL = 1e-5


def mm_decimal(x: float) -> Decimal:
    """Metres → millimetres, exactly in decimal: the shortest text that reads back as
    ``x`` (``repr``), its point moved three places. :func:`metres_of` moves it back, so a
    dataset written from the twin holds the very doubles the twin's own run used (last-bit
    differences would otherwise turn into µm through the localizer's discrete choices)."""
    return Decimal(repr(float(x))).scaleb(3)


def mm_text(x: float) -> str:
    text = format(mm_decimal(x), "f")
    return text if "." in text else text + ".0"


def metres_of(value: str | Decimal | int | float) -> float:
    """Millimetres (text or number as read) → metres, the inverse of :func:`mm_decimal`."""
    d = value if isinstance(value, Decimal) else Decimal(str(value))
    return float(d.scaleb(-3))


def _pose_text(T: Array) -> str:
    """A flange pose as PLUS writes transforms: 16 numbers, row-major, millimetres."""
    return " ".join(
        mm_text(T[i, j]) if j == 3 and i < 3 else repr(float(T[i, j]))
        for i in range(4)
        for j in range(4)
    )


def _fmt(values: Any) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


@contextlib.contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """A temporary sibling of ``path`` that replaces it when the block succeeds."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_sequence(path: str | os.PathLike[str], sweep: Sweep, timestamps: Array) -> None:
    """Write one sweep as a PLUS sequence metafile (atomically).

    Parameters
    ----------
    sweep : its frames, spacing, reported joint angles and flange poses
    timestamps : (n,) float, seconds (acquisition clock)
    """
    path = Path(path)
    images = np.ascontiguousarray(sweep.images, dtype=np.uint8)
    n, H, W = images.shape
    sx, sy = (mm_text(v) for v in sweep.spacing)
    known_q = np.all(np.isfinite(np.asarray(sweep.q, dtype=float)), axis=1)
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CenterOfRotation = 0 0 0",
        "CompressedData = False",
        f"DimSize = {W} {H} {n}",
        "ElementNumberOfChannels = 1",
        f"ElementSpacing = {sx} {sy} 1",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "UltrasoundImageOrientation = MFA",
        "UltrasoundImageType = BRIGHTNESS",
        f"uscal_Target = {sweep.target}",
        f"uscal_PoseId = {int(sweep.pose_id)}",
    ]
    for j in range(n):
        p = f"Seq_Frame{j:04d}_"
        lines += [
            f"{p}EEToBaseTransform = {_pose_text(np.asarray(sweep.T_base_ee[j], float))}",
            f"{p}EEToBaseTransformStatus = OK",
            *([f"{p}JointAnglesRad = {_fmt(sweep.q[j])}"] if known_q[j] else []),
            f"{p}Timestamp = {float(timestamps[j])!r}",
            f"{p}ImageStatus = OK",
        ]
    lines.append("ElementDataFile = LOCAL")
    header = ("\n".join(lines) + "\n").encode("ascii")
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        f.write(images.tobytes())
        f.flush()
        os.fsync(f.fileno())


_KEY = re.compile(rb"^([A-Za-z0-9_]+) = (.*)$")


def _read_header(path: Path, f) -> tuple[dict[str, str], int]:
    """The header's ``key = value`` pairs up to ``ElementDataFile``, and where the data
    starts."""
    fields: dict[str, str] = {}
    read = 0
    while True:
        line = f.readline(65536)
        read += len(line)
        if not line:
            raise DatasetError(f"{path}: header ends before ElementDataFile (truncated?)")
        if read > _MAX_HEADER_BYTES:
            raise DatasetError(f"{path}: header longer than {_MAX_HEADER_BYTES} bytes")
        m = _KEY.match(line.rstrip(b"\r\n"))
        if m is None:
            if line.strip() == b"":
                continue
            raise DatasetError(
                f"{path}: header line {len(fields) + 1} is not 'key = value': {line[:60]!r}"
            )
        try:
            key, value = m.group(1).decode("ascii"), m.group(2).decode("utf-8").strip()
        except UnicodeDecodeError as e:
            raise DatasetError(f"{path}: header is not text ({e.reason})") from None
        fields[key] = value
        if key == "ElementDataFile":
            return fields, read


def _numbers(path: Path, key: str, text: str | None, n: int) -> Array:
    if text is None:
        raise DatasetError(f"{path}: missing header field {key}")
    try:
        values = np.array([float(v) for v in text.split()])
    except ValueError:
        raise DatasetError(f"{path}: {key} = {text[:80]!r} is not {n} numbers") from None
    if len(values) != n or not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: {key} must be {n} finite numbers, got {text[:80]!r}")
    return values


def checked_rigid(path: Path, key: str, T: Array) -> Array:
    """``T`` if it is a rigid transform, else one line naming the file and the field."""
    try:
        return se3.check(T, key, tol=_ROTATION_TOL)
    except TransformError as e:
        raise DatasetError(f"{path}: {e}") from None


def _flange_pose(path: Path, key: str, text: str | None) -> Array:
    T = _numbers(path, key, text, 16).reshape(4, 4)
    assert text is not None  # checked by _numbers
    T[:3, 3] = [metres_of(v) for v in np.array(text.split()).reshape(4, 4)[:3, 3]]
    return checked_rigid(path, key, T)


@dataclass(frozen=True)
class Metafile:
    """A sequence metafile as read: its header fields (frame fields included, as
    ``Seq_FrameNNNN_<name>``) and its frames turned to ``MF`` (columns toward the marked
    side, rows away from the transducer), ``(n, H, W)`` uint8."""

    path: Path
    fields: dict[str, str]
    images: NDArray[np.uint8]

    def frame_field(self, j: int, name: str, *, default: str | None = None) -> str | None:
        return self.fields.get(f"Seq_Frame{j:04d}_{name}", default)

    def transform(self, j: int, name: str) -> Array:
        """Frame ``j``'s transform ``name`` (PLUS: row-major, mm), metres; checked rigid."""
        key = f"Seq_Frame{j:04d}_{name}"
        return _flange_pose(self.path, key, self.fields.get(key))

    def timestamp(self, j: int) -> float:
        """Frame ``j``'s timestamp (s; NaN when not recorded, as in a sequence PLUS
        wrote without timestamps, or a single image)."""
        key = f"Seq_Frame{j:04d}_Timestamp"
        if key not in self.fields:
            return float("nan")
        return float(_numbers(self.path, key, self.fields[key], 1)[0])

    def spacing_mm(self) -> tuple[float, float]:
        """The frames' pixel spacing (columns, rows) as the header gives it, mm."""
        v = _numbers(self.path, "ElementSpacing", self.fields.get("ElementSpacing", "1 1 1"), 3)
        if not np.all(v[:2] > 0):
            raise DatasetError(f"{self.path}: ElementSpacing must be positive")
        return float(v[0]), float(v[1])

    def frame_names(self) -> list[str]:
        """The names of the per-frame fields of frame 0 (``ProbeToTrackerTransform`` …)."""
        p = "Seq_Frame0000_"
        return [k[len(p) :] for k in self.fields if k.startswith(p)]


def _mirror_to_mf(path: Path, orientation: str) -> tuple[bool, bool]:
    """Which axes of a frame to reverse to turn ``orientation`` into ``MF``: (columns,
    rows).

    PLUS writes two letters or, for a sequence, three (``MFA`` is ``MF``): the first says
    where the image's x axis points (``M`` the transducer's marked side, ``U`` the other),
    the second its y axis (``F`` away from the transducer, ``N`` toward it), the third
    the slice axis within a frame (``A``/``D``), which a stack of 2-D frames does not
    have: the frames are time, never reversed (as PLUS reads them)."""
    o = orientation.upper()
    if len(o) in (2, 3) and o[0] in "MU" and o[1] in "FN" and o[2:] in ("", "A", "D"):
        return o[0] == "U", o[1] == "N"
    raise DatasetError(
        f"{path}: UltrasoundImageOrientation = {orientation!r}; this reader takes B-mode "
        "frames with columns lateral and rows axial: MF, MN, UF, UN, with or without the "
        "sequence's third letter (A or D); transposed (RF) orientations are not supported"
    )


@contextlib.contextmanager
def _element_data(path: Path, header, name: str | None) -> Iterator:
    """Where the image bytes are: after the header (``LOCAL``, a ``.mha``) or in the file
    ``ElementDataFile`` names beside it (a ``.mhd`` header with its ``.raw`` or, zlib
    compressed, ``.zraw``), a plain name in the header's folder."""
    if name == "LOCAL":
        yield header
        return
    if not name or name in ("LIST",) or name.split()[0] in ("LIST",) or "%" in name:
        raise DatasetError(
            f"{path}: ElementDataFile = {name!r}; this reader takes the frames in the same "
            "file ('LOCAL') or in one data file beside it (e.g. 'frames.raw', 'frames.zraw')"
        )
    data_path = path.parent / name
    if Path(name).is_absolute() or data_path.resolve().parent != path.parent.resolve():
        raise DatasetError(
            f"{path}: ElementDataFile = {name!r} is not a file beside the header; "
            "move the data file next to it"
        )
    try:
        f = open(data_path, "rb")  # noqa: SIM115 - closed below, errors mapped first
    except OSError as e:
        raise DatasetError(
            f"{path}: its ElementDataFile {data_path} cannot be opened ({e.strerror})"
        ) from None
    with f:
        yield f


def read_metafile(path: str | os.PathLike[str]) -> Metafile:
    """Read a sequence metafile as PLUS and uscal write it: a stack of single-channel
    ``MET_UCHAR`` frames (``NDims = 3``) or one frame (``NDims = 2``), raw or
    zlib-compressed, after the header (``.mha``) or in the data file beside it that
    ``ElementDataFile`` names (a ``.mhd`` header), in any B-mode orientation.

    Raises
    ------
    DatasetError
        Naming the file: not a metafile, no images (a tracking-only recording), an
        unsupported element type, channel count or orientation, or fewer (or more) image
        bytes than the header announces.
    """
    path = Path(path)
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below, errors mapped first
    except OSError as e:
        raise DatasetError(f"{path}: cannot open ({e.strerror})") from None
    with f:
        fields, _ = _read_header(path, f)
        if fields.get("ObjectType") != "Image" or fields.get("NDims") not in ("2", "3"):
            raise DatasetError(
                f"{path}: ObjectType = {fields.get('ObjectType')!r}, NDims = "
                f"{fields.get('NDims')!r}; this reader needs an 'Image' of NDims '3' (a stack "
                "of 2-D frames) or '2' (one frame)"
            )
        ndims = int(fields["NDims"])
        dims = _numbers(path, "DimSize", fields.get("DimSize"), ndims)
        if ndims == 2:
            dims = np.append(dims, 1.0)  # one frame
        if fields.get("ElementType") == "MET_OTHER" or np.any(dims[:2] == 0):
            raise DatasetError(
                f"{path}: holds no images (ElementType = {fields.get('ElementType')}, "
                f"DimSize = {' '.join(fields.get('DimSize', '').split())}): a tracking-only "
                "recording; calibration needs the B-mode frames"
            )
        if fields.get("ElementType") != "MET_UCHAR":
            raise DatasetError(
                f"{path}: ElementType = {fields.get('ElementType')!r}; this reader takes "
                "8-bit grey frames (MET_UCHAR)"
            )
        if fields.get("ElementNumberOfChannels", "1") != "1":
            raise DatasetError(f"{path}: only single-channel (grey) images are supported")
        flip_columns, flip_rows = _mirror_to_mf(
            path, fields.get("UltrasoundImageOrientation", "MF")
        )
        W, H, n = (int(v) for v in dims)
        if not (
            np.all(dims == np.round(dims))
            and 0 < W <= _MAX_SIDE_PX
            and 0 < H <= _MAX_SIDE_PX
            and 0 < n <= _MAX_FRAMES
        ):
            raise DatasetError(f"{path}: DimSize = {fields['DimSize']!r} is not a frame stack")
        size = W * H * n
        compressed = fields.get("CompressedData", "False").lower() == "true"
        with _element_data(path, f, fields.get("ElementDataFile")) as data_file:
            data = _decompress(path, data_file, size) if compressed else data_file.read(size + 1)
        if len(data) != size:
            raise DatasetError(
                f"{path}: {len(data)} image bytes, the header announces {size} "
                f"({n} frames of {H} × {W}); the file is "
                + ("truncated" if len(data) < size else "longer than announced")
            )
    images = np.frombuffer(data, dtype=np.uint8).reshape(n, H, W)
    if flip_columns:
        images = images[:, :, ::-1]
    if flip_rows:
        images = images[:, ::-1, :]
    return Metafile(path, fields, np.ascontiguousarray(images))


def read_sequence(path: str | os.PathLike[str]) -> tuple[Sweep, Array]:
    """Read a sweep written by :func:`write_sequence` (or by PLUS, with the same frame
    fields); returns the sweep and its timestamps (s). Joint angles are optional (a
    tracked probe has none: NaN).

    Raises
    ------
    DatasetError
        Naming the file: see :func:`read_metafile`; also a missing or malformed frame
        field, or a frame whose transform status is not OK.
    """
    meta = read_metafile(path)
    path, fields, images = meta.path, meta.fields, meta.images
    n = len(images)
    spacing = _numbers(path, "ElementSpacing", fields.get("ElementSpacing"), 3)
    if not np.all(spacing[:2] > 0):
        raise DatasetError(f"{path}: ElementSpacing must be positive")
    T, q, t = np.empty((n, 4, 4)), np.full((n, 6), np.nan), np.empty(n)
    for j in range(n):
        p = f"Seq_Frame{j:04d}_"
        status = fields.get(f"{p}EEToBaseTransformStatus", "OK")
        if status != "OK":
            raise DatasetError(f"{path}: frame {j}: EEToBaseTransformStatus = {status}")
        T[j] = _flange_pose(path, f"{p}EEToBaseTransform", fields.get(f"{p}EEToBaseTransform"))
        if f"{p}JointAnglesRad" in fields:
            q[j] = _numbers(path, f"{p}JointAnglesRad", fields[f"{p}JointAnglesRad"], 6)
        t[j] = _numbers(path, f"{p}Timestamp", fields.get(f"{p}Timestamp", "nan"), 1)[0]
    target = fields.get("uscal_Target", path.stem)
    try:
        pose_id = int(fields.get("uscal_PoseId", "-1"))
    except ValueError:
        raise DatasetError(f"{path}: uscal_PoseId = {fields['uscal_PoseId']!r}") from None
    sx_text, sy_text = fields["ElementSpacing"].split()[:2]
    spacing_m = (metres_of(sx_text), metres_of(sy_text))
    return Sweep(target, pose_id, images, spacing_m, q, T), t


def _decompress(path: Path, f, size: int) -> bytes:
    """zlib-compressed image data (PLUS's ``CompressedData = True``), read in pieces so a
    forged header cannot make it inflate beyond the announced size."""
    d = zlib.decompressobj()
    out = bytearray()
    try:
        while len(out) <= size:
            chunk = f.read(1 << 20)
            if not chunk:
                break
            out += d.decompress(chunk, size + 1 - len(out))
            if d.unconsumed_tail:
                break
        out += d.flush()[: size + 1 - len(out)]
    except zlib.error as e:
        raise DatasetError(f"{path}: compressed image data is corrupt ({e})") from None
    return bytes(out)
