"""``uscal plan --optimize``: choose the sweeps that determine ``T_ee_us`` best for the
robot time (:mod:`calib.acquisition.planning`), where the arm can actually put the probe.

For each sphere of the plan: teach the nominal pose (emulated as the session's
acquisition teaches it, its teaching error included: a rig plans from its taught pose),
lay the scenario's candidate sweeps about it (:mod:`bench.candidates`: in the image by
the margin, reachable with the clearance from the tank and the phantom), and choose N of
them for the information of the joint problem (one sphere: its centre unknown; three
spheres: the phantom's pose unknown, the layout the CAD's within the print tolerance).
Every frame of the chosen sweeps, and every transit between them in acquisition order,
must keep the clearance too, each pose solved from the one before as the controller
moves (from the taught joint angles); a sweep that does not is replaced. A plan is made
to be reused: the same check runs in ``planning.session_draws`` other sessions, each
with the taught pose and the coarse mount another day may bring (the stated teaching
error and coarse-mount error, drawn as the twin draws a session's), and the plan keeps
``planning.spares`` spare sweeps per sphere (the next-best, clear in the same sessions)
that an acquisition puts in place of a sweep that no longer clears
(:func:`calib.acquisition.protocol.clear_sweeps`). The paper's plan is scored the same way beside
it, and both are timed as the twin's controller would move (trapezoidal profiles at the
configured speeds, settle and grab per frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.planning import (
    Candidates,
    Criterion,
    PlanPrediction,
    SweepPose,
    bias_covariance,
    image_metric,
    predict,
    select_sweeps,
    sweep_scores,
)
from calib.acquisition.protocol import PlannedSweep, check_plan, default_poses, plan_sweeps
from calib.errors import UscalError
from twin.arm_errors import trapezoid_time_s
from twin.robot import RobotConfig

from ..acquire_sim import coarse_estimate, make_twin
from ..candidates import (
    NOT_CLEAR,
    PlanTarget,
    candidate_set,
    candidate_sweeps,
    clear,
    observations,
    path_clear,
    sweep_of,
    taught_target,
)
from ..config.geometry import TARGET_PHANTOMS, acquisition_targets
from ..config.method import image_points
from ..config.scenario import Scenario
from ..sessions import PLAN_SESSIONS_KEY, stage_rngs, stream

#: Sweeps of each sphere a three-marker plan keeps at least: the multi-marker fit needs
#: every sphere seen, and its outlier test a handful of views of each.
MIN_SWEEPS_PER_SPHERE = 5

__all__ = ["PlanChoice", "PlanComparison", "optimize_plan", "plan_about", "plan_time_s"]

Array = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PlanChoice:
    """A plan (its sweeps about each target, in acquisition order) and what it
    predicts; ``candidates`` how many sweeps it was chosen from, and why the others
    were left out."""

    poses: dict[str, tuple[SweepPose, ...]]
    prediction: PlanPrediction
    robot_time_s: float
    candidates: int = 0
    left_out: dict[str, int] | None = None
    spares: dict[str, tuple[SweepPose, ...]] | None = None
    sessions: int = 0  # other sessions every sweep and spare was checked in

    @property
    def n_sweeps(self) -> int:
        return sum(len(v) for v in self.poses.values())


@dataclass(frozen=True, eq=False)
class PlanComparison:
    """The optimized plan beside the paper's, for the same spheres and noise."""

    optimized: PlanChoice
    paper: PlanChoice
    criterion: Criterion
    spheres: list[str]  # the targets planned (spheres, or the one wire/cone target)
    calibration: str = ""  # what the plan is chosen for, as the reader meets it
    noise: str = ""  # the noise it is chosen for, in words


_MAX_REPLAN_ROUNDS = 60  # see optimize_plan


