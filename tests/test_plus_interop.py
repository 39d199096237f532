"""PLUS and 3D Slicer interop: the real PLUS files read (or refused with one line), every
orientation PLUS writes turned to MF, an independent reader (ITK through SimpleITK)
reading uscal's files back exactly, and a tracked-probe recording written as PLUS would
write it from the twin, imported and calibrated against the truth."""

from __future__ import annotations

import json
import zlib
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest

from bench.acquire_sim import make_twin
from bench.config.scenario import load_scenario
from bench.truth import transform_difference
from calib import se3
from calib.errors import DatasetError
from calib.files.dataset import read_dataset
from calib.files.metafile import read_metafile, read_sequence, write_sequence
from calib.files.plus_import import plus_frames
from calib.records import Sweep

from .conftest import QUICK
from .plus_data import (
    FCAL_SEQUENCE,
    NWIRE_CROPPED,
    PLUS_DATA,
    needs_plus_data,
)
from .plus_writer import ORIENTATION_FLIPS, write_plus_sequence
from .test_cli import uscal, uscal_here

sitk = pytest.importorskip("SimpleITK")

NWIRE = NWIRE_CROPPED
SYNTHETIC = PLUS_DATA / "SyntheticVideoBuffer20.igs.mha"
TRACKING = PLUS_DATA / "SlidingProbeTrackingData.igs.mha"
FCAL = FCAL_SEQUENCE


def _itk_frames(path: Path) -> np.ndarray:
    return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))


def _itk_fields(path: Path) -> dict[str, str]:
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    reader.ReadImageInformation()
    return {k: reader.GetMetaData(k) for k in reader.GetMetaDataKeys()}


# ------------------------------------------------------------- the real PLUS files


@needs_plus_data
@pytest.mark.parametrize(
    "path, transform, shape, spacing",
    [
        (NWIRE, "ProbeToTrackerTransform", (20, 150, 200), None),
        (SYNTHETIC, "ToolToTracker", (20, 240, 320), (0.3, 0.3)),
    ],
)
def test_real_plus_files_read_as_itk_reads_them(path, transform, shape, spacing):
    frames = plus_frames(path, transform)
    assert frames.images.shape == shape and frames.spacing_mm == spacing
    # Both files are MFA: no flip; the pixels are ITK's, frame by frame.
    assert np.array_equal(frames.images, _itk_frames(path))
    fields = _itk_fields(path)
    name = transform if transform.endswith("Transform") else transform + "Transform"
    for j in (0, len(frames.images) - 1):
        text = fields[f"Seq_Frame{j:04d}_{name}"].split()
        T = np.array([float(v) for v in text]).reshape(4, 4)
        T[:3, 3] *= 1e-3
        assert np.allclose(frames.T_base_probe[j], T, rtol=0, atol=1e-12)


@needs_plus_data
def test_the_real_freehand_file_is_refused_as_a_sweep_then_imported_when_allowed(capsys, tmp_path):
    args = [
        "import", "plus", str(NWIRE), "--pose-transform", "ProbeToTracker",
        "--out", str(tmp_path / "d"), "--radius-mm", "5", "--no-speed-correction",
    ]  # fmt: skip
    r = uscal_here(capsys, *args)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "--spacing-mm" in r.stderr and not (tmp_path / "d").exists()
    r = uscal_here(capsys, *args, "--spacing-mm", "0.2", "0.2")
    assert r.returncode == 2 and "turns by 2.35°" in r.stderr and not (tmp_path / "d").exists()
    assert not list(tmp_path.iterdir())  # nothing half-written
    r = uscal_here(capsys, *args, "--spacing-mm", "0.2", "0.2", "--max-turn-deg", "3")
    assert r.returncode == 0, r.stderr
    dataset, info = read_dataset(tmp_path / "d")
    (sweep,) = dataset.sweeps
    assert sweep.images.shape == (20, 150, 200) and np.isnan(sweep.q).all()
    assert sweep.spacing == (0.2e-3, 0.2e-3) and info.T_ee_us_coarse is None
    assert not info.sound_speed_correction and info.source == "plus"


