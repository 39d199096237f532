"""Sequence metafiles written the way PLUS writes a tracked-probe recording.

Follows what PLUS's ``vtkPlusMetaImageSequenceIO`` writes (checked against the real files
in ``../shared/data/plus``): ``ObjectType`` and ``NDims`` first, the other header fields in
alphabetical order, ``DimSize`` and ``Kinds`` padded with spaces, one zlib stream over
all frames (``CompressedDataSize``), ``ElementSpacing = 1 1 1`` (PLUS keeps the pixel
spacing in ``ImageToProbe``), the per-frame fields in alphabetical order with
``ImageStatus`` last, transforms as 16 numbers at precision 16, each followed by a
space, in millimetres. Used by the tests only: uscal's own writer is
:func:`calib.files.metafile.write_sequence`.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

ORIENTATION_FLIPS = {"MFA": (False, False), "UFA": (True, False), "MNA": (False, True),
                     "UNA": (True, True), "MF": (False, False), "UN": (True, True)}  # fmt: skip


def _matrix_text(T_m: np.ndarray) -> str:
    T = np.array(T_m, dtype=float)
    T[:3, 3] *= 1e3
    return "".join(f"{v:.16g} " for v in T.ravel())


def write_plus_sequence(
    path: Path,
    images: np.ndarray,
    transforms: Mapping[str, Sequence[np.ndarray]],
    statuses: Mapping[str, Sequence[str]],
    timestamps: Sequence[float],
    orientation: str = "MFA",
    image_status: Sequence[str] | None = None,
) -> None:
    """``images`` (n, H, W) as seen in MF; stored as ``orientation`` says. ``transforms``
    name (``ProbeToTracker``) → n (4, 4) metres; ``statuses`` name → n statuses."""
    flip_cols, flip_rows = ORIENTATION_FLIPS[orientation]
    stored = images[:, :, ::-1] if flip_cols else images
    stored = stored[:, ::-1, :] if flip_rows else stored
    n, H, W = images.shape
    status = image_status or ["OK"] * n
    data = zlib.compress(np.ascontiguousarray(stored, dtype=np.uint8).tobytes())
    head = {
        "AnatomicalOrientation": "RAI",
        "BinaryData": "True",
        "BinaryDataByteOrderMSB": "False",
        "CenterOfRotation": "0 0 0",
        "CompressedData": "True",
        "CompressedDataSize": f"{len(data)}".ljust(20),
        "DimSize": f"{W} {H} ".ljust(40) + f"{n}",
        "ElementNumberOfChannels": "1",
        "ElementSpacing": "1 1 1",
        "ElementType": "MET_UCHAR",
        "Kinds": "domain domain ".ljust(40) + "list",
        "Offset": "0 0 0",
        "TransformMatrix": "1 0 0 0 1 0 0 0 1",
        "UltrasoundImageOrientation": orientation,
        "UltrasoundImageType": "BRIGHTNESS",
    }
    lines = ["ObjectType = Image", "NDims = 3", *(f"{k} = {v}" for k, v in sorted(head.items()))]
    for j in range(n):
        fields = {"FrameNumber": str(j), "Timestamp": f"{timestamps[j]:.6f}"}
        fields["UnfilteredTimestamp"] = fields["Timestamp"]
        for name, Ts in transforms.items():
            fields[f"{name}Transform"] = _matrix_text(Ts[j])
            fields[f"{name}TransformStatus"] = statuses[name][j]
        p = f"Seq_Frame{j:04d}_"
        lines += [f"{p}{k} = {v}" for k, v in sorted(fields.items())]
        lines.append(f"{p}ImageStatus = {status[j]}")
    lines.append("ElementDataFile = LOCAL")
    path.write_bytes(("\n".join(lines) + "\n").encode("ascii") + data)
