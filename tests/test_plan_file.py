"""Plan files (bench.config.plan_file) and `uscal plan --optimize`: the file round-trips,
is validated like every scenario key (one line naming the file and the entry), is found
beside the scenario that names it, and the optimized plan beats the paper's as
predicted, with its robot time as the twin's clock will count it."""

from __future__ import annotations

import json

import pytest
import yaml

from bench.config.plan_file import read_plan, write_plan
from bench.config.scenario import load_scenario, sweeps_per_target
from calib.acquisition.planning import SweepPose
from calib.errors import ScenarioError

from .conftest import QUICK
from .test_cli import uscal, uscal_here

POSES = {
    "sphere_1": (SweepPose((10.0, -20.0, 0.0), 4.0, -2.0), SweepPose((0.0, 0.0, 30.0), 0.0, 6.0))
}


def test_a_plan_file_round_trips(tmp_path):
    path = write_plan(tmp_path / "plan.yaml", POSES, {"criterion": "D"})
    assert read_plan(path) == POSES
    doc = yaml.safe_load(path.read_text())
    assert doc["kind"] == "uscal-plan" and doc["criterion"] == "D"
    assert doc["targets"]["sphere_1"][0] == {
        "rotation_xyz_deg": [10.0, -20.0, 0.0],
        "lateral_mm": 4.0,
        "axial_mm": -2.0,
    }


def test_a_plan_file_of_spheres_only_still_reads_and_wires_are_targets(tmp_path):
    """Files written before other targets had their sweeps under ``spheres``; a plan
    about a wire, an N-wire phantom or a cone's tip names that target."""
    path = write_plan(tmp_path / "plan.yaml", POSES, {})
    doc = yaml.safe_load(path.read_text())
    doc["spheres"] = doc.pop("targets")
    path.write_text(yaml.safe_dump(doc))
    assert read_plan(path) == POSES
    for name in ("wire", "nwire", "apex"):
        wired = {name: POSES["sphere_1"]}
        assert read_plan(write_plan(tmp_path / f"{name}.yaml", wired, {})) == wired