@needs_plus_data
def test_tracking_only_file_and_unknown_transform_are_one_line(capsys, tmp_path):
    r = uscal_here(
        capsys, "import", "plus", str(TRACKING), "--pose-transform", "ProbeToTracker",
        "--out", str(tmp_path / "d"), "--radius-mm", "5", "--temperature-c", "20",
    )  # fmt: skip
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "holds no images" in r.stderr and "tracking-only" in r.stderr
    r = uscal_here(
        capsys, "import", "plus", str(SYNTHETIC), "--pose-transform", "ProbeToTracker",
        "--out", str(tmp_path / "d"), "--radius-mm", "5", "--temperature-c", "20",
    )  # fmt: skip
    assert r.returncode == 2 and "records ToolToTrackerTransform" in r.stderr
    r = uscal_here(
        capsys, "import", "plus", str(SYNTHETIC), "--pose-transform", "ToolToTracker",
        "--out", str(tmp_path / "d"), "--radius-mm", "5", "--temperature-c", "20",
    )  # fmt: skip
    # The synthetic buffer's tool never moves: not a sweep.
    assert r.returncode == 2 and "moves 0.00 mm" in r.stderr
    r = uscal_here(
        capsys, "import", "plus", str(SYNTHETIC), "--pose-transform", "ToolToTracker",
        "--out", str(tmp_path / "d"), "--radius-mm", "5", "--temperature-c", "200",
    )  # fmt: skip
    assert r.returncode == 2 and "0 to 60" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "d").exists()


# ---------------------------------------- PLUS files as PLUS writes them (issue 37)


def _split(path: Path, folder: Path, name: str, inflate: bool) -> Path:
    """The real ``.mha`` as a ``.mhd`` header with its data file beside it (zlib as the
    file has it: ``.zraw``; ``inflate``: raw bytes, ``.raw``), as PLUS writes a sequence
    with ``.mhd``."""
    blob = path.read_bytes()
    end = blob.index(b"ElementDataFile = LOCAL") + len(b"ElementDataFile = LOCAL\n")
    header, data = blob[:end].decode("latin-1"), blob[end:]
    data_name = f"{name}.{'raw' if inflate else 'zraw'}"
    if inflate:
        data = zlib.decompress(data)
        header = header.replace("CompressedData = True", "CompressedData = False")
    header = header.replace("ElementDataFile = LOCAL", f"ElementDataFile = {data_name}")
    (folder / data_name).write_bytes(data)
    mhd = folder / f"{name}.mhd"
    mhd.write_text(header, encoding="latin-1")
    return mhd


@needs_plus_data
@pytest.mark.parametrize("inflate", [False, True])
def test_a_sequence_with_its_frames_in_a_data_file_beside_it(tmp_path, inflate):
    """``.mhd`` + ``.zraw`` (or ``.raw``): the same frames as ITK reads from that pair
    and as the real ``.mha`` holds; a data file that is not there is one line."""
    mhd = _split(NWIRE, tmp_path, "nwire", inflate)
    frames = read_metafile(mhd).images
    assert np.array_equal(frames, _itk_frames(mhd))
    assert np.array_equal(frames, read_metafile(NWIRE).images)
    (tmp_path / f"nwire.{'raw' if inflate else 'zraw'}").unlink()
    with pytest.raises(DatasetError, match=r"ElementDataFile .* cannot be opened"):
        read_metafile(mhd)


def test_a_single_image_reads_as_one_frame(tmp_path, rng):
    """``NDims = 2`` (one B-mode image, as ITK and PLUS write a single frame)."""
    image = rng.integers(0, 256, (40, 30), dtype=np.uint8)
    path = tmp_path / "one.mha"
    sitk.WriteImage(sitk.GetImageFromArray(image), str(path))
    assert "NDims = 2" in path.read_bytes()[:400].decode("latin-1")
    meta = read_metafile(path)
    assert meta.images.shape == (1, 40, 30) and np.array_equal(meta.images[0], image)
    assert np.isnan(meta.timestamp(0))


