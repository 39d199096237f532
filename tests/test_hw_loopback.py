"""The hw adapters against a real client and a loopback controller: `uscal twin serve`
(a separate process: the twin behind RTDE, the dashboard and the script port, its
scanner writing frames to a file) driven by the unmodified ur_rtde client through
hw.URRobot / `uscal acquire`, read by hw.FrameGrabber (OpenCV), then `uscal calibrate`
against the twin's truth; and the faults."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calib import se3
from calib.errors import FrameGrabberError, RobotConnectionError, RobotSetupError
from calib.files.dataset import read_dataset
from hw.config import GrabberConfig, URRobotConfig
from hw.grabber import FrameGrabber
from hw.robot import URRobot

from .conftest import QUICK
from .test_cli import uscal, uscal_here

# One sphere, the whole 45-sweep protocol: the claim. The fault tests use short sweeps.
ONE_SPHERE = ["--set", "protocol.spheres=[1]"]
SHORT = [*ONE_SPHERE, "--set", "protocol.frames_per_sweep=3"]


class Controller:
    """`uscal twin serve` in its own process group on a loopback address."""

    def __init__(self, tmp: Path, host: str, *extra: str) -> None:
        self.host, self.frames, self.hw = host, tmp / "live.pgm", tmp / "hw.yaml"
        script = Path(sys.executable).parent / "uscal"
        cmd = [str(script)] if script.exists() else [sys.executable, "-m", "bench.cli"]
        self.proc = subprocess.Popen(
            [*cmd, "twin", "serve", str(QUICK), "--host", host, "--frames", str(self.frames),
             "--hw-config", str(self.hw), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"controller exited: {self.proc.stdout.read()}")
            if self.hw.exists() and self.frames.exists() and _listening(host, 30004):
                return
            time.sleep(0.2)
        self.stop()
        raise RuntimeError("controller did not start within 60 s")

    def dashboard(self, command: str) -> str:
        with socket.create_connection((self.host, 29999), timeout=5) as s:
            f = s.makefile("rw")
            f.readline()
            f.write(command + "\n")
            f.flush()
            return f.readline().strip()

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


@pytest.fixture
def controller(tmp_path, request):
    host, *extra = request.param
    c = Controller(tmp_path, host, *extra)
    yield c
    c.stop()


def _one_line_error(r: subprocess.CompletedProcess) -> str:
    """The CLI's error: exit code 2 and exactly one `uscal: error:` line, no traceback."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [line for line in r.stderr.splitlines() if line.startswith("uscal: error:")]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def _calibrates_to_the_truth(dataset: Path, out: Path, max_deg: float = 0.6, *flags: str) -> dict:
    """`uscal calibrate` of a loopback dataset (with ``flags``): the served twin's true
    mount (same scenario and seed), within the tolerance of `uscal run` on it
    (tests/test_run.py). Returns the metrics."""
    from bench.acquire_sim import make_twin
    from bench.config.scenario import load_scenario
    from bench.truth import image_error_mm

    r = uscal(
        "calibrate", str(dataset), "--markers", "1", "--settings", str(QUICK),
        "--out", str(out), "--no-rrd", *flags,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "metrics.json").read_text())
    T = np.array(m["calibration"]["single"]["T_ee_us"])
    scenario = load_scenario(QUICK)
    T_true = make_twin(scenario).truth.T_ee_us
    assert image_error_mm(scenario, T, T_true) <= 0.5
    assert np.degrees(se3.rotation_angle(T, T_true)) <= max_deg
    return m


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.3",)], indirect=True)
def test_acquire_on_the_loopback_rig_then_calibrate_finds_the_true_mount(controller, tmp_path):
    """`uscal acquire` with a requirement calibrates what it acquired and gates on it: a
    requirement it cannot meet (0.01 mm) exits 3 with the verdict's reason; `uscal
    calibrate` of the same dataset within 1 mm is accepted and finds the true mount."""
    dataset, out = tmp_path / "ds", tmp_path / "cal"
    r = uscal(
        "acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE,
        "--require-image-mm", "0.01", "--markers", "1", "--settings", str(QUICK),
    )  # fmt: skip
    assert r.returncode == 3, (r.returncode, r.stderr)
    said = " ".join(r.stdout.split())
    assert "acquired 45 sweeps" in said and "required 0.01 mm" in said
    strict = json.loads((tmp_path / "ds-calibration" / "metrics.json").read_text())
    assert strict["calibration"]["single"]["verdict"]["status"] == "rejected"
    ds, info = read_dataset(dataset)
    assert len(ds.sweeps) == 45 and all(s.n_frames == 21 for s in ds.sweeps)
    assert info.source == "hardware"
    # The reported poses are the controller's: RTDE's actual_TCP_pose, the nominal model.
    assert all(np.isfinite(s.T_base_ee).all() for s in ds.sweeps)
    # Accepted within a requirement it meets: exit 0.
    m = _calibrates_to_the_truth(dataset, out, 0.6, "--require-image-mm", "1")
    assert m["calibration"]["single"]["verdict"]["status"] == "accepted"