def noise_about(scenario: Scenario, markers: int) -> tuple[str, str, dict]:
    """What a plan of ``scenario`` is chosen for: the calibration (in words), the noise
    model (in words) and the same for the plan file."""
    p = scenario.planning
    arm = f"the arm's {p.pose_noise_mm:g} mm"
    kind = scenario.phantom.kind

    def axes(v) -> str:
        return " / ".join(f"{x:g}" for x in v)

    if kind in ("wire", "nwire"):
        what = "a single-wire" if kind == "wire" else "an N-wire"
        return (
            f"{what} calibration (phantom pose and pixel scale unknown)",
            f"a dot's noise {axes(p.dot_noise_mm)} mm per frame and "
            f"{axes(p.dot_sweep_noise_mm)} mm shared by a sweep's dots (lateral / axial, "
            f"1 σ), {arm}",
            {
                "dot_noise_mm": list(p.dot_noise_mm),
                "dot_sweep_noise_mm": list(p.dot_sweep_noise_mm),
            },
        )
    if kind == "cone":
        return (
            "a cone-tip calibration (the tip's position unknown)",
            f"a tip's noise {axes(p.cone_tip_noise_mm)} mm per sweep (lateral / axial / "
            f"elevation, 1 σ), {arm}",
            {"cone_tip_noise_mm": list(p.cone_tip_noise_mm)},
        )
    return (
        ("three-marker" if markers >= 3 else "single-marker")
        + " calibration, fitted as calib.calibration.markers fits",
        f"localization noise {axes(p.localization_noise_mm)} mm (lateral / axial / "
        f"elevation, 1 σ), {arm}",
        {"localization_noise_mm": list(p.localization_noise_mm)},
    )


def plan_time_s(plan: Sequence[PlannedSweep], robot: RobotConfig, start: Array) -> float:
    """Robot time of planned sweeps, in order, from ``start``: a linear move to every
    pose at the controller's tool speed and acceleration (its turn at the joint limits)
    and the settle, and a grab at every frame — the twin's session clock
    (:class:`twin.robot.SimRobot`)."""
    moves = [T for s in plan for T in (*s.approach, *s.T_base_ee)]
    poses = np.array(moves)
    previous = np.concatenate([np.asarray(start, dtype=float)[None], poses[:-1]])
    total = 0.0
    for T0, T1 in zip(previous, poses, strict=True):
        path_mm = 1e3 * float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        turn_deg = float(np.degrees(se3.rotation_angle(T0, T1)))
        total += max(
            trapezoid_time_s(path_mm, robot.tool_speed_mm_s, robot.tool_acceleration_mm_s2),
            trapezoid_time_s(turn_deg, robot.joint_speed_deg_s, robot.joint_acceleration_deg_s2),
        )
    frames = sum(len(s.T_base_ee) for s in plan)
    return total + len(moves) * robot.settle_s + frames * robot.grab_s


def _ordered(chosen: list, start: Array) -> list:
    """The chosen (index, sphere, pose, commands), sphere by sphere, each sphere's by
    nearest next start (the move from one sweep's last frame to the next's first is what
    the order changes)."""
    out = []
    for name in dict.fromkeys(c[1].name for c in chosen):
        todo = [c for c in chosen if c[1].name == name]
        here = start
        while todo:
            k = int(np.argmin([np.linalg.norm(c[3][0][:3, 3] - here[:3, 3]) for c in todo]))
            here = todo[k][3][-1]
            out.append(todo.pop(k))
        start = here
    return out


@dataclass(frozen=True, eq=False)
class OtherSession:
    """Another session a plan must hold in: each sphere's taught pose and the coarse
    mount that day, as the pipeline's commands would be made from them."""

    taught: dict[str, Array]
    coarse: Array