@needs_plus_data
def test_a_transform_the_file_does_not_record_is_composed_from_the_chain():
    """fCal 2.0's calibration sweep records ProbeToTracker and ReferenceToTracker per
    frame; ProbeToReference is ReferenceToTracker⁻¹ · ProbeToTracker, as PLUS's transform
    repository composes it (the numbers read by ITK); a frame where a link is not OK is
    skipped as PLUS skips it; no chain is one line naming what the file records."""
    composed = plus_frames(FCAL, "ProbeToReference")
    fields = _itk_fields(FCAL)

    def matrix(j: int, name: str) -> np.ndarray:
        T = np.array([float(v) for v in fields[f"Seq_Frame{j:04d}_{name}"].split()])
        T = T.reshape(4, 4)
        T[:3, 3] *= 1e-3
        return T

    n = len(composed.images)
    assert n == len(plus_frames(FCAL, "ProbeToTracker").images) > 100
    for j in (0, n // 2, n - 1):
        expected = np.linalg.inv(matrix(j, "ReferenceToTrackerTransform")) @ matrix(
            j, "ProbeToTrackerTransform"
        )
        # To the six digits the file prints (its rotations are orthonormal to 1e-6).
        assert np.allclose(composed.T_base_probe[j], expected, atol=2e-5)
    with pytest.raises(DatasetError, match="nor a chain of them from Probe to Phantom"):
        plus_frames(FCAL, "ProbeToPhantom")


@needs_plus_data
def test_a_sequence_without_timestamps_imports_in_frame_order(tmp_path):
    """Timestamps removed from a real file: its frames are numbered in order instead of
    refused ("Seq_Frame0000_Timestamp must be 1 finite numbers")."""
    blob = NWIRE.read_bytes()
    end = blob.index(b"ElementDataFile = LOCAL")
    lines = blob[:end].decode("latin-1").splitlines(keepends=True)
    header = "".join(line for line in lines if "_Timestamp =" not in line)
    path = tmp_path / "untimed.mha"
    path.write_bytes(header.encode("latin-1") + blob[end:])
    frames = plus_frames(path, "ProbeToTracker")
    assert np.array_equal(frames.timestamps, np.arange(len(frames.images)))
    assert np.array_equal(frames.images, plus_frames(NWIRE, "ProbeToTracker").images)


# -------------------------------------------------------------- orientations


@pytest.mark.parametrize("orientation", sorted(ORIENTATION_FLIPS))
def test_every_b_mode_orientation_reads_as_mf(tmp_path, rng, orientation):
    n, H, W = 6, 12, 9
    images = rng.integers(0, 256, (n, H, W), dtype=np.uint8)
    T = [se3.make(np.eye(3), [0.0, 0.0, 1e-3 * j]) for j in range(n)]
    path = tmp_path / "s.mha"
    write_plus_sequence(
        path, images, {"ProbeToTracker": T}, {"ProbeToTracker": ["OK"] * n},
        np.arange(n) * 0.1, orientation,
    )  # fmt: skip
    assert np.array_equal(read_metafile(path).images, images)
    # ITK reads the pixels as stored: reversed as the letters say.
    stored = _itk_frames(path)
    flip_cols, flip_rows = ORIENTATION_FLIPS[orientation]
    assert np.array_equal(stored[:, :: -1 if flip_rows else 1, :: -1 if flip_cols else 1], images)


@pytest.mark.parametrize("orientation", ["FM", "AMF", "XX", "MFX"])
def test_transposed_or_unknown_orientations_are_refused(tmp_path, rng, orientation):
    sweep = Sweep(
        "sphere_1", 0, rng.integers(0, 256, (5, 8, 6), dtype=np.uint8), (1e-4, 1e-4),
        np.zeros((5, 6)), np.tile(np.eye(4), (5, 1, 1)),
    )  # fmt: skip
    path = tmp_path / "s.mha"
    write_sequence(path, sweep, np.zeros(5))
    text = path.read_bytes().replace(b"Orientation = MFA", f"Orientation = {orientation}".encode())
    path.write_bytes(text)
    with pytest.raises(DatasetError, match="UltrasoundImageOrientation") as err:
        read_sequence(path)
    assert "s.mha" in str(err.value)


# ------------------------------------------------- uscal's files, read by ITK


def test_itk_reads_uscal_sequence_files_back_exactly(tmp_path, rng):
    n, H, W = 7, 40, 30
    T = np.array([se3.make(se3.matrix_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 0.3, 3))
                  for _ in range(n)])  # fmt: skip
    sweep = Sweep(
        "sphere_2", 4, rng.integers(0, 256, (n, H, W), dtype=np.uint8), (0.25e-3, 0.125e-3),
        rng.uniform(-3, 3, (n, 6)), T,
    )  # fmt: skip
    path = tmp_path / "s.mha"
    write_sequence(path, sweep, np.arange(n) * 0.04)
    assert_itk_reads_back(path, sweep)


def assert_itk_reads_back(path: Path, sweep: Sweep) -> None:
    """ITK's pixels, spacing and every frame's transform and joint angles are exactly
    what uscal holds."""
    image = sitk.ReadImage(str(path))
    assert np.array_equal(sitk.GetArrayFromImage(image), sweep.images)
    sx, sy, _ = image.GetSpacing()
    assert (sx * 1e-3, sy * 1e-3) == pytest.approx(sweep.spacing, rel=1e-15)
    fields = _itk_fields(path)
    assert fields["UltrasoundImageOrientation"] == "MFA"
    assert fields["Kinds"].split() == ["domain", "domain", "list"]
    for j in range(sweep.n_frames):
        text = fields[f"Seq_Frame{j:04d}_EEToBaseTransform"].split()
        T = np.array([float(Decimal(v).scaleb(-3 if k % 4 == 3 and k < 12 else 0))
                      for k, v in enumerate(text)]).reshape(4, 4)  # fmt: skip
        assert np.array_equal(T, sweep.T_base_ee[j])
        assert fields[f"Seq_Frame{j:04d}_EEToBaseTransformStatus"] == "OK"
        if np.all(np.isfinite(sweep.q[j])):
            q = [float(v) for v in fields[f"Seq_Frame{j:04d}_JointAnglesRad"].split()]
            assert np.array_equal(q, sweep.q[j])


