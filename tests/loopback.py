"""The loopback rig the hw tests drive: `uscal twin serve` (a separate process: the twin
behind RTDE, the dashboard and the script port, its scanner writing frames to a file),
and the checks its tests share. The ``controller`` fixture (conftest.py) starts one per
test, with the test's address and flags (indirect parametrization)."""

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

from calib import se3

from .conftest import QUICK
from .test_cli import uscal

# One sphere, the whole 45-sweep protocol: the claim. The fault tests use short sweeps.
ONE_SPHERE = ["--set", "protocol.spheres=[1]"]
SHORT = [*ONE_SPHERE, "--set", "protocol.frames_per_sweep=3"]
# Sweeps of 13 frames 1 mm apart: a calibration can localize the sphere in them (3 frames
# 10 mm apart cannot resolve its elevation, nor 7 frames 3.3 mm apart the specular cap's).
SWEEPS_OF_13 = ["--set", "protocol.frames_per_sweep=13", "--set", "protocol.sweep_half_length_mm=6"]


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
            if self.hw.exists() and self.frames.exists() and listening(host, 30004):
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


def listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def one_line_error(r: subprocess.CompletedProcess) -> str:
    """The CLI's error: exit code 2 and exactly one `uscal: error:` line, no traceback."""
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [line for line in r.stderr.splitlines() if line.startswith("uscal: error:")]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def calibrates_to_the_truth(dataset: Path, out: Path, max_deg: float = 0.6, *flags: str) -> dict:
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
