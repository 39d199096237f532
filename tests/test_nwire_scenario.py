"""The scenarios of targets other than spheres (scenarios/nwire.yaml, wire.yaml,
cone_tip.yaml) are valid scenarios, their protocols check, the planner refuses them in
one line, writing nothing, and `uscal sweep` and `uscal budget` measure them."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import yaml

from bench.config.scenario import load_scenario

from .test_cli import uscal_here

ROOT = Path(__file__).resolve().parents[1]
NWIRE = str(ROOT / "scenarios" / "nwire.yaml")
SCENARIOS = {k: str(ROOT / "scenarios" / f"{k}.yaml") for k in ("nwire", "wire", "cone_tip")}
KIND = {"nwire": "nwire", "wire": "wire", "cone_tip": "cone"}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_the_scenario_is_valid_and_its_protocol_checks(capsys, name):
    r = uscal_here(capsys, "check", SCENARIOS[name])
    assert r.returncode == 0, r.stderr
    assert KIND[name] in r.stdout and "scenario is valid" in r.stdout
    r = uscal_here(capsys, "plan", SCENARIOS[name])
    assert r.returncode == 0, r.stderr


#: A coarse candidate grid and few other sessions: the planner's every step, in seconds.
COARSE_PLAN = [
    "--set", "planning.rotation_step_deg=15", "--set", "planning.shift_step_mm=5",
    "--set", "planning.session_draws=2", "--set", "planning.spares=2",
]  # fmt: skip
TARGET = {"wire": "wire", "nwire": "nwire", "cone_tip": "apex"}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_the_planner_plans_its_target_and_the_scenario_takes_the_plan(capsys, tmp_path, name):
    """`uscal plan --optimize` of a wire, N-wire or cone-tip scenario: sweeps about its
    one target, the plan file naming it, each sweep checked in the other sessions, with
    spares; the scenario takes the plan (`uscal check`), a sphere plan it refuses."""
    plan = tmp_path / "plan.yaml"
    args = ["plan", SCENARIOS[name], "--optimize", "--sweeps", "8", *COARSE_PLAN]
    r = uscal_here(capsys, *args, "--out", str(plan))
    assert r.returncode == 0, r.stderr
    doc = yaml.safe_load(plan.read_text())
    target = TARGET[name]
    assert list(doc["targets"]) == [target] and len(doc["targets"][target]) == 8
    assert len(doc["spares"][target]) == 2 and doc["checked_in_other_sessions"] == 2
    assert doc["markers"] == 1 and doc["calibration"].startswith(
        ("a single-wire", "an N-wire", "a cone")
    )
    p = doc["predicted"]
    assert 0 < p["image_mm_rms"] < 1 and 0 < p["rotation_deg_1sigma"] < 2
    assert p["robot_time_s"] < 0.5 * doc["paper_plan"]["robot_time_s"]
    if name != "cone_tip":  # a wire's echo needs the probe within the protocol's tilt
        tilt = load_scenario(SCENARIOS[name]).protocol.tilt_deg
        assert all(abs(s["rotation_xyz_deg"][0]) <= tilt for s in doc["targets"][target])
    r = uscal_here(capsys, "check", SCENARIOS[name], "--set", f"protocol.plan={plan}")
    assert r.returncode == 0, r.stderr


def test_a_sweep_mixing_spheres_and_other_targets_is_refused(capsys, tmp_path):
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(
        f"base: {SCENARIOS['wire']}\ngrid:\n  phantom.kind: [wire, spheres]\n", encoding="utf-8"
    )
    r = uscal_here(capsys, "sweep", str(sweep), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "sweep them in separate files" in r.stderr and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_sweep_over_a_wire_calibrates_each_point(capsys, tmp_path):
    """Each point finds and calibrates the wire as `uscal run` does: one row named after
    the target, its unused share of frames, its true error and verdict."""
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(
        # Sweeps of 7 frames (2 mm apart), as in the budget's test below.
        f"base: {SCENARIOS['wire']}\ngrid:\n  imaging.gain_db: [-6, 6]\n"
        "  protocol.frames_per_sweep: [7]\nseeds: [0]\n",
        encoding="utf-8",
    )
    r = uscal_here(capsys, "sweep", str(sweep), "--out", str(tmp_path / "out"), "--workers", "1")
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader((tmp_path / "out" / "results.csv").open()))
    assert [row["method"] for row in rows] == ["wire", "wire"]
    assert all(0 < float(row["calibration_image_mm"]) < 0.3 for row in rows)
    assert all(float(row["rejected_fraction"]) < 0.1 for row in rows)
    assert all(row["calibration_verdict"] == "accepted" for row in rows)


@pytest.mark.slow
def test_the_budget_measures_a_wire_scenario(capsys, tmp_path):
    """One source, one seed: the error-free rig, the scenario, the source alone and all
    but it, each a whole run of the single wire, its true error in the budget."""
    out = tmp_path / "budget"
    r = uscal_here(
        capsys, "budget", SCENARIOS["wire"], "--sources", "print_tolerance",
        "--seeds", "1", "--workers", "1", "--out", str(out),
        # Sweeps of 7 frames (2 mm apart): every frame gives the wire's dots, so the
        # calibration stays well posed at a third of the frames.
        "--set", "protocol.frames_per_sweep=7",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader((out / "budget.csv").open()))
    assert len(rows) == 4 and not any(row["error"] for row in rows), rows
    image = [float(row["image_mm"]) for row in rows]
    assert all(0 < v < 0.3 for v in image)  # the single wire's error, every source off or on
    assert "single marker or the target" in (out / "budget.md").read_text()