@pytest.mark.slow
def test_itk_reads_every_file_of_a_twin_dataset_back_exactly(quick_run):
    out, *_ = quick_run
    dataset, _ = read_dataset(out.parent / "dataset")
    files = sorted((out.parent / "dataset" / "sweeps").glob("*.mha"))
    assert len(files) == len(dataset.sweeps) == 45
    by_pose = {s.pose_id: s for s in dataset.sweeps}
    for path in files:
        sweep, _ = read_sequence(path)
        assert_itk_reads_back(path, by_pose[sweep.pose_id])


# ------------------------------------------- a tracked probe, end to end, with truth


@pytest.mark.slow
def test_a_tracked_probe_recording_imports_and_calibrates_to_the_truth(quick_run, tmp_path):
    """The twin's sweeps of sphere 1, written as PLUS writes a tracked probe: the pose is
    ProbeToTrackerTransform (a tracker far from the robot base), the pixel spacing not
    in the file, orientations mixed, some frames with an INVALID status. Imported and
    calibrated, T_probe_image is the twin's T_ee_us (the probe's body is the flange)."""
    out, _, m, _ = quick_run
    dataset, _ = read_dataset(out.parent / "dataset")
    T_tracker_base = se3.make(se3.matrix_from_rotvec([0.4, -2.1, 0.9]), [-0.19, -0.098, -1.949])
    orientations = ["MFA", "UNA", "UFA", "MNA"]
    files, invalid = [], 0
    for k, sweep in enumerate(dataset.sweeps):
        n = sweep.n_frames
        probe = [T_tracker_base @ T for T in sweep.T_base_ee]
        status = ["OK"] * n
        image_status = ["OK"] * n
        if k % 5 == 0:  # the tracker lost the probe for a frame
            status[3] = "INVALID"
            probe[3] = np.eye(4)
            invalid += 1
        if k % 7 == 0:  # the grabber dropped one
            image_status[n - 2] = "INVALID"
            invalid += 1
        stylus = [se3.make(np.eye(3), [1e-4, 2e-4, -6e-5])] * n
        path = tmp_path / f"Recording{k:02d}.igs.mha"
        write_plus_sequence(
            path, sweep.images,
            {"ProbeToTracker": probe, "StylusToTracker": stylus},
            {"ProbeToTracker": status, "StylusToTracker": ["INVALID"] * n},
            1000.0 + 0.05 * np.arange(n), orientations[k % 4], image_status,
        )  # fmt: skip
        files.append(str(path))
    sx, sy = (format(Decimal(repr(s)).scaleb(3), "f") for s in dataset.sweeps[0].spacing)
    settings = load_scenario(QUICK, ["protocol.spheres=[1]"])
    r = uscal(
        "import", "plus", *files, "--pose-transform", "ProbeToTrackerTransform",
        "--target", "sphere_1", "--out", str(tmp_path / "tracked"), "--spacing-mm", sx, sy,
        "--radius-mm", repr(settings.phantom.sphere_radius_mm),
        "--temperature-c", repr(settings.medium.temperature_c),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert f"skipped {invalid} frames" in " ".join(r.stdout.split())
    r = uscal(
        "calibrate", str(tmp_path / "tracked"), "--markers", "1", "--out", str(tmp_path / "cal"),
        "--settings", str(QUICK), "--no-rrd",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    got = json.loads((tmp_path / "cal" / "metrics.json").read_text())
    assert got["dataset"]["n_sweeps"] == 45
    T_probe_image = np.array(got["calibration"]["single"]["T_ee_us"])
    truth = make_twin(settings).truth.T_ee_us
    err = transform_difference(T_probe_image, truth)
    # As good as the twin's own run on the same frames (0.25° / 0.13 mm on quick.yaml),
    # not the same digits: a few frames are gone and the poses passed through a tracker.
    run_err = m["calibration"]["single"]["true_error"]
    assert err["rotation_deg"] < max(0.5, 1.5 * run_err["rotation_deg"])
    assert err["translation_mm"] < max(0.5, 1.5 * run_err["translation_mm"])
    # ... and within the bounds it reports.
    bound = got["calibration"]["single"]["bound95"]
    assert err["rotation_deg"] < bound["rotation_deg"]
    assert err["translation_mm"] < bound["translation_mm"]