def test_acquire_checks_what_its_calibration_needs_before_anything_moves(tmp_path, capsys):
    """With a requirement, `uscal acquire` will calibrate: a settings file that is not
    there, or a calibration directory already in use, is one line before any motion."""
    hw = tmp_path / "hw.yaml"
    hw.write_text("robot: {host: 127.0.0.250}\ngrabber: {source: '0'}\n")
    (tmp_path / "ds-calibration").mkdir()
    (tmp_path / "ds-calibration" / "x").write_text("")
    args = ["acquire", str(hw), "--out", str(tmp_path / "ds"), "--yes"]
    r = uscal_here(capsys, *args, "--require-image-mm", "1", "--settings", "nowhere.yaml")
    assert r.returncode == 2 and "nowhere.yaml" in r.stderr
    r = uscal_here(capsys, *args, "--require-image-mm", "1")
    assert r.returncode == 2 and "ds-calibration: exists" in r.stderr
    assert not (tmp_path / "ds").exists()


# The gain raised 40 dB, as an operator does in clear water: the receiver noise shows,
# so every grabbed frame differs from the last even where nothing is in view.
@pytest.mark.parametrize(
    "controller", [("127.0.0.4", "--set", "imaging.gain_db=40")], indirect=True
)
def test_robot_and_grabber_adapters_move_read_and_grab(controller):
    cfg = URRobotConfig(host=controller.host, settle_s=0.0)
    grabber_cfg = GrabberConfig(source=str(controller.frames), pixel_spacing_mm=(0.2, 0.1))
    with URRobot(cfg) as robot, FrameGrabber(grabber_cfg) as grabber:
        start = robot.read()
        before = grabber.grab().image
        target = start.T_base_ee.copy()
        target[2, 3] -= 0.01  # 10 mm down
        reading = robot.move_to(target, "10 mm down")
        # The controller reaches the commanded pose in its own model (encoder noise only).
        assert se3.translation_distance(reading.T_base_ee, target) < 0.1e-3
        after = grabber.grab()
        assert after.spacing == (0.2e-3, 0.1e-3) and after.image.dtype == np.uint8
        assert after.image.shape == before.shape and not np.array_equal(after.image, before)
        far = reading.T_base_ee.copy()
        far[0, 3] += 0.3
        with pytest.raises(Exception, match=r"outside the workspace|max_step"):
            robot.move_to(far, "a jump")  # refused before anything moves
        assert se3.translation_distance(robot.read().T_base_ee, reading.T_base_ee) < 0.1e-3
    roi = FrameGrabber(GrabberConfig(source=str(controller.frames), roi_px=(10, 5, 40, 30)))
    assert roi.grab().image.shape == (30, 40)
    assert controller.dashboard("PolyscopeVersion").startswith("URSoftware 5.")


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.5", "--fault-drop-at-move", "30")], indirect=True)
def test_connection_lost_mid_sweep_keeps_finished_sweeps_and_resumes(controller, tmp_path):
    dataset = tmp_path / "ds"
    args = ["acquire", str(controller.hw), "--out", str(dataset), "--yes", *SHORT]
    t0 = time.monotonic()
    r = uscal(*args)
    line = _one_line_error(r)
    assert "connection lost" in line and "--resume" in line
    assert time.monotonic() - t0 < 60
    # Move 1 goes to the taught pose, then 3 moves per sweep: move 30 is in sweep 10.
    partial, _ = read_dataset(dataset, allow_incomplete=True)
    assert [s.pose_id for s in partial.sweeps] == list(range(9))
    deadline = time.monotonic() + 30  # the outage ends after 3 s
    while not _listening(controller.host, 30004) and time.monotonic() < deadline:
        time.sleep(0.2)
    r = uscal(*args, "--resume")
    assert r.returncode == 0, r.stderr
    assert "9 from before" in r.stdout
    full, _ = read_dataset(dataset)
    assert [s.pose_id for s in full.sweeps] == list(range(45))
    # The sweeps written before the fault are untouched by the resume.
    assert all(
        np.array_equal(a.images, b.images)
        for a, b in zip(partial.sweeps, full.sweeps[:9], strict=True)
    )


