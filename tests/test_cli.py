"""The uscal command line, run as a user runs it (separate processes)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
QUICK = str(ROOT / "scenarios" / "quick.yaml")


def uscal(
    *args: str, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """``env``: variables set on top of this process's environment."""
    script = Path(sys.executable).parent / "uscal"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "bench.cli"]
    return subprocess.run(
        [*cmd, *args], capture_output=True, text=True, cwd=cwd, timeout=300,
        env={**os.environ, **env} if env else None,
    )  # fmt: skip


def uscal_here(capsys: pytest.CaptureFixture[str], *args: str) -> subprocess.CompletedProcess[str]:
    """The same command through ``bench.cli.main`` in this process: for the many
    one-line-error cases, which would each spend seconds importing in a new process (the
    console script itself is exercised by the tests that use :func:`uscal`)."""
    from bench.cli import main

    capsys.readouterr()
    code = main(list(args))
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(["uscal", *args], code, out, err)


def test_check_valid_scenario():
    r = uscal("check", QUICK)
    assert r.returncode == 0, r.stderr
    assert "scenario is valid" in r.stdout


def test_check_default_scenario():
    r = uscal("check")
    assert r.returncode == 0, r.stderr
    assert "<default>" in r.stdout


def test_bad_scenario_is_one_line_exit_2_no_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("imaging:\n  gain_db: 100\n")
    r = uscal("check", str(bad))
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "bad.yaml: imaging.gain_db = 100: out of range" in lines[0]
    assert "≤ 60" in lines[0]
    # --debug shows where it came from.
    r = uscal("--debug", "check", str(bad))
    assert r.returncode == 2 and "Traceback" in r.stderr


def test_set_override_is_validated():
    r = uscal("check", QUICK, "--set", "robot.dh_error_scale=-2")
    assert r.returncode == 2
    assert "robot.dh_error_scale = -2" in r.stderr


def test_twin_export_writes_loadable_mjcf_and_prints_landmarks(tmp_path):
    out = tmp_path / "twin"
    r = uscal("twin", "export", QUICK, str(out), "--set", "robot.dh_error_scale=0")
    assert r.returncode == 0, r.stderr
    assert "sphere_1" in r.stdout and "vertex_4" in r.stdout
    model = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
    assert model.nmesh >= 13 and (out / "meshes" / "sphere_1.stl").exists()
    assert [model.joint(i).name for i in range(6)] == [f"joint{i}" for i in range(1, 7)]
    truth = yaml.safe_load((out / "truth.yaml").read_text())
    s1 = np.array(truth["landmarks_base_mm"]["sphere_1"])
    # quick.yaml: phantom at (300, 0, 0) mm turned -3° about z; sphere 1 at (-25, -25, 20).
    c, s = np.cos(np.radians(-3)), np.sin(np.radians(-3))
    expected = np.array([300 + c * -25 - s * -25, s * -25 + c * -25, 20])
    assert np.linalg.norm(s1 - expected) < 1.0  # within printing tolerance (mm)
    # Zero DH error: the exported arm is the nominal UR3.
    assert truth["dh_true"]["a_m"][1] == pytest.approx(-0.24365, abs=1e-15)


@pytest.mark.slow  # ten seconds or more on this machine
def test_twin_export_refuses_to_overwrite_and_failed_export_leaves_nothing(tmp_path):
    out = tmp_path / "twin"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = uscal("twin", "export", QUICK, str(out))
    assert r.returncode == 2 and "not empty" in r.stderr
    assert (out / "keep.txt").read_text() == "mine"
    # A scenario error after the directory would have been started leaves no output.
    fresh = tmp_path / "fresh"
    r = uscal("twin", "export", QUICK, str(fresh), "--set", "phantom.position_mm=[900,0,0]")
    assert r.returncode == 2
    assert not fresh.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["twin"]
    # --force replaces atomically.
    r = uscal("twin", "export", QUICK, str(out), "--force")
    assert r.returncode == 0, r.stderr
    assert not (out / "keep.txt").exists() and (out / "scene.xml").exists()


def test_docs_command_prints_the_scenario_reference():
    r = uscal("docs", "scenarios")
    assert r.returncode == 0
    assert r.stdout == (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")


@pytest.mark.slow
def test_image_gallery(tmp_path):
    out = tmp_path / "gallery"
    r = uscal("image", QUICK, "--out", str(out))
    assert r.returncode == 0, r.stderr
    from skimage import io as skio

    nominal = skio.imread(out / "frame_nominal.png")
    assert nominal.dtype == np.uint8 and nominal.ndim == 2
    assert nominal.max() > 150  # the sphere's cap and the floor line
    assert (out / "gallery.png").stat().st_size > 10_000
    poses = yaml.safe_load((out / "gallery.yaml").read_text())["poses"]
    assert poses["a_m10_p10_p10_offset"]["in_plane_mm"] == [3, 3]
    assert len(list(out.glob("frame_*.png"))) == len(poses) == 10


@pytest.mark.slow
def test_quiet_prints_nothing_before_or_after_the_command():
    for args in (("--quiet", "check", QUICK), ("check", QUICK, "-q")):
        r = uscal(*map(str, args))
        assert r.returncode == 0, r.stderr
        assert r.stdout == ""


def test_run_shows_progress_with_counts(quick_run):
    out, *_ = quick_run
    stdout = (out.parent / "stdout.txt").read_text(encoding="utf-8")
    assert "acquire sweeps" in stdout and "45/45" in stdout  # one sphere, 45 sweeps
    assert "calibrations" in stdout


@pytest.mark.parametrize(
    "args",
    [
        ("run", QUICK, "--out", "/proc/uscal-out"),
        ("run", QUICK, "--out", "{tmp}/run", "--rrd", "/proc/uscal-out/run.rrd"),
        ("sweep", str(ROOT / "scenarios" / "robustness.yaml"), "--out", "/proc/uscal-out"),
        ("image", QUICK, "--out", "/proc/uscal-out/gallery"),
    ],
    ids=["run", "rrd", "sweep", "image"],
)
def test_an_output_place_that_cannot_hold_a_directory_is_one_line(capsys, tmp_path, args):
    """An output under a place that cannot hold a directory fails before any work, in one
    line naming it, and writes nothing anywhere."""
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    r = uscal_here(capsys, *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "/proc/uscal-out" in lines[0], r.stderr
    assert "cannot" in lines[0] and "Traceback" not in r.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_recording_of_fewer_frames_than_a_sweep_is_refused_before_any_work(capsys, tmp_path):
    """The recording logs whole sweeps: ``--rrd-frames`` below one sweep's frames would
    record no B-mode frame at all. It is one line before the run starts; 0 (none), a
    sweep's frames or ``--no-rrd`` are accepted."""
    r = uscal_here(capsys, "run", QUICK, "--out", str(tmp_path / "run"), "--rrd-frames", "20")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "--rrd-frames 20" in lines[0] and "21" in lines[0], r.stderr
    assert list(tmp_path.iterdir()) == []