@pytest.mark.parametrize(
    "body,message",
    [
        ("kind: something\n", "not a plan file"),
        ("kind: uscal-plan\nspheres: {}\n", "no sweeps"),
        ("kind: uscal-plan\nspheres:\n  ball: [{}]\n", "spheres.ball"),
        (
            "kind: uscal-plan\ntargets:\n  wires: [{}]\n",
            "targets.wires.*sphere_N, wire, nwire, apex",
        ),
        (
            "kind: uscal-plan\nspheres:\n  sphere_1:\n    - {rotation_xyz_deg: [0, 0, 90], "
            "lateral_mm: 0, axial_mm: 0}\n",
            r"spheres.sphere_1\[0\].rotation_xyz_deg",
        ),
        (
            "kind: uscal-plan\nspheres:\n  sphere_1:\n    - {rotation_xyz_deg: [0, 0], "
            "lateral_mm: 0, axial_mm: 0}\n",
            "three angles",
        ),
        (
            "kind: uscal-plan\nspheres:\n  sphere_1:\n    - {rotation_xyz_deg: [0, 0, 0], "
            "lateral_mm: 0}\n",
            "exactly these keys",
        ),
    ],
)
def test_a_broken_plan_file_is_one_error_naming_the_entry(tmp_path, body, message):
    path = tmp_path / "plan.yaml"
    path.write_text(body)
    with pytest.raises(ScenarioError, match=message) as info:
        read_plan(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_scenario_finds_its_plan_beside_it_and_checks_it(tmp_path):
    write_plan(tmp_path / "plan.yaml", POSES, {})
    scenario = tmp_path / "s.yaml"
    scenario.write_text(QUICK.read_text() + "\n")
    text = yaml.safe_load(scenario.read_text())
    text["protocol"] = {**text.get("protocol", {}), "spheres": [1], "plan": "plan.yaml"}
    scenario.write_text(yaml.safe_dump(text))
    s = load_scenario(scenario, check_reach=False)
    assert s.protocol.plan == str(tmp_path / "plan.yaml") and sweeps_per_target(s) == 2
    # The protocol's spheres must be the plan's.
    with pytest.raises(ScenarioError, match="the plan has sweeps for sphere_1; the protocol"):
        load_scenario(scenario, ["protocol.spheres=[1, 2]"], check_reach=False)
    # A sweep that puts the sphere outside this image is refused before anything runs.
    write_plan(tmp_path / "plan.yaml", {"sphere_1": (SweepPose((0, 0, 0), 14.0, 0.0),)}, {})
    with pytest.raises(ScenarioError, match="sweep 0 of sphere_1 puts the sphere"):
        load_scenario(scenario, check_reach=False)


def test_plan_mistakes_on_the_command_line_are_one_line(tmp_path, capsys):
    r = uscal_here(capsys, "run", str(QUICK), "--set", f"protocol.plan={tmp_path / 'none.yaml'}")
    assert r.returncode == 2 and "none.yaml" in r.stderr and r.stderr.count("\n") == 1
    r = uscal("plan", str(QUICK), "--optimize", "--sweeps", "0")
    assert r.returncode == 2 and "--sweeps: '0' is not a whole number ≥ 1" in r.stderr
    r = uscal_here(
        capsys, "plan", str(QUICK), "--set", "protocol.spheres=[1]", "--optimize", "--markers", "3"
    )
    assert r.returncode == 2 and "three-marker plans need three" in r.stderr
    # A wire phantom has one target: no three-marker plan of it.
    wire = QUICK.parent.parent / "scenarios" / "wire.yaml"
    r = uscal_here(capsys, "plan", str(wire), "--optimize", "--markers", "3")
    assert r.returncode == 2 and "a wire phantom has one target" in r.stderr
    assert r.stderr.count("\n") == 1
    # A plan of spheres does not fit a wire scenario.
    write_plan(tmp_path / "spheres.yaml", POSES, {})
    r = uscal_here(
        capsys, "check", str(wire), "--set", f"protocol.plan={tmp_path / 'spheres.yaml'}"
    )
    assert r.returncode == 2 and "a plan made for this phantom" in r.stderr


@pytest.mark.slow
def test_uscal_plan_optimize_writes_a_plan_that_beats_the_papers(tmp_path):
    plan = tmp_path / "plan.yaml"
    r = uscal(
        "plan", str(QUICK), "--set", "protocol.spheres=[1]", "--optimize", "--sweeps", "15",
        "--set", "planning.rotation_step_deg=15", "--set", "planning.shift_step_mm=3",
        "--set", "planning.session_draws=6", "--out", str(plan),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc = yaml.safe_load(plan.read_text())
    assert len(doc["targets"]["sphere_1"]) == 15 == len(read_plan(plan)["sphere_1"])
    opt, paper = doc["predicted"], doc["paper_plan"]
    assert paper["sweeps"] == 45
    # A third of the sweeps: better determined, in at most 40 % of the robot time.
    assert opt["rotation_deg_1sigma"] < paper["rotation_deg_1sigma"]
    assert opt["image_mm_rms"] < paper["image_mm_rms"]
    assert opt["robot_time_s"] <= 0.4 * paper["robot_time_s"]
    # The paper's plan's predicted time is the twin's session clock (≈ 350 s a sphere).
    assert paper["robot_time_s"] == pytest.approx(349.5, abs=10)
    assert "optimized" in r.stdout and "paper" in r.stdout
    json.dumps(doc)  # plain data only


@pytest.mark.slow
def test_a_planned_run_on_the_twin_takes_the_planned_time_and_calibrates(tmp_path):
    from bench.jobs.plan_optimize import optimize_plan, plan_about
    from bench.jobs.single import run
    from bench.progress import reporting

    sets = ["protocol.spheres=[1]", "seed=3"]
    # Planned on the coarser grid with fewer other sessions, as the test above plans
    # (what is tested here is that the twin carries the plan out).
    coarse = [
        "planning.rotation_step_deg=15",
        "planning.shift_step_mm=3",
        "planning.session_draws=6",
    ]
    scenario = load_scenario(QUICK, [*sets, *coarse])
    c = optimize_plan(scenario, 15, "D", 1)
    plan = write_plan(tmp_path / "plan.yaml", c.optimized.poses, plan_about(c, scenario))
    with reporting(None):
        m = run(load_scenario(QUICK, [*sets, f"protocol.plan={plan}"])).metrics
    assert m["acquisition"]["sweeps"] == 15 and m["localization"]["n_rejected"] == 0
    # The twin's controller spends the time the plan predicted (moves, settles, grabs).
    assert m["acquisition"]["robot_time_s"] == pytest.approx(c.optimized.robot_time_s, rel=0.03)
    # Fifteen sweeps of one sphere calibrate the image to a third of a millimetre, and
    # the run's own 95 % bounds hold the truth. The rotation is the least determined:
    # over seeds 3-8 of this plan 0.13-0.82°, its bound 0.8-1.1° (seed 3 gave under 0.6°
    # with the same code in another environment, 0.82° in this one: a limit below the
    # bound, set on one seed, is a claim the run itself does not make).
    single = m["calibration"]["single"]
    err, bound = single["true_error"], single["bound95"]
    assert err["image_mm"] <= 0.3
    for key in ("rotation_deg", "translation_mm", "image_mm"):
        assert err[key] <= bound[key], key
    assert bound["rotation_deg"] <= 1.2 and err["rotation_deg"] <= 1.0


@pytest.mark.slow
def test_the_sequential_acquisition_stops_when_the_predicted_bounds_are_reached():
    from bench.jobs.single import run
    from bench.progress import reporting
    from bench.sequential import StopRule

    scenario = load_scenario(QUICK, ["protocol.spheres=[1]", "seed=2"])
    with reporting(None):
        # The precision the paper's 45 sweeps predict (0.381° / 0.130 mm, planning's
        # noise model): the sequential mode reaches it with far fewer.
        m = run(scenario, until=StopRule(0.38, 0.13)).metrics
    seq = m["acquisition"]["sequential"]["sphere_1"]
    assert seq["reached"] and seq["predicted_rotation_deg"] <= 0.38
    assert seq["predicted_translation_mm"] <= 0.13
    # It stopped at the first sweep that reached them, well before the paper's 45.
    history = seq["history"]
    assert all(h["rotation_deg"] > 0.38 or h["translation_mm"] > 0.13 for h in history[:-1])
    assert m["acquisition"]["sweeps"] == seq["sweeps"] < 25
    assert m["acquisition"]["robot_time_s"] < 0.6 * 349.5
    err = m["calibration"]["single"]["true_error"]
    # The truth within twice the 1 σ predicted where the acquisition stopped. (A fixed
    # 0.5° stood here, 1.3 σ: which sweeps the sequential mode picks turns on last-bit
    # differences between CPUs' vector units; this run stops after 10 sweeps 0.53° off
    # with AVX-512 kernels, after 11 sweeps 0.49° and 0.19 mm off with AVX2 ones.)
    assert err["rotation_deg"] <= 2 * seq["predicted_rotation_deg"]
    assert err["translation_mm"] <= 2 * seq["predicted_translation_mm"]


def test_the_sequential_acquisition_is_one_acquisition(capsys):
    r = uscal_here(capsys, "run", "--until-rotation-deg", "0.2", "--out", "/nonexistent/x")
    assert r.returncode == 2 and "the sequential acquisition is one acquisition" in r.stderr