@pytest.mark.parametrize(
    "controller", [("127.0.0.6", "--fault-protective-stop-at-move", "20")], indirect=True
)
@pytest.mark.slow
def test_protective_stop_mid_move_ends_the_acquisition_cleanly(controller, tmp_path):
    dataset = tmp_path / "ds"
    # Sweeps of 13 frames 1 mm apart: the calibration below must be able to localize the
    # sphere in them (3 frames 10 mm apart cannot resolve its elevation, nor 7 frames
    # 3.3 mm apart the specular cap's).
    frames = ["--set", "protocol.frames_per_sweep=13", "--set", "protocol.sweep_half_length_mm=6"]
    args = ["acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE, *frames]
    line = _one_line_error(uscal(*args))
    assert "protective stop" in line and "1 of 45 sweeps are saved" in line
    assert controller.dashboard("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    # The operator clears the stop; the acquisition resumes where it ended.
    assert controller.dashboard("unlock protective stop") == "Protective stop releasing"
    # The resume also takes the touches, hand-guided by the rig's emulated operator.
    r = uscal(*args, "--resume", "--touches", "loopback")
    assert r.returncode == 0, r.stderr
    ds, _ = read_dataset(dataset)
    assert len(ds.sweeps) == 45 and len(ds.touches) == 4 * 6  # vertices × touches each
    # The touches, recorded through RTDE, fix the phantom within the contact noise (0.2 mm).
    out = tmp_path / "cal"
    r = uscal(
        "calibrate", str(dataset), "--markers", "1", "--settings", str(QUICK), "--out", str(out),
        "--no-rrd", "--set", "evaluation.initialisations=2",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    ev = json.loads((out / "metrics.json").read_text())["evaluation"]
    assert ev["touches"] == 24 and ev["touch_residual_rms_mm"] < 0.6
    assert max(ev["tool_precision_mm"].values()) < 0.6


@pytest.mark.parametrize("controller", [("127.0.0.7",)], indirect=True)
def test_a_grabber_without_frames_fails_with_one_line(controller, tmp_path):
    # Without --yes the first motion waits for a confirmation: none can be given here.
    line = _one_line_error(
        uscal("acquire", str(controller.hw), "--out", str(tmp_path / "ds0"), *SHORT)
    )
    assert "pass --yes" in line and controller.dashboard("running") == "Program running: false"
    r = uscal(
        "acquire", str(controller.hw), "--out", str(tmp_path / "ds"), "--yes", *SHORT,
        "--set", f"grabber.source={tmp_path / 'no-such-frame.pgm'}",
        "--set", "grabber.timeout_s=0.5",
    )  # fmt: skip
    line = _one_line_error(r)
    assert "no frame for 0.5 s" in line and "0 of 45 sweeps are saved" in line
    with pytest.raises(FrameGrabberError, match="cannot be opened"):
        FrameGrabber(GrabberConfig(source="rtsp://127.0.0.7:1/none"))


def test_an_unreachable_controller_fails_within_seconds(tmp_path):
    hw = tmp_path / "hw.yaml"
    hw.write_text(
        "robot:\n  host: 127.0.0.9\n  connect_timeout_s: 1\n"
        "rig:\n  taught_sphere_1_deg: [0, -90, -90, -90, 90, 0]\n"
    )
    t0 = time.monotonic()
    line = _one_line_error(
        uscal("acquire", str(hw), "--out", str(tmp_path / "ds"), "--yes", *SHORT)
    )
    assert "unreachable" in line and time.monotonic() - t0 < 15
    assert not (tmp_path / "ds").exists() or not any((tmp_path / "ds" / "sweeps").iterdir())
    # An address outside this machine (it may not answer at all, or a firewall may): the
    # timeout bounds the wait either way.
    t0 = time.monotonic()
    with pytest.raises(RobotConnectionError, match=r"10\.255\.255\.1"):
        URRobot(URRobotConfig(host="10.255.255.1", connect_timeout_s=1.0))
    assert time.monotonic() - t0 < 5


def test_hw_config_mistakes_are_one_line(tmp_path, capsys):
    hw = tmp_path / "hw.yaml"
    cases = {
        "robot:\n  hots: 1.2.3.4\n": "robot.hots",
        "grabber:\n  source: '0'\n": "robot.host",
        "robot:\n  host: h\n  speed_m_s: 9\n": "speed_m_s",
        "robot:\n  host: h\n  workspace_min_mm: [0, 0, 900]\n": "workspace box is empty",
        "robot:\n  host: h\nrig:\n  taught_sphere_1_deg: [1, 2]\n": "expected 6 values",
    }
    for text, message in cases.items():
        hw.write_text(text)
        line = _one_line_error(
            uscal_here(capsys, "acquire", str(hw), "--out", str(tmp_path / "ds"), "--dry-run")
        )
        assert message in line, (text, line)
    hw.write_text("robot:\n  host: h\n")
    line = _one_line_error(uscal("acquire", str(hw), "--out", str(tmp_path / "ds"), "--dry-run"))
    assert "no taught pose for sphere_1" in line


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.8",)], indirect=True)
def test_a_planned_acquisition_on_the_loopback_rig(controller, tmp_path):
    """`uscal plan --optimize --out PLAN` then `uscal acquire` with protocol.plan: the
    rig acquires the plan's sweeps (a third of the paper's) and calibrates as well; a
    plan for other spheres is refused before anything moves."""
    plan, dataset, out = tmp_path / "plan.yaml", tmp_path / "ds", tmp_path / "cal"
    r = uscal("plan", str(QUICK), *ONE_SPHERE, "--optimize", "--sweeps", "15", "--out", str(plan))
    assert r.returncode == 0, r.stderr
    assert "optimized" in r.stdout and plan.exists()
    use = ["--set", f"protocol.plan={plan}"]
    wrong = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *use)
    assert "the plan has sweeps for sphere_1; the protocol scans" in _one_line_error(wrong)
    assert not dataset.exists()
    r = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE, *use)
    assert r.returncode == 0, r.stderr
    ds, _ = read_dataset(dataset)
    assert len(ds.sweeps) == 15
    m = _calibrates_to_the_truth(dataset, out)
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
    until = ["--until-rotation-deg", "0.35", "--until-translation-mm", "0.12"]
    r = uscal("acquire", str(controller.hw), "--out", str(dataset), "--yes", *ONE_SPHERE, *until)
    assert r.returncode == 0, r.stderr
    ds, _ = read_dataset(dataset)
    assert 6 <= len(ds.sweeps) < 30
    _calibrates_to_the_truth(dataset, out, max_deg=0.8)
    again = uscal("acquire", str(controller.hw), "--out", str(dataset), "--resume", *until)
    assert "starts anew" in _one_line_error(again)


# ------------------------------------------------------------- the controller's TCP

TCP_150 = ("--tcp-offset", "0", "0", "150", "0", "0", "20")


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.10", *TCP_150)], indirect=True)
def test_a_non_zero_tcp_is_refused_before_anything_moves(controller, tmp_path):
    from calib.dh import NOMINAL_TABLES, forward_kinematics
    from hw.rtde_process import RtdeProcess

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
    r = uscal("acquire", str(controller.hw), "--out", str(tmp_path / "ds"), "--yes", *SHORT)
    line = _one_line_error(r)
    assert "active TCP offset is [0.0, 0.0, 150.0] mm" in line and "--set-tcp-zero" in line
    assert "nothing moved" in line and not (tmp_path / "ds").exists()
    cfg = URRobotConfig(host=controller.host, settle_s=0.0)
    with pytest.raises(RobotSetupError, match="must be zero"):
        URRobot(cfg)
    # Asked to, the adapter sets it to zero and says what it was; the poses are the
    # flange's again, and the arm has not moved.
    with URRobot(cfg, set_tcp_zero=True) as robot:
        assert np.allclose(robot.tcp_offset_cleared, [0, 0, 0.15, 0, 0, np.radians(20)])
        assert np.all(robot.tcp_offset() == 0)
        reading = robot.read()
        assert np.allclose(reading.q, q0, atol=1e-4)  # encoder noise only
        T_model = forward_kinematics(NOMINAL_TABLES["ur3"], reading.q)
        assert se3.translation_distance(reading.T_base_ee, T_model) < 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("controller", [("127.0.0.11", *TCP_150)], indirect=True)
def test_acquire_with_set_tcp_zero_records_the_flange_and_calibrates(controller, tmp_path):
    dataset = tmp_path / "ds"
    r = uscal(
        "acquire", str(controller.hw), "--out", str(dataset), "--yes", "--set-tcp-zero",
        *ONE_SPHERE,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "TCP offset was [0.0, 0.0, 150.0] mm" in " ".join(r.stdout.split())
    _calibrates_to_the_truth(dataset, tmp_path / "cal")
