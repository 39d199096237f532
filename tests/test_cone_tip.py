"""The cone's tip as a calibration target (calib/localize/cone_tip.py and the point
target of calib/calibration/targets.py): the twin's printed cone swept over its apex
(scenarios/cone_tip.yaml), the apex of every sweep against the twin's truth, the
calibration against its ground truth with its bounds covering it, every error source
off as the sanity case, and the dataset a run saves calibrated again by `uscal calibrate`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.acquire_sim import acquisition_info, make_imager, make_twin, simulate_acquisition
from bench.config.scenario import load_scenario
from calib import se3
from calib.calibration.nwire import dataset_spacing_m
from calib.localize.cone_tip import locate_cone_tip

from .test_cli import uscal, uscal_here

pytestmark = pytest.mark.slow  # twin acquisitions of 945 frames
ROOT = Path(__file__).resolve().parents[1]
CONE = ROOT / "scenarios" / "cone_tip.yaml"


def test_each_sweep_s_apex_lies_where_the_truth_puts_it():
    """Every sweep's apex found, within 0.6 mm of the truth in each direction of the
    image (laterally and in depth a few tenths; along the sweep, where frames are 0.5
    mm apart, a little more)."""
    scenario = load_scenario(str(CONE), [])
    twin = make_twin(scenario)
    acq = simulate_acquisition(scenario, twin, make_imager(scenario, twin))
    info = acquisition_info(scenario, twin, acq.T_ee_us_coarse)
    spacing = dataset_spacing_m(acq.dataset, info)
    X, apex = twin.truth.T_ee_us, twin.truth.landmarks_base["apex"]
    errors = []
    for s in acq.dataset.sweeps:
        true_poses = acq.T_base_ee_true[(s.target, s.pose_id)]
        normal = (s.T_base_ee[s.reference_index] @ X)[:3, 2]
        e = (s.T_base_ee[:, :3, 3] - s.T_base_ee[s.reference_index, :3, 3]) @ normal
        tip = locate_cone_tip(s.images, e, spacing, s.images.shape[2])
        assert tip.ok, tip.reason
        k = int(np.argmin(np.abs(e - tip.elevation_m)))
        truth = se3.apply(se3.invert(true_poses[k] @ X), apex)
        errors.append(np.array([tip.x_m, tip.depth_m, tip.elevation_m - e[k]]) - truth)
        assert 25 < tip.half_angle_deg < 45  # the cone's 33.9°
    errors = np.abs(np.array(errors)) * 1e3
    assert errors.max(axis=0)[0] < 0.4 and errors.max(axis=0)[1] < 0.6
    assert errors.max(axis=0)[2] < 0.8 and np.median(errors[:, 2]) < 0.3


@pytest.fixture(scope="module")
def cone_run(tmp_path_factory):
    """One `uscal run` of the cone scenario, its dataset saved (≈ 30 s: shared)."""
    base = tmp_path_factory.mktemp("cone")
    run, data = base / "run", base / "d"
    r = uscal("run", str(CONE), "--out", str(run), "--save-dataset", str(data), "--no-rrd")
    assert r.returncode == 0, r.stderr
    return base, json.loads((run / "metrics.json").read_text()), r.stdout


def test_the_cone_tip_calibrates_within_its_bound(cone_run):
    _, m, stdout = cone_run
    c = m["calibration"]["cone_tip"]
    assert m["dataset"]["target"] == "cone_tip" and m["detection"]["sweeps_found"] == 45
    e = c["true_error"]
    assert e["rotation_deg"] < 1.5 and e["translation_mm"] < 1.0 and e["image_mm"] < 1.0
    assert all(c["bound_covers"].values()), (e, c["bound95"])
    assert "against the twin's truth" in stdout


def test_with_every_error_source_off_the_tip_gives_the_mount(tmp_path):
    r = uscal(
        "run", str(CONE), "--out", str(tmp_path / "run"),
        "--set", "phantom.tolerance_position_mm=0", "--set", "protocol.teaching_error_mm=0",
        "--set", "phantom.tolerance_radius_mm=0",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    c = json.loads((tmp_path / "run" / "metrics.json").read_text())["calibration"]["cone_tip"]
    e = c["true_error"]
    # Left: where each view's echoes put the surface (a few tenths of a millimetre).
    assert e["image_mm"] < 0.8 and all(c["bound_covers"].values())


def test_its_dataset_calibrates_as_the_run_did_and_validate_refuses_it(cone_run, tmp_path, capsys):
    base, metrics, _ = cone_run
    m, data = metrics["calibration"]["cone_tip"], base / "d"
    r = uscal_here(capsys, "calibrate", str(data), "--out", str(tmp_path / "cal"))
    assert r.returncode == 0, r.stderr
    again = json.loads((tmp_path / "cal" / "metrics.json").read_text())["calibration"]
    np.testing.assert_allclose(again["cone_tip"]["T_ee_us"], m["T_ee_us"], atol=1e-6)
    r = uscal_here(
        capsys, "validate", str(data), "--calibration", str(tmp_path / "cal" / "calibration.yaml")
    )
    assert r.returncode == 2 and "a cone-tip dataset" in r.stderr
