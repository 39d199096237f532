"""protocol.second_pass: the spheres scanned again with the sweeps planned through the
first pass's calibration, so that they run along the image normal; the first pass's
sweeps run along the coarse mount's axis, off it by the mount's error."""

from __future__ import annotations

import numpy as np
import pytest

from bench.config.scenario import load_scenario
from bench.jobs.single import run
from bench.outputs.report import report_markdown
from calib import se3
from calib.acquisition.protocol import sweep_axis_off_normal
from calib.errors import UscalError
from calib.records import Sweep

from .conftest import QUICK
from .test_cli import uscal_here

# Seed 9's coarse mount is 7.6° off the true one, almost all of it towards depth (the
# tilt that moves a sphere's depth from frame to frame along a sweep).
SHALLOW = [
    "seed=9",
    "protocol.spheres=[1]",
    "protocol.target_depth_mm=12",
    "imaging.depth_mm=27",
    "protocol.second_pass=true",
]


def _sweep(X, turn_deg, backwards=False):
    """A sweep of 5 frames whose flange moves along the image's elevational axis of
    ``X`` turned by ``turn_deg`` (x-y-z Euler angles about the image axes)."""
    T0 = se3.make(se3.matrix_from_euler(np.radians([170.0, 5.0, 30.0])), [0.3, 0.1, 0.2])
    R_us = T0[:3, :3] @ X[:3, :3]
    axis = R_us @ se3.matrix_from_euler(np.radians(turn_deg))[:, 2]
    steps = np.linspace(-0.01, 0.01, 5) * (-1 if backwards else 1)
    T = np.array([se3.make(T0[:3, :3], T0[:3, 3] + k * axis) for k in steps])
    return Sweep("sphere_1", 0, np.zeros((5, 2, 2), np.uint8), (1e-4, 1e-4), np.zeros((5, 6)), T)


def test_the_sweep_axis_off_the_normal_in_depth_and_across():
    X = se3.make(se3.matrix_from_euler(np.radians([3.0, -2.0, 40.0])), [0.01, 0.02, 0.1])
    along = sweep_axis_off_normal([_sweep(X, [0, 0, 0]), _sweep(X, [0, 0, 0], True)], X)
    assert along == pytest.approx(
        {"angle_deg": 0.0, "in_depth_deg": 0.0, "across_deg": 0.0}, abs=1e-6
    )
    # The way the flange moved turned 5° about the image's lateral axis (x): towards depth
    # (the image's y) alone; about its axial axis (y): across the image alone.
    a = sweep_axis_off_normal([_sweep(X, [-5.0, 0, 0])], X)
    assert a["angle_deg"] == pytest.approx(5.0) and a["in_depth_deg"] == pytest.approx(5.0)
    assert a["across_deg"] == pytest.approx(0.0, abs=1e-9)
    a = sweep_axis_off_normal([_sweep(X, [0, 5.0, 0]), _sweep(X, [0, 5.0, 0], True)], X)
    assert a["across_deg"] == pytest.approx(5.0) and a["in_depth_deg"] == pytest.approx(0.0)
    # The median over sweeps: one sweep far off does not move it.
    many = [_sweep(X, [-2.0, 0, 0])] * 4 + [_sweep(X, [-30.0, 0, 0])]
    assert sweep_axis_off_normal(many, X)["in_depth_deg"] == pytest.approx(2.0)


def test_the_second_pass_is_planned_through_the_first_pass_calibration():
    scenario = load_scenario(QUICK, SHALLOW)
    result = run(scenario)
    m = result.metrics
    first = m["first_pass"]
    # The first pass ran along the coarse mount, 7.6° off the normal, nearly all in depth.
    assert first["sweep_axis"]["angle_deg"] > 5.0
    assert abs(first["sweep_axis"]["in_depth_deg"]) > 5.0
    # The second pass's sweeps were planned through the first pass's calibration, which
    # was within a degree of the truth: its sweeps ran within two of the final normal.
    assert first["true_error"]["single"]["rotation_deg"] < 1.5
    assert m["calibration"]["sweep_axis"]["angle_deg"] < 2.0
    # Scanned once, that tilt over caps 5-8 mm under the face made the calibration
    # suspect; the second pass's sweeps, along the normal, leave it nothing to say.
    assert first["tilted_over_shallow_caps"] == {"single": True}
    reasons = m["calibration"]["single"]["verdict"]["reasons"]
    assert not any("towards depth" in r for r in reasons), reasons
    first_error = first["true_error"]["single"]
    coarse = result.acquisition.T_ee_us_coarse
    truth = m["calibration"]["coarse_error"]  # the second pass's planning mount vs truth
    assert truth["rotation_deg"] == pytest.approx(first_error["rotation_deg"], abs=1e-9)
    assert truth["translation_mm"] == pytest.approx(first_error["translation_mm"], abs=1e-9)
    assert not np.allclose(coarse, result.single.result.T_ee_us)
    # Both passes' robot time is the acquisition's.
    assert m["acquisition"]["robot_time_s"] == pytest.approx(
        first["robot_time_s"] + result.acquisition.robot_time_s
    )
    assert m["acquisition"]["robot_time_s"] > 1.9 * first["robot_time_s"]
    assert "simulate_s" not in first and m["timing_s"]["simulate"] < m["timing_s"]["total"]
    # The report says both passes' tilts and what the first pass was off by.
    md = report_markdown(scenario, result, {})
    assert "The second pass's sweeps ran" in md and "The first pass's sweeps ran" in md
    assert f"rotation {first['true_error']['single']['rotation_deg']:.3f} °" in md


@pytest.mark.parametrize(
    "extra, said",
    [
        (["--until-rotation-deg", "0.5"], "not the sequential acquisition"),
        (["--set", "evaluation.datasets=[A, B]"], "the paper's experiment on several datasets"),
    ],
)
def test_a_second_pass_where_there_is_none_is_refused_before_anything_runs(
    capsys, tmp_path, extra, said
):
    out = tmp_path / "out"
    r = uscal_here(
        capsys, "run", str(QUICK), "--set", "protocol.second_pass=true", "--out", str(out), *extra
    )
    assert r.returncode != 0
    assert "protocol.second_pass" in r.stderr and said in r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists()


def test_the_refusal_is_the_runs_own_error():
    with pytest.raises(UscalError, match=r"protocol\.second_pass"):
        run(load_scenario(QUICK, ["protocol.second_pass=true", "evaluation.datasets=[A, B]"]))


def test_on_the_rig_a_second_pass_is_a_second_acquisition(tmp_path, capsys):
    """A hw config asking for a second pass is refused before anything connects, naming
    what does it on the rig: the first calibration's mount as the coarse one."""
    hw = tmp_path / "hw.yaml"
    hw.write_text(
        "robot: {host: 127.0.0.250}\ngrabber: {source: '0'}\nprotocol: {second_pass: true}\n"
    )
    r = uscal_here(capsys, "acquire", str(hw), "--out", str(tmp_path / "ds"), "--yes")
    assert r.returncode == 2
    assert "protocol.second_pass" in r.stderr and "rig.coarse_rotation_xyz_deg" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "ds").exists()
