"""Acquisitions on the loopback rig beyond the paper's protocol: a saved plan (and its
spares), a sequential acquisition that stops at its predicted bounds, and a controller
whose TCP is not the flange."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.errors import RobotSetupError
from calib.files.dataset import read_dataset
from hw.config import URRobotConfig
from hw.robot import URRobot

from .loopback import (
    ONE_SPHERE,
    QUICK,
    SHORT,
    SWEEPS_OF_13,
    calibrates_to_the_truth,
    one_line_error,
)
from .test_cli import uscal


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.8",)], indirect=True)
def test_a_planned_acquisition_on_the_loopback_rig(controller, tmp_path):
    """`uscal plan --optimize --out PLAN` then `uscal acquire` with protocol.plan: the
    rig acquires the plan's sweeps (a third of the paper's) and calibrates as well; a
    plan for other spheres is refused before anything moves."""
    plan, dataset, out = tmp_path / "plan.yaml", tmp_path / "ds", tmp_path / "cal"
    # The planner's coarser grid and fewer other sessions, as tests/test_plan_file.py
    # plans (the plan's quality is tested there): what is tested here is the rig.
    coarse = [
        "--set", "planning.rotation_step_deg=15", "--set", "planning.shift_step_mm=3",
        "--set", "planning.session_draws=6",
    ]  # fmt: skip
    r = uscal(
        "plan", str(QUICK), *ONE_SPHERE, "--optimize", "--sweeps", "15", *coarse,
        "--out", str(plan),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "optimized" in r.stdout and plan.exists()
    use = ["--set", f"protocol.plan={plan}"]
    wrong = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *use)
    assert "the plan has sweeps for sphere_1; the protocol scans" in one_line_error(wrong)
    assert not dataset.exists()
    r = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE, *use)
    assert r.returncode == 0, r.stderr
    ds, _ = read_dataset(dataset)
    assert len(ds.sweeps) == 15
    m = calibrates_to_the_truth(dataset, out)
    assert m["localization"]["n_rejected"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.12",)], indirect=True)
def test_a_sweep_the_rig_refuses_is_replaced_by_a_spare_not_the_acquisition(controller, tmp_path):
    """A plan's sweep that falls outside the rig's workspace box this day: `uscal
    acquire` puts the plan's first spare that passes in its place, says so in one line,
    and acquires every sweep through the loopback controller."""
    from bench.config.hw import load_hw_config
    from bench.config.plan_file import write_plan
    from calib.acquisition.planning import SweepPose
    from calib.acquisition.protocol import plan_sweeps
    from calib.dh import NOMINAL_TABLES, forward_kinematics

    sets = ["protocol.spheres=[1]", "protocol.frames_per_sweep=3"]
    cfg = load_hw_config(controller.hw, sets)
    taught = forward_kinematics(NOMINAL_TABLES[cfg.robot.model], np.radians(cfg.rig.taught_deg(1)))
    level = (0.0, 0.0, 0.0)
    plan = [
        SweepPose(level, 0.0, 0.0),
        SweepPose(level, 30.0, 0.0),
        SweepPose((10.0, 0.0, 0.0), 0.0, 0.0),
        SweepPose((0.0, 10.0, 0.0), 0.0, 0.0),
    ]
    far, spare = SweepPose(level, 28.0, 0.0), SweepPose(level, -4.0, 0.0)
    every = [*plan, far, spare]
    sweeps = plan_sweeps("sphere_1", taught, cfg.rig.T_ee_us_coarse, cfg.protocol, poses=every)
    where = {
        p: np.array([T[:3, 3] for T in s.T_base_ee]) * 1e3
        for p, s in zip(every, sweeps, strict=True)
    }
    # The box's upper corner cut between the 30 mm sweep and every other (the taught
    # pose included), along the base axis where they part most.
    top = {p: xyz.max(axis=0) for p, xyz in where.items()}
    others = np.max([top[p] for p in where if p not in (plan[1], far)] + [taught[:3, 3] * 1e3], 0)
    axis = int(np.argmax(top[plan[1]] - others))
    assert top[plan[1]][axis] - others[axis] > 10 and top[far][axis] > others[axis] + 5
    box = list(cfg.robot.workspace_max_mm)
    box[axis] = float(others[axis] + 2.0)
    path = write_plan(tmp_path / "plan.yaml", {"sphere_1": plan}, {}, {"sphere_1": (far, spare)})
    use = [*(x for s in sets for x in ("--set", s)), "--set", f"protocol.plan={path}",
           "--set", f"robot.workspace_max_mm={box}"]  # fmt: skip
    dataset = tmp_path / "ds"
    r = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *use)
    assert r.returncode == 0, r.stderr
    said = " ".join(r.stdout.split())
    assert "sphere_1 sweep 1 replaced by spare 1 (turned 0°, 0°, 0°, shifted -4 / 0 mm)" in said
    ds, _ = read_dataset(dataset)
    assert len(ds.sweeps) == 4 and all(s.n_frames == 3 for s in ds.sweeps)


# The served scanner with the paper's stated widths and smooth surfaces: on the
# transducer's own beam with printed-surface speckle the predicted bounds stop the
# acquisition too early (1.17° true rotation error against a 0.35° target: the per-sweep
# noise the prediction assumes is the smoother images'); issue 36 makes the bounds hold.
STATED_SCANNER = (
    "--set", "imaging.lateral_fwhm_mm=0.7", "--set", "imaging.axial_fwhm_mm=0.35",
    "--set", "imaging.slice_thickness_mm=0.7", "--set", "imaging.side_lobe_db=-40",
    "--set", "imaging.noise_db=-55", "--set", "imaging.surface_speckle=false",
    "--set", "imaging.scanline_spacing_mm=0.2",
)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.9", *STATED_SCANNER)], indirect=True)
def test_a_sequential_acquisition_on_the_loopback_rig(controller, tmp_path):
    """`uscal acquire --until-rotation-deg --until-translation-mm`: the rig takes the
    paper's sweeps in the order that informs most and stops at the predicted bounds,
    long before the 45; the dataset calibrates."""
    dataset, out = tmp_path / "ds", tmp_path / "cal"
    # Bounds the 45 reach (they predict 0.38° / 0.13 mm for planning's noise model).
    until = ["--until-rotation-deg", "0.45", "--until-translation-mm", "0.15"]
    r = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE, *until)
    assert r.returncode == 0, r.stderr
    ds, _ = read_dataset(dataset)
    assert 6 <= len(ds.sweeps) < 30
    calibrates_to_the_truth(dataset, out, max_deg=0.8)
    again = uscal("acquire", str(controller.hw), "--out", str(dataset), "--resume", *until)
    assert "starts anew" in one_line_error(again)


# ------------------------------------------------------------- the controller's TCP

TCP_150 = ("--tcp-offset", "0", "0", "150", "0", "0", "20")


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.10", *TCP_150)], indirect=True)
def test_a_non_zero_tcp_is_refused_or_cleared_and_the_flange_calibrates(controller, tmp_path):
    """A controller whose active TCP is not the flange: `uscal acquire` refuses before
    anything moves; the adapter asked to clears it without moving; `uscal acquire
    --set-tcp-zero` says what it cleared, records the flange and calibrates."""
    from calib.dh import NOMINAL_TABLES, forward_kinematics
    from hw.rtde_process import RtdeProcess

    tcp_150 = [0.0, 0.0, 0.15, 0.0, 0.0, float(np.radians(20))]
    # What the controller reports with this TCP: the TCP's pose, 150 mm beyond the flange
    # (the poses a calibration would silently get wrong).
    raw = RtdeProcess(controller.host)
    try:
        q0 = np.array(raw.call("receive", "getActualQ"))
        T_tcp = se3.matrix_from_pose6(raw.call("receive", "getActualTCPPose"))
    finally:
        raw.close()
    T_flange = forward_kinematics(NOMINAL_TABLES["ur3"], q0)
    assert abs(se3.translation_distance(T_tcp, T_flange) - 0.150) < 1e-4
    r = uscal("acquire", str(controller.hw), "--out", str(tmp_path / "ds0"), "--yes", *SHORT)
    line = one_line_error(r)
    assert "active TCP offset is [0.0, 0.0, 150.0] mm" in line and "--set-tcp-zero" in line
    assert "nothing moved" in line and not (tmp_path / "ds0").exists()
    cfg = URRobotConfig(host=controller.host, settle_s=0.0)
    with pytest.raises(RobotSetupError, match="must be zero"):
        URRobot(cfg)
    # Asked to, the adapter sets it to zero and says what it was; the poses are the
    # flange's again, and the arm has not moved.
    with URRobot(cfg, set_tcp_zero=True) as robot:
        assert np.allclose(robot.tcp_offset_cleared, tcp_150)
        assert np.all(robot.tcp_offset() == 0)
        reading = robot.read()
        assert np.allclose(reading.q, q0, atol=1e-4)  # encoder noise only
        T_model = forward_kinematics(NOMINAL_TABLES["ur3"], reading.q)
        assert se3.translation_distance(reading.T_base_ee, T_model) < 1e-6
    # The TCP set again (as another program on the teach pendant would), then acquired
    # with the flag: sweeps of 13 frames 1 mm apart, enough to localize the sphere.
    raw = RtdeProcess(controller.host)
    try:
        raw.call("control", "setTcp", tcp_150)
        assert np.allclose(raw.call("control", "getTCPOffset"), tcp_150)
    finally:
        raw.close()
    dataset = tmp_path / "ds"
    r = uscal(
        "acquire", str(controller.hw), "--out", str(dataset), "--yes", "--set-tcp-zero",
        *ONE_SPHERE, *SWEEPS_OF_13,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "TCP offset was [0.0, 0.0, 150.0] mm" in " ".join(r.stdout.split())
    calibrates_to_the_truth(dataset, tmp_path / "cal")