def other_sessions(scenario: Scenario, spheres: Sequence[PlanTarget], coarse: Array, n: int):
    """``n`` sessions drawn as the twin draws a session's (:mod:`bench.acquire_sim`):
    the taught pose off this one's by the difference of two teaching errors
    (``protocol.teaching_error_mm`` 1 σ each), the coarse mount off this one's by the
    difference of two coarse-mount errors (± ``calibration.initial_error_mm / _deg``
    each). Only stated settings enter, never the truth."""
    rng = stream(scenario.seed, PLAN_SESSIONS_KEY)
    sigma = np.sqrt(2.0) * scenario.protocol.teaching_error_mm * 1e-3
    out = []
    for _ in range(n):
        ours, theirs = (coarse_estimate(np.eye(4), scenario.calibration, rng) for _ in range(2))
        miss = {s.name: rng.normal(0.0, sigma, 3) for s in spheres}
        taught = {s.name: se3.make(np.eye(3), miss[s.name]) @ s.taught for s in spheres}
        out.append(OtherSession(taught, coarse @ se3.invert(ours) @ theirs))
    return out


def _unclear_in(scenario, twin, sessions, s: PlanTarget, poses: Sequence[SweepPose]) -> set[int]:
    """Indices of ``poses`` (one sphere's sweeps, in acquisition order with their
    transits) that do not keep the clearance on the way in one of ``sessions``."""
    proto = scenario.protocol
    bad: set[int] = set()
    for o in sessions:
        steps = plan_sweeps(s.name, o.taught[s.name], o.coarse, proto, poses=list(poses))
        owner = [k for k, st in enumerate(steps) for _ in (*st.approach, *st.T_base_ee)]
        way = np.array([T for st in steps for T in (*st.approach, *st.T_base_ee)])
        ok = path_clear(scenario, twin, way, s.taught_q)
        bad |= {owner[i] for i in np.flatnonzero(~ok)}
    return bad


def _clear_elsewhere(scenario, twin, sessions, found):
    """``admissible(k)`` of :func:`calib.acquisition.planning.select_sweeps`: candidate
    ``k``'s first, middle and last frames keep the clearance in every other session
    (asked of the few candidates the selection would take, not of all of them;
    remembered)."""
    need = scenario.planning.clearance_mm * 1e-3
    memo: dict[int, bool] = {}

    def ends(s: PlanTarget, o: OtherSession, pose: SweepPose) -> Array:
        return sweep_of(scenario, replace(s, taught=o.taught[s.name]), o.coarse, pose, 3)

    def admissible(k: int) -> bool:
        if k not in memo:
            s, pose, _ = found[k]
            memo[k] = True
            for batch in range(0, len(sessions), 6):  # most that fail, fail early
                T = np.array([ends(s, o, pose) for o in sessions[batch : batch + 6]])
                if np.any(twin.robot.clearances(T.reshape(-1, 4, 4), need + 1e-3) < need):
                    memo[k] = False
                    break
        return memo[k]

    return admissible


def _spares(
    scenario, twin, spheres, sessions, found, cands: Candidates, chosen, criterion, M, admissible
) -> dict[str, tuple[SweepPose, ...]]:
    """Per sphere, ``planning.spares`` candidates best first: by what each adds to the
    plan (:func:`calib.acquisition.planning.sweep_scores`; a spare stands in for one sweep, not
    beside the others), every frame clear here and in the other sessions."""
    want = scenario.planning.spares
    out: dict[str, tuple[SweepPose, ...]] = {}
    if not want:
        return out
    ranked = np.argsort(-sweep_scores(cands, chosen, criterion=criterion, M=M))
    taken = set(chosen)
    for s in spheres:
        kept: list[int] = []
        for k in (int(k) for k in ranked):
            if len(kept) == want:
                break
            if k in taken or found[k][0].name != s.name:
                continue
            if (
                admissible(k)
                and clear(scenario, twin, found[k][2])
                and not _unclear_in(scenario, twin, sessions, s, [found[k][1]])
            ):
                kept.append(k)
        if kept:
            out[s.name] = tuple(found[k][1] for k in kept)
    return out


