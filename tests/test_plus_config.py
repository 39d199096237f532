"""PLUS's own calibration files read as PLUS means them (calib/files/plus_config.py): fCal 2.0's
device set configuration (its N-wire phantom and coordinate definitions) and fCal's
results file (ImageToProbe, reprojection errors, per-frame segmentation), from the real
files in ../shared/data/plus; broken files are one line."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import DatasetError
from calib.files.plus_config import read_plus_config, read_plus_results

from .plus_data import (
    FCAL_CONFIG,
    FCAL_RESULTS,
    PLUS_DATA,
    needs_plus_data,
)

CONFIG, RESULTS = FCAL_CONFIG, FCAL_RESULTS
MM = 1e-3


@needs_plus_data
def test_the_fcal_2_phantom_is_three_n_patterns_in_metres():
    c = read_plus_config(CONFIG)
    assert c.sequence_file == "fCal_Test_Calibration_3NWires_fCal2.0.igs.mha"
    names = [[w.name for w in p.wires] for p in c.patterns]
    assert names == [
        ["7:G1_g1", "8:L1_h1", "9:M1_m1"],
        ["4:G3_g3", "5:H3_l3", "6:M3_m3"],
        ["1:H5_h5", "2:L5_i5", "3:M5_m5"],
    ]
    diagonal = c.patterns[0].wires[1]
    np.testing.assert_allclose(diagonal.front, np.array([55.0, 0.0, 20.0]) * MM)
    np.testing.assert_allclose(diagonal.back, np.array([35.0, 40.0, 20.0]) * MM)
    # Phantom → Reference as the file gives it (mm → m), and its inverse the other way.
    T = c.transform("Phantom", "Reference")
    np.testing.assert_allclose(T[:3, 3], np.array([15.6642, -25.3628, -40.7799]) * MM)
    np.testing.assert_allclose(c.transform("Reference", "Phantom") @ T, np.eye(4), atol=1e-12)
    with pytest.raises(DatasetError, match="no coordinate definition ProbeToReference"):
        c.transform("Probe", "Reference")


@needs_plus_data
def test_fcal_s_answer_and_its_segmentation_are_read():
    r = read_plus_results(RESULTS)
    # ImageToProbe with the pixel spacing in it: 0.074–0.080 mm per pixel.
    scale = np.linalg.norm(r.image_to_probe[:3, :3], axis=0) / MM
    np.testing.assert_allclose(scale[:2], [0.0803, 0.0745], atol=2e-4)
    origin = np.array([11.2137, 48.4162, -0.398993]) * MM
    np.testing.assert_allclose(r.image_to_probe[:3, 3], origin)
    assert r.reprojection_3d_mm == {
        "calibration_mean_mm": 0.479116,
        "calibration_sd_mm": 0.22656,
        "validation_mean_mm": 0.539932,
        "validation_sd_mm": 0.223536,
    }
    assert len(r.reprojection_2d_px) == 9
    assert (len(r.calibration), sum(f.ok for f in r.calibration)) == (190, 184)
    assert (len(r.validation), sum(f.ok for f in r.validation)) == (103, 103)
    first = r.calibration[0]
    assert first.index == 0 and len(first.points) == 9
    assert first.points["7:G1_g1"] == (592.1, 195.808)


@pytest.mark.parametrize(
    "body, message",
    [
        ("not xml at all <", "not XML"),
        ("<Other/>", "root element is <Other>"),
        ("<PlusConfiguration/>", "no PhantomDefinition/Geometry"),
        (
            "<PlusConfiguration><PhantomDefinition><Geometry><Pattern Type='NWire'>"
            "<Wire Name='a' EndPointFront='0 0 0' EndPointBack='0 40 0'/>"
            "<Wire Name='b' EndPointFront='20 0 0' EndPointBack='5 40 0'/>"
            "</Pattern></Geometry></PhantomDefinition></PlusConfiguration>",
            "has 2 wires",
        ),
        (
            "<PlusConfiguration><PhantomDefinition><Geometry><Pattern Type='NWire'>"
            "<Wire Name='a' EndPointFront='0 0 0' EndPointBack='0 40 0'/>"
            "<Wire Name='b' EndPointFront='20 0 0' EndPointBack='5 40 0'/>"
            "<Wire Name='c' EndPointFront='25 0 0' EndPointBack='35 40 0'/>"
            "</Pattern></Geometry></PhantomDefinition></PlusConfiguration>",
            "is not an N: its outer wires are 14.0° apart",
        ),
        (
            "<PlusConfiguration><PhantomDefinition><Geometry><Pattern Type='NWire'>"
            "<Wire Name='a' EndPointFront='0 0 0' EndPointBack='0 40 0'/>"
            "<Wire Name='b' EndPointFront='20 0 0' EndPointBack='5 40 3'/>"
            "<Wire Name='c' EndPointFront='25 0 0' EndPointBack='25 40 0'/>"
            "</Pattern></Geometry></PhantomDefinition></PlusConfiguration>",
            "3.00 mm out of one plane",
        ),
    ],
)
def test_a_configuration_that_is_not_one_or_defines_no_n_is_one_line(tmp_path, body, message):
    path = tmp_path / "config.xml"
    path.write_text(body)
    with pytest.raises(DatasetError, match=message) as err:
        read_plus_config(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


@needs_plus_data
@pytest.mark.slow  # detection on 190 real frames (≈ 5 s)
def test_n_wires_are_found_where_plus_finds_them_without_a_threshold():
    """uscal's threshold-free N-wire detection (calib/localize/nwire.py) on fCal 2.0's 190 real
    calibration frames, against PLUS's own segmentation of them: found in at least as
    many frames (PLUS: 184), and within a pixel of PLUS's points in the median."""
    from calib.files.metafile import read_metafile
    from calib.localize.nwire import detect_nwires

    config, results = read_plus_config(CONFIG), read_plus_results(RESULTS)
    frames = read_metafile(PLUS_DATA / config.sequence_file).images
    spacing = config.pixel_spacing_mm()
    np.testing.assert_allclose(spacing, (0.0796446, 0.0744856))
    found = [detect_nwires(f, config.patterns, spacing) for f in frames]
    plus = results.calibration
    assert sum(d.ok for d in found) >= sum(p.ok for p in plus) == 184
    distances = []
    for ours, theirs in zip(found, plus, strict=True):
        if ours.ok and theirs.ok:
            for name, p in ours.points.items():
                distances.append(np.hypot(*np.subtract(p, theirs.points[name])))
    assert len(distances) == 9 * 184
    assert np.median(distances) <= 1.0
    # A frame with nothing in it: rejected, with the reason.
    blank = detect_nwires(np.zeros_like(frames[0]), config.patterns, spacing)
    assert not blank.ok and "9 wires to find" in blank.reason


