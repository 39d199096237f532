"""Dataset files (calib.files.dataset): PLUS sequence metafiles + manifest, round trip,
what a damaged or hostile file gives, resume; and `uscal calibrate` on the twin's
dataset against `uscal run`'s result and the truth."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

import numpy as np
import pytest

from calib import se3
from calib.errors import DatasetError
from calib.files.dataset import AcquisitionInfo, DatasetWriter, read_dataset
from calib.files.metafile import read_sequence, write_sequence
from calib.records import Sweep, Touch

from .conftest import QUICK
from .rrd import Recording
from .test_cli import uscal


def _sweep(rng: np.random.Generator, target="sphere_1", pose_id=3, n=5, H=40, W=30) -> Sweep:
    images = rng.integers(0, 256, (n, H, W), dtype=np.uint8)
    T = np.array(
        [
            se3.make(se3.matrix_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 0.3, 3))
            for _ in range(n)
        ]
    )
    q = rng.uniform(-np.pi, np.pi, (n, 6))
    return Sweep(target, pose_id, images, (0.25e-3, 0.125e-3), q, T)


def _info() -> AcquisitionInfo:
    return AcquisitionInfo(
        T_ee_us_coarse=se3.make(np.eye(3), [0.0, 0.0, 0.15]),
        landmarks={f"sphere_{i}": np.array([0.02 * i, 0.0, 0.01]) for i in (1, 2, 3)},
        sphere_radius_mm=5.0,
        temperature_c=21.5,
        assumed_speed_m_s=1540.0,
        stylus_tip_cad_mm=(0.0, 0.0, 120.0),
        target_depth_mm=25.0,
    )


def test_sequence_round_trip_is_exact_and_plus_shaped(tmp_path, rng):
    sweep = _sweep(rng)
    path = tmp_path / "s.mha"
    t = np.arange(5) * 0.04 + 1000.0
    write_sequence(path, sweep, t)
    back, t_back = read_sequence(path)
    assert back.target == "sphere_1" and back.pose_id == 3
    assert np.array_equal(back.images, sweep.images)
    assert np.array_equal(back.q, sweep.q)  # repr round-trips floats exactly
    assert np.array_equal(back.T_base_ee, sweep.T_base_ee)  # mm text, bit-exact metres
    assert back.spacing == sweep.spacing
    assert np.array_equal(t_back, t)
    header = path.read_bytes().split(b"ElementDataFile = LOCAL\n")[0].decode()
    fields = dict(line.split(" = ", 1) for line in header.splitlines())
    assert fields["DimSize"] == "30 40 5" and fields["ElementType"] == "MET_UCHAR"
    assert fields["ElementSpacing"].split()[:2] == ["0.25", "0.125"]
    assert fields["UltrasoundImageOrientation"] == "MFA"
    # The PLUS transform field: row-major, millimetres, EE → base.
    T0 = np.array(fields["Seq_Frame0000_EEToBaseTransform"].split(), float).reshape(4, 4)
    assert np.allclose(T0[:3, 3], sweep.T_base_ee[0][:3, 3] * 1e3)
    assert fields["Seq_Frame0004_EEToBaseTransformStatus"] == "OK"
    # The image data is exactly the frames after the header, nothing more.
    assert path.stat().st_size == len(header) + len("ElementDataFile = LOCAL\n") + 5 * 40 * 30


def test_compressed_data_as_plus_writes_it(tmp_path, rng):
    sweep = _sweep(rng)
    raw = tmp_path / "raw.mha"
    write_sequence(raw, sweep, np.zeros(5))
    head, data = raw.read_bytes().split(b"ElementDataFile = LOCAL\n")
    packed = zlib.compress(data)
    head = head.replace(b"CompressedData = False", b"CompressedData = True")
    head += f"CompressedDataSize = {len(packed)}\n".encode()
    comp = tmp_path / "comp.mha"
    comp.write_bytes(head + b"ElementDataFile = LOCAL\n" + packed)
    back, _ = read_sequence(comp)
    assert np.array_equal(back.images, sweep.images)
    comp.write_bytes(head + b"ElementDataFile = LOCAL\n" + packed[:20] + b"\x00" * 50)
    with pytest.raises(DatasetError, match=r"comp\.mha"):
        read_sequence(comp)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: b[: len(b) - 100], "truncated"),
        (lambda b: b + b"x", "longer than announced"),
        (lambda b: b[:200], "truncated|missing|ends before"),
        (lambda b: b"\x89PNG\r\n\x1a\n" + b"\x00" * 64, "not 'key = value'|not text"),
        (lambda b: b.replace(b"MET_UCHAR", b"MET_FLOAT"), "ElementType"),
        (lambda b: b.replace(b"File = LOCAL", b"File = /etc/passwd"), "beside the header"),
        (lambda b: b.replace(b"DimSize = 30 40 5", b"DimSize = 30 40 -5"), "DimSize"),
        (lambda b: b.replace(b"Status = OK", b"Status = INVALID", 1), "INVALID"),
        (lambda b: b.replace(b"0002_JointAnglesRad = ", b"0002_JointAnglesRad = 1 "), "Joint"),
    ],
)  # fmt: skip
def test_damaged_sequence_gives_one_dataset_error_naming_the_file(tmp_path, rng, damage, message):
    path = tmp_path / "s.mha"
    write_sequence(path, _sweep(rng), np.zeros(5))
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(DatasetError, match=message) as err:
        read_sequence(path)
    assert "s.mha" in str(err.value)


def test_a_non_rigid_flange_pose_is_refused(tmp_path, rng):
    sweep = _sweep(rng)
    bad = sweep.T_base_ee.copy()
    bad[1, :3, :3] *= 1.01  # a scaled "rotation"
    path = tmp_path / "s.mha"
    write_sequence(
        path, Sweep("sphere_1", 0, sweep.images, sweep.spacing, sweep.q, bad), np.zeros(5)
    )
    with pytest.raises(DatasetError, match="Frame0001_EEToBaseTransform: not a rigid transform"):
        read_sequence(path)


def _write_dataset(directory: Path, rng, sweeps=4, finish=True) -> list[Sweep]:
    writer = DatasetWriter(directory, "lab", _info(), {"width_px": 30})
    out = [_sweep(rng, f"sphere_{1 + i % 2}", i) for i in range(sweeps)]
    for s in out:
        writer.add_sweep(s)
    writer.add_touches([Touch("vertex_1", 0, np.arange(6.0), se3.make(np.eye(3), [0.1, 0.2, 0.3]))])
    if finish:
        writer.finish()
    return out


def test_dataset_round_trip(tmp_path, rng):
    sweeps = _write_dataset(tmp_path / "ds", rng)
    dataset, info = read_dataset(tmp_path / "ds")
    assert [(s.target, s.pose_id) for s in dataset.sweeps] == [
        (s.target, s.pose_id) for s in sweeps
    ]
    assert all(
        np.array_equal(a.images, b.images) for a, b in zip(dataset.sweeps, sweeps, strict=True)
    )
    assert dataset.targets() == ["sphere_1", "sphere_2"]
    assert info.temperature_c == 21.5 and info.stylus_tip_cad_mm == (0.0, 0.0, 120.0)
    assert info.target_depth_mm == 25.0
    assert np.array_equal(info.T_ee_us_coarse, _info().T_ee_us_coarse)
    assert np.array_equal(info.landmarks["sphere_3"], _info().landmarks["sphere_3"])
    (touch,) = dataset.touches
    assert touch.vertex == "vertex_1" and np.allclose(touch.T_base_ee[:3, 3], [0.1, 0.2, 0.3])


def test_interrupted_dataset_resumes_and_is_refused_until_complete(tmp_path, rng):
    directory = tmp_path / "ds"
    _write_dataset(directory, rng, sweeps=3, finish=False)
    with pytest.raises(DatasetError, match="not complete"):
        read_dataset(directory)
    partial, _ = read_dataset(directory, allow_incomplete=True)
    assert len(partial.sweeps) == 3
    with pytest.raises(DatasetError, match="already holds a dataset"):
        DatasetWriter(directory, "lab", _info())
    writer = DatasetWriter(directory, "lab", _info(), resume=True)
    assert writer.has("sphere_1", 0) and writer.has("sphere_2", 1) and not writer.has("sphere_1", 3)
    writer.add_sweep(_sweep(rng, "sphere_2", 3))
    writer.finish()
    dataset, _ = read_dataset(directory)
    assert [s.pose_id for s in dataset.sweeps] == [0, 1, 2, 3]
    assert not list(directory.rglob(".*tmp*"))  # no temporary files left behind
    with pytest.raises(DatasetError, match="already complete"):
        DatasetWriter(directory, "lab", _info(), resume=True)


def test_hostile_or_broken_manifests_are_refused(tmp_path, rng):
    directory = tmp_path / "ds"
    _write_dataset(directory, rng)
    manifest = directory / "dataset.yaml"
    text = manifest.read_text()
    cases = {
        # The safe loader builds no Python objects.
        "!!python/object/apply:os.system ['echo hacked']": "not valid YAML|not a uscal dataset",
        text.replace("file: sweeps/", "file: ../../", 1): "outside the dataset",
        text.replace("frames: 5", "frames: 6", 1): "manifest lists",
        text.replace("version: 1", "version: 9"): "version 9",
        text.replace("sphere_radius_mm: 5.0", "sphere_radius_mm: -1"): "sphere_radius_mm",
        "format: [unclosed": "not valid YAML",
    }
    for content, message in cases.items():
        manifest.write_text(content)
        with pytest.raises(DatasetError, match=message):
            read_dataset(directory)
    manifest.write_text(text)
    (directory / "sweeps" / "sphere_2_pose01.mha").unlink()
    with pytest.raises(DatasetError, match=r"sphere_2_pose01\.mha: cannot open"):
        read_dataset(directory)


# ------------------------------------------------------------------ uscal calibrate


@pytest.mark.slow  # ten seconds or more on this machine
def test_calibrate_reproduces_the_runs_calibration_from_the_saved_dataset(quick_run, tmp_path):
    out, _, m, _ = quick_run
    dataset = out.parent / "dataset"
    dest = tmp_path / "cal"
    r = uscal(
        "calibrate", str(dataset), "--markers", "1", "--out", str(dest), "--rrd-frames", "42",
        "--settings", str(QUICK),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    got = json.loads((dest / "metrics.json").read_text())
    assert got["dataset"]["source"] == "twin" and got["dataset"]["n_sweeps"] == 45
    T_run = np.array(m["calibration"]["single"]["T_ee_us"])
    T_off = np.array(got["calibration"]["single"]["T_ee_us"])
    # The same frames, and poses whose millimetre text reads back to the same doubles:
    # the same estimate, to the last digit metrics.json keeps.
    assert np.array_equal(T_run, T_off)
    assert "true_error" not in got["calibration"]["single"]  # no truth offline
    assert (dest / "calibration.yaml").exists() and (dest / "report.html").exists()
    assert "Precision" in (dest / "report.md").read_text()
    # The recording: the arm at the reported joint angles, the frames and the sections
    # found; no truth and no scene (the phantom's placement is unknown offline).
    rec = Recording(dest / "recording.rrd")
    assert rec.rows("/run/bmode/image") == 42
    assert rec.rows("/run/bmode/section/detected") == 42
    assert not any("true" in e for e in rec.entities)
    assert not any(e.startswith("/run/world/scene/") for e in rec.entities)
    loss = rec.values("/run/calibration/single/loss_mm2", "Scalars:scalars", index="iteration")
    history = got["calibration"]["single"]["history"]
    assert np.allclose([v[0] for v in loss], [h["cost_mm2"] for h in history])


@pytest.mark.slow
def test_calibrate_errors_are_one_line(tmp_path):
    r = uscal("calibrate", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "no such dataset" in r.stderr
    (tmp_path / "empty").mkdir()
    r = uscal("calibrate", str(tmp_path / "empty"))
    assert r.returncode == 2 and "no dataset.yaml" in r.stderr
    assert not (tmp_path / "empty-calibration").exists()  # nothing half-written