def optimize_plan(
    scenario: Scenario, n_sweeps: int, criterion: Criterion = "D", markers: int | None = None
) -> PlanComparison:
    """Choose ``n_sweeps`` sweeps (in all) for single-marker calibration on the first
    sphere (``markers`` 1) or three-marker calibration on the first three (3; default:
    3 when the protocol scans three or more spheres) and score the paper's plan beside
    them (see the module docstring)."""
    proto = scenario.protocol
    if scenario.phantom.kind in TARGET_PHANTOMS:
        # One target (the wires' centre or the cone's tip): the phantom's pose is unknown
        # whatever the plan, as the fit estimates it.
        if markers not in (None, 1):
            raise UscalError(
                f"--markers {markers}: a {scenario.phantom.kind} phantom has one target to "
                "sweep about; plan it with --markers 1 (or without --markers)"
            )
        markers, names = 1, acquisition_targets(scenario.phantom.kind, proto)
    else:
        if markers is None:
            markers = 3 if len(proto.spheres) >= 3 else 1
        if markers == 3 and n_sweeps < 3 * MIN_SWEEPS_PER_SPHERE:
            raise UscalError(
                f"--sweeps {n_sweeps}: a three-marker plan needs at least "
                f"{3 * MIN_SWEEPS_PER_SPHERE} ({MIN_SWEEPS_PER_SPHERE} of each sphere)"
            )
        if markers == 3 and len(proto.spheres) < 3:
            raise UscalError(
                f"--markers 3: the protocol scans {len(proto.spheres)} sphere(s); "
                "three-marker plans need three (protocol.spheres)"
            )
        names = [f"sphere_{i}" for i in proto.spheres[:markers]]
    twin = make_twin(scenario)
    rngs = stage_rngs(scenario)
    coarse = coarse_estimate(twin.truth.T_ee_us, scenario.calibration, rngs["calibration"])
    spheres = [
        taught_target(scenario, twin, coarse, name, k, rngs["protocol"])
        for k, name in enumerate(names)
    ]
    M = image_metric(coarse, image_points(scenario))
    bias = bias_covariance(coarse, scenario.planning.localization_bias_mm)
    start = spheres[0].taught
    multi = markers == 3

    paper, _ = candidate_sweeps(
        scenario, twin, spheres, coarse,
        lambda s: default_poses(proto), check=False,
    )  # fmt: skip
    paper_pred = predict(
        observations(scenario, coarse, spheres, paper, multi, twin),
        range(len(paper)),
        M,
        bias=bias,
    )
    paper_plan = [p for s in spheres for p in plan_sweeps(s.name, s.taught, coarse, proto)]
    paper_choice = PlanChoice(
        {s.name: tuple(default_poses(proto)) for s in spheres},
        paper_pred,
        plan_time_s(paper_plan, scenario.robot, start),
    )

    dense = candidate_set(scenario)
    found, left = candidate_sweeps(scenario, twin, spheres, coarse, lambda s: dense, check=True)
    if not found:
        raise UscalError(
            "no candidate sweep keeps the target in the image and is reachable without a "
            f"collision ({left}); widen the image or lower planning.image_margin_mm"
        )
    sessions = other_sessions(scenario, spheres, coarse, scenario.planning.session_draws)
    this = OtherSession({s.name: s.taught for s in spheres}, coarse)
    clear_elsewhere = _clear_elsewhere(scenario, twin, sessions, found)
    refused: set[int] = set()  # chosen once, then found not to clear on the way

    def admissible(k: int) -> bool:
        return k not in refused and clear_elsewhere(k)

    cands = observations(scenario, coarse, spheres, found, multi, twin)
    least = MIN_SWEEPS_PER_SPHERE if multi else 0
    # Replace chosen sweeps that fail the frame-by-frame check. A sweep refused on the way
    # is often followed by a neighbour with the same transit, so this can take a few dozen
    # rounds (24 for quick.yaml's sphere 1 with the A criterion in one session, where 20
    # rounds gave up on a plan that exists); each round costs seconds, a refusal a user.
    for _ in range(_MAX_REPLAN_ROUNDS):
        try:
            chosen_idx = select_sweeps(
                cands,
                n_sweeps,
                criterion=criterion,
                M=M,
                min_per_target=least,
                admissible=admissible,
            )
        except ValueError as e:
            raise UscalError(
                f"no plan of {n_sweeps} sweeps keeps its clearance in the other sessions "
                f"({e}); lower planning.clearance_mm or planning.session_draws, or ask for "
                "fewer sweeps"
            ) from None
        # Every frame from the taught joint angles, as the acquisition checks the plan
        # before it moves (calib.acquisition.protocol.check_plan) ...
        bad = {k for k in dict.fromkeys(chosen_idx) if not clear(scenario, twin, found[k][2])}
        if not bad:
            # ... and along the way it then moves: in acquisition order, with the
            # transits between sweeps, each sphere's moves from its taught joint angles;
            # every pose keeps the clearance on that way (the sweep is replaced if not).
            # The same in the other sessions the plan is made for.
            ordered = _ordered([(k, *found[k]) for k in chosen_idx], start)
            planned = []
            for s in spheres:
                mine = [o for o in ordered if o[1].name == s.name]
                if not mine:
                    continue
                poses_s = [o[2] for o in mine]
                unclear = _unclear_in(scenario, twin, [this, *sessions], s, poses_s)
                bad |= {mine[i][0] for i in unclear}
                planned += plan_sweeps(s.name, s.taught, coarse, proto, poses=poses_s)
        if not bad:
            break
        left[NOT_CLEAR] += len(bad)
        refused |= bad
    else:
        raise UscalError(
            f"could not find a plan whose every pose is reachable and clear in "
            f"{_MAX_REPLAN_ROUNDS} rounds ({len(refused)} sweeps refused on the way); lower "
            "planning.clearance_mm or planning.session_draws, or ask for fewer sweeps"
        )
    prediction = predict(cands, chosen_idx, M, bias=bias)
    poses: dict[str, tuple[SweepPose, ...]] = {
        s.name: tuple(o[2] for o in ordered if o[1].name == s.name) for s in spheres
    }
    check_plan(twin.robot, planned)  # every pose, transits included, in order
    spares = _spares(
        scenario, twin, spheres, sessions, found, cands, chosen_idx, criterion, M, admissible
    )
    optimized = PlanChoice(
        {k: v for k, v in poses.items() if v},
        prediction,
        plan_time_s(planned, scenario.robot, start),
        len(found) - len(refused),
        left,
        spares,
        len(sessions),
    )
    what, noise, _ = noise_about(scenario, markers)
    return PlanComparison(optimized, paper_choice, criterion, names, what, noise)


def plan_about(comparison: PlanComparison, scenario: Scenario) -> dict:
    """What a plan file records for its reader: how it was chosen and what it predicts
    beside the paper's plan."""

    def figures(c: PlanChoice) -> dict:
        p = c.prediction
        return {
            "sweeps": c.n_sweeps,
            "rotation_deg_1sigma": round(p.rotation_deg, 4),
            "translation_mm_1sigma": round(p.translation_mm, 4),
            "image_mm_rms": round(p.image_mm, 4),
            "condition_number": round(p.condition_number, 1),
            "robot_time_s": round(c.robot_time_s, 1),
        }

    return {
        "scenario": scenario.source,
        "criterion": comparison.criterion,
        "markers": len(comparison.spheres),
        "calibration": comparison.calibration,
        **noise_about(scenario, len(comparison.spheres))[2],
        "pose_noise_mm": scenario.planning.pose_noise_mm,
        "clearance_mm": scenario.planning.clearance_mm,
        "checked_in_other_sessions": comparison.optimized.sessions,
        "predicted": figures(comparison.optimized),
        "paper_plan": figures(comparison.paper),
    }
