"""Plans that hold in another session (issue: a saved plan failed the next day): the
planner keeps every frame and transit clear in other sessions' taught pose and coarse
mount, the plan file keeps spares, and an acquisition replaces a sweep that does not
clear by the first spare that does — one line says which — instead of stopping."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from bench.acquire_sim import coarse_estimate, make_twin, teach_at
from bench.candidates import in_image, sweep_of, taught_target
from bench.config.plan_file import read_plan, read_spares, spare_poses, sphere_poses, write_plan
from bench.config.scenario import load_scenario
from bench.sessions import stage_rngs
from calib.acquisition.planning import SweepPose
from calib.acquisition.protocol import check_plan, clear_sweeps
from calib.errors import CollisionError, ScenarioError, UnreachablePoseError

from .conftest import QUICK
from .test_cli import uscal_here

ONE = ["protocol.spheres=[1]", "robot.dh_error_scale=0"]


def test_a_plan_file_keeps_its_spares_best_first(tmp_path):
    poses = {"sphere_1": (SweepPose((10.0, 0.0, 0.0), 0.0, 0.0),)}
    spares = {"sphere_1": (SweepPose((0.0, 20.0, 0.0), 2.0, 0.0), SweepPose((0.0, 0.0, 5.0), 0, 1))}
    path = write_plan(tmp_path / "plan.yaml", poses, {"criterion": "D"}, spares)
    assert read_plan(path) == poses and read_spares(path) == spares
    # A plan file without spares (as written before spares) has none.
    bare = write_plan(tmp_path / "bare.yaml", poses, {})
    assert read_spares(bare) == {} and "spares" not in yaml.safe_load(bare.read_text())
    doc = yaml.safe_load(path.read_text())
    doc["spares"]["sphere_2"] = doc["spares"]["sphere_1"]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ScenarioError, match="spares for sphere_2, which the plan does not scan"):
        read_spares(path)


@pytest.fixture(scope="module")
def session():
    """The twin of quick.yaml's sphere 1, taught; and candidate sweeps sorted into those
    that clear and those that do not, by the twin's own arm and scene."""
    scenario = load_scenario(QUICK, ONE)
    twin = make_twin(scenario)
    rngs = stage_rngs(scenario)
    coarse = coarse_estimate(twin.truth.T_ee_us, scenario.calibration, rngs["calibration"])
    sphere = taught_target(scenario, twin, coarse, "sphere_1", 0, rngs["protocol"])
    grid = [p for p in scenario.planning.candidates()[::7] if in_image(scenario, p)]
    ends = np.array([sweep_of(scenario, sphere, coarse, p)[[0, 10, 20]] for p in grid])
    room = twin.robot.clearances(ends.reshape(-1, 4, 4), 0.01).reshape(len(grid), 3).min(axis=1)
    # Clear sweeps, each at its own flange orientation (a plan of one orientation does
    # not determine T_ee_us), and sweeps that collide.
    turns = {p.rotation_deg: p for p, r in zip(grid, room, strict=True) if r >= 0.01}
    fine = list(turns.values())
    blocked = [p for p, r in zip(grid, room, strict=True) if r < 0]
    assert len(fine) >= 8 and len(blocked) >= 4
    return scenario, twin, sphere, coarse, fine, blocked


def _clear(session, poses, spares=()):
    scenario, twin, sphere, coarse, _, _ = session

    def check(sweep, _here):
        check_plan(twin.robot, [sweep])

    return clear_sweeps(
        "sphere_1", sphere.taught, coarse, scenario.protocol, check, poses=poses, spares=spares
    )


def test_a_sweep_that_does_not_clear_is_replaced_by_the_first_spare_that_does(session):
    *_, fine, blocked = session
    plan = [fine[0], blocked[0], fine[1]]
    sweeps, changed = _clear(session, plan, spares=[blocked[1], fine[2], fine[3]])
    assert [s.pose for s in sweeps] == [fine[0], fine[2], fine[1]]
    assert [s.pose_id for s in sweeps] == [0, 1, 2]  # the replacement takes the slot
    (r,) = changed
    assert (r.pose_id, r.spare, r.pose) == (1, 1, fine[2])
    assert r.line().startswith("sphere_1 sweep 1 replaced by spare 1 (turned")
    assert "would put" in r.line() or "cannot reach" in r.line()
    # What the acquisition then moves through clears, transits included.
    check_plan(session[1].robot, sweeps)


def test_without_a_spare_that_clears_the_sweep_is_left_out_not_the_acquisition(session):
    *_, fine, blocked = session
    sweeps, changed = _clear(session, [fine[0], blocked[0], fine[1], fine[2]], [blocked[1]])
    assert [s.pose for s in sweeps] == [fine[0], fine[1], fine[2]]
    assert [s.pose_id for s in sweeps] == [0, 2, 3]
    assert changed[0].spare is None and "left out" in changed[0].line()
    # A plan of which half would be left out does not suit the session: refused before
    # anything moves, the count said.
    with pytest.raises((CollisionError, UnreachablePoseError), match="2 of the 4 sweeps"):
        _clear(session, [blocked[0], fine[0], blocked[1], fine[1]])