def test_the_middle_wire_point_follows_from_the_ratio_of_the_dots():
    """A plane cutting fCal 2.0's first N obliquely: the dots' ratio along their line
    gives back the diagonal's true crossing point (the N-wire construction)."""
    from calib.files.plus_config import NWire, NWirePattern
    from calib.localize.nwire import middle_wire_point

    wires = (
        NWire("a", np.array([30.0, 0, 20]) * MM, np.array([30.0, 40, 20]) * MM),
        NWire("m", np.array([55.0, 0, 20]) * MM, np.array([35.0, 40, 20]) * MM),
        NWire("b", np.array([60.0, 0, 20]) * MM, np.array([60.0, 40, 20]) * MM),
    )
    pattern = NWirePattern(wires)
    # The cut: the line y = 10 + 0.4 (x − 30) in the N's plane.
    pa, pb = np.array([30.0, 10.0]), np.array([60.0, 22.0])
    # The diagonal x = 55 − y / 2 meets it where x = 55 − (10 + 0.4 (x − 30)) / 2.
    x = 56.0 / 1.2
    truth = np.array([x, 10 + 0.4 * (x - 30), 20.0]) * MM
    pm = np.array([x, 10 + 0.4 * (x - 30)])
    # Seen in an image: the plane's own 2-D coordinates, scaled and turned.
    R = np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]) * 13.0
    p = middle_wire_point(pattern, R @ pa, R @ pm, R @ pb)
    np.testing.assert_allclose(p, truth, atol=1e-12)
