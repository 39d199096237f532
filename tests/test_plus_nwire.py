"""PLUS's fCal 2.0 calibration run end to end from PLUS's real files with uscal's own
wire detection, as a PLUS user runs it: ``uscal import plus SEQ --config CONFIG``, then
``uscal calibrate``, then ``uscal validate`` with uscal's answer and with PLUS's. The
figures are held to PLUS's own (its results file): the 3-D reprojection error no worse
than its 0.48 mm, the transform within 1 mm / 1° of its ImageToProbe over the image.
Bad input is one line and leaves nothing behind."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from calib.files.dataset import read_dataset
from calib.files.plus_config import read_plus_results

from .plus_data import (
    FCAL_CONFIG,
    FCAL_RESULTS,
    FCAL_SEQUENCE,
    NWIRE_CROPPED,
    needs_plus_data,
)
from .test_cli import uscal, uscal_here

SEQUENCE, CONFIG, RESULTS, CROPPED = FCAL_SEQUENCE, FCAL_CONFIG, FCAL_RESULTS, NWIRE_CROPPED
pytestmark = needs_plus_data


@pytest.fixture(scope="module")
def fcal(tmp_path_factory):
    """The import and the calibration, once: (dataset, output directory, stdout)."""
    base = tmp_path_factory.mktemp("fcal")
    r = uscal("import", "plus", str(SEQUENCE), "--config", str(CONFIG), "--out", str(base / "d"))
    assert r.returncode == 0, r.stderr
    r = uscal("calibrate", str(base / "d"), "--out", str(base / "cal"))
    assert r.returncode == 0, r.stderr
    return base / "d", base / "cal", r.stdout


def _over_image_mm(A: np.ndarray, B: np.ndarray, w: int = 820, h: int = 616) -> float:
    corners = np.array([[0, 0, 0, 1], [w - 1, 0, 0, 1], [0, h - 1, 0, 1], [w - 1, h - 1, 0, 1]])
    return float(np.linalg.norm((corners @ A.T - corners @ B.T)[:, :3], axis=1).max())


def _rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    RA, RB = (M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0) for M in (A, B))
    return float(np.degrees(np.arccos(np.clip((np.trace(RA.T @ RB) - 1) / 2, -1, 1))))


@pytest.mark.slow  # the import and calibration of 190 frames (≈ 15 s, once)
def test_the_import_keeps_the_phantom_and_its_tracked_pose(fcal):
    dataset, info = read_dataset(fcal[0])
    assert info.nwire is not None and len(info.nwire.patterns) == 3
    assert info.extra["pose_transform"] == "ProbeToReferenceTransform"
    # Phantom → Reference from the configuration, in metres; spacing from its
    # TransducerOriginPixel → TransducerOrigin (the file holds PLUS's default 1 × 1).
    np.testing.assert_allclose(
        info.nwire.T_base_phantom[:3, 3], np.array([15.6642, -25.3628, -40.7799]) * 1e-3
    )
    (sequence,) = dataset.sweeps
    assert sequence.images.shape == (190, 616, 820)
    assert np.isfinite(sequence.T_base_ee).all()


@pytest.mark.slow  # the import and calibration of 190 frames (≈ 15 s, once)
def test_fcal_2_calibrates_as_well_as_plus_with_uscal_s_own_detection(fcal):
    _, out, stdout = fcal
    m = json.loads((out / "metrics.json").read_text())
    plus = read_plus_results(RESULTS)
    assert m["detection"]["frames_found"] >= sum(f.ok for f in plus.calibration)  # 184
    nw = m["calibration"]["nwire"]
    error = nw["reprojection_3d_mm"]
    assert error["plus_mean"] <= plus.reprojection_3d_mm["calibration_mean_mm"] + 1e-3
    ours = np.array(nw["plus_ImageToProbe_mm"])
    theirs = plus.image_to_probe.copy()
    theirs[:3, :] *= 1e3
    assert _over_image_mm(ours, theirs) < 1.0
    assert _rotation_deg(ours, theirs) < 1.0
    assert nw["converged"] and nw["verdict"]["status"] != "rejected"
    assert "3-D reprojection error" in stdout and "verdict:" in stdout


@pytest.mark.slow  # the import and calibration of 190 frames (≈ 15 s, once)
def test_calibration_yaml_carries_the_plus_coordinate_definition(fcal):
    doc = yaml.safe_load((fcal[1] / "calibration.yaml").read_text())
    element = ET.fromstring(doc["plus_coordinate_definitions"])
    assert (element.tag, element.get("From"), element.get("To")) == ("Transform", "Image", "Probe")
    matrix = np.array([float(v) for v in element.get("Matrix").split()]).reshape(4, 4)
    np.testing.assert_allclose(matrix, doc["plus_ImageToProbe"]["matrix"], rtol=1e-8, atol=1e-8)
    assert float(element.get("Error")) == pytest.approx(doc["reprojection_3d_mm"]["mean"], abs=1e-3)
    assert doc["verdict"]["status"] in ("accepted", "suspect")
    assert (fcal[1] / "report.html").is_file() and (fcal[1] / "figures").is_dir()


@pytest.mark.slow  # two detections of 190 frames (≈ 15 s)
def test_validate_measures_any_calibration_with_the_same_detection(fcal, capsys, tmp_path):
    dataset, out, _ = fcal
    last = re.compile(r"^reprojection_mm=(\d+\.\d+) sd_mm=(\d+\.\d+)$")
    r = uscal_here(
        capsys, "validate", str(dataset), "--calibration", str(out / "calibration.yaml"),
        "--json", str(tmp_path / "v.json"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    ours = last.match(r.stdout.strip().splitlines()[-1])
    assert ours is not None
    m = json.loads((out / "metrics.json").read_text())["calibration"]["nwire"]
    assert float(ours.group(1)) == pytest.approx(m["reprojection_3d_mm"]["plus_mean"], abs=1e-3)
    assert json.loads((tmp_path / "v.json").read_text())["frames_found"] >= 184
    # PLUS's own answer through uscal's detection: its stated 0.48 ± 0.23 mm.
    r = uscal_here(capsys, "validate", str(dataset), "--calibration", str(RESULTS))
    assert r.returncode == 0, r.stderr
    theirs = last.match(r.stdout.strip().splitlines()[-1])
    assert theirs is not None and float(theirs.group(1)) == pytest.approx(0.48, abs=0.02)


@pytest.mark.parametrize(
    "config, message",
    [
        (RESULTS, "not a PLUS configuration"),
        (SEQUENCE, "not a PLUS configuration (not XML"),
    ],
)
def test_a_config_that_is_not_one_is_one_line_and_writes_nothing(capsys, tmp_path, config, message):
    r = uscal_here(
        capsys, "import", "plus", str(SEQUENCE), "--config", str(config), "--out",
        str(tmp_path / "d"),
    )  # fmt: skip
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and message in r.stderr
    assert not list(tmp_path.iterdir())


def test_a_sequence_where_no_frame_shows_the_wires_is_one_line(capsys, tmp_path):
    """PLUS's cropped freehand frames (200 × 150 px of another phantom) imported with the
    fCal 2.0 configuration: the import reads them, the calibration says why it cannot."""
    r = uscal_here(
        capsys, "import", "plus", str(CROPPED), "--config", str(CONFIG),
        "--out", str(tmp_path / "d"), "--spacing-mm", "0.2", "0.2",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = uscal_here(capsys, "calibrate", str(tmp_path / "d"), "--out", str(tmp_path / "c"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "frames show every wire pattern" in r.stderr
    assert not (tmp_path / "c").exists()
    r = uscal_here(capsys, "validate", str(tmp_path / "d"), "--calibration", str(RESULTS))
    assert r.returncode == 2 and "no frame shows every wire pattern" in r.stderr


def test_a_missing_link_of_the_pose_chain_is_one_line(capsys, tmp_path):
    r = uscal_here(
        capsys, "import", "plus", str(SEQUENCE), "--config", str(CONFIG), "--out",
        str(tmp_path / "d"), "--pose-transform", "ProbeToPhantom",
    )  # fmt: skip
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "nor a chain of them from Probe to Phantom" in r.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.slow  # one more calibration of 190 frames
def test_a_requirement_the_bound_misses_exits_3(fcal, capsys, tmp_path):
    """The recording's bound (≈ 2 mm over the image) against a 0.5 mm requirement: the
    verdict rejects it and the command exits 3, writing its files all the same."""
    r = uscal_here(
        capsys, "calibrate", str(fcal[0]), "--out", str(tmp_path / "c"),
        "--require-image-mm", "0.5",
    )  # fmt: skip
    assert r.returncode == 3, r.stderr
    assert "the N-wire calibration is rejected" in r.stdout
    doc = yaml.safe_load((tmp_path / "c" / "calibration.yaml").read_text())
    assert doc["verdict"]["status"] == "rejected"
    assert any("above the requirement" in reason for reason in doc["verdict"]["reasons"])