def _run_with(plan, tmp_path, capsys):
    """`uscal run` of quick.yaml's sphere 1 with the plan file: the run and its metrics."""
    out = tmp_path / "out"
    r = uscal_here(
        capsys, "run", str(QUICK), "--out", str(out), *(f"--set={s}" for s in ONE),
        f"--set=protocol.plan={plan}",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    return r, json.loads((out / "metrics.json").read_text())


def test_uscal_run_says_which_sweep_it_replaced_and_calibrates(session, tmp_path, capsys):
    """End to end on the twin: a plan with a sweep that collides in this session runs
    through, one line naming the sweep, the reason and the spare, in the console and in
    metrics.json."""
    *_, fine, blocked = session
    plan = write_plan(
        tmp_path / "plan.yaml",
        {"sphere_1": (fine[0], blocked[0], *fine[1:6])},
        {},
        {"sphere_1": (blocked[1], fine[6])},
    )
    r, m = _run_with(plan, tmp_path, capsys)
    (line,) = [x for x in r.stdout.splitlines() if x.startswith("plan: ")]
    assert line.startswith("plan: sphere_1 sweep 1 replaced by spare 1 (turned")
    assert m["acquisition"]["sweeps"] == 7 and len(m["acquisition"]["replaced"]) == 1
    single = m["calibration"]["single"]
    # Seven arbitrary sweeps calibrate to the millimetre, within their own bound.
    assert single["true_error"]["image_mm"] < 1.0
    assert single["true_error"]["image_mm"] <= single["bound95"]["image_mm"]


def test_a_plan_of_one_orientation_is_rejected_not_handed_back(session, tmp_path, capsys):
    """Sweeps that all share one flange orientation do not determine T_ee_us's rotation:
    the fit stops anywhere (here metres off over the image), and the verdict says rejected,
    why and what to do, instead of a bound of kilometres marked suspect."""
    scenario, twin, sphere, coarse, *_ = session
    grid = [p for p in scenario.planning.candidates() if in_image(scenario, p)]
    ends = np.array([sweep_of(scenario, sphere, coarse, p)[[0, 10, 20]] for p in grid[:400]])
    room = twin.robot.clearances(ends.reshape(-1, 4, 4), 0.01).reshape(-1, 3).min(axis=1)
    turn = next(p.rotation_deg for p, r in zip(grid, room, strict=False) if r >= 0.01)
    same = [p for p, r in zip(grid, room, strict=False) if r >= 0.01 and p.rotation_deg == turn]
    assert len(same) >= 6
    plan = write_plan(tmp_path / "plan.yaml", {"sphere_1": tuple(same[:6])}, {})
    r, m = _run_with(plan, tmp_path, capsys)
    verdict = m["calibration"]["single"]["verdict"]
    assert verdict["status"] == "rejected"
    assert verdict["reasons"][0].startswith("the kept sweeps were taken from 1 flange orientation")
    assert "single-marker verdict: rejected: the kept sweeps" in " ".join(r.stdout.split())


@pytest.mark.slow
def test_a_plan_made_once_holds_in_twenty_new_sessions(tmp_path):
    """The issue's case: a 15-sweep plan of sphere 1 made in one session; twenty new
    sessions (seeds: their own coarse mount and taught pose) move through it with no
    sweep refused. The plan made without other sessions does not (the issue's seed 301
    stopped at sweep 4)."""
    from bench.jobs.plan_optimize import optimize_plan, plan_about

    def made(sets):
        # On the planner's coarser grid (what is tested is that the sweeps chosen clear in
        # other sessions, not how fine the grid they are chosen from is).
        grid = ["planning.rotation_step_deg=15", "planning.shift_step_mm=3"]
        scenario = load_scenario(QUICK, [*ONE, *grid, *sets])
        c = optimize_plan(scenario, 15, "D", 1)
        path = tmp_path / f"plan{len(sets)}.yaml"
        return write_plan(path, c.optimized.poses, plan_about(c, scenario), c.optimized.spares)

    def refused(plan, seed):
        scenario = load_scenario(QUICK, [*ONE, f"seed={seed}", f"protocol.plan={plan}"])
        twin = make_twin(scenario)
        rngs = stage_rngs(scenario)
        proto = scenario.protocol
        coarse = coarse_estimate(twin.truth.T_ee_us, scenario.calibration, rngs["calibration"])
        taught = teach_at(
            twin,
            twin.truth.landmarks_base["sphere_1"],
            proto.target_depth_mm * 1e-3,
            "taught",
            rngs["protocol"],
            proto.teaching_error_mm,
        )
        _, changed = clear_sweeps(
            "sphere_1",
            taught.T_base_ee,
            coarse,
            proto,
            lambda sweep, _here: check_plan(twin.robot, [sweep]),
            poses=sphere_poses(proto, "sphere_1"),
            spares=spare_poses(proto, "sphere_1"),
        )
        return len(changed)

    reused = made([])
    assert len(read_spares(reused)["sphere_1"]) == 10
    assert [refused(reused, seed) for seed in range(300, 320)] == [0] * 20
    this_session_only = made(["planning.session_draws=0", "planning.spares=0"])
    assert refused(this_session_only, 301) > 0
