"""``uscal acquire``: the sphere protocol on a real rig (a UR through RTDE and a frame
grabber), recorded sweep by sweep into a dataset (:mod:`calib.files.dataset`).

The same protocol code as the twin's (:func:`calib.acquisition.protocol.plan_sweeps`,
:func:`calib.acquisition.protocol.acquire`) drives :class:`hw.robot.URRobot` and
:class:`hw.grabber.FrameGrabber`. Before anything moves the whole plan is checked
(workspace box, step between consecutive poses; a sweep that does not pass is
replaced by a spare of the plan file, one line saying which), ``--dry-run`` stops
there, and the operator confirms the first motion. Each finished sweep is on disk at once; when the
robot stops, the connection drops or the grabber goes quiet, the acquisition ends with
one message and ``--resume`` continues with the sweeps still missing.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.acquisition.planning import Candidates, bias_covariance
from calib.acquisition.protocol import (
    PlannedSweep,
    Replacement,
    acquire,
    clear_sweeps,
    default_poses,
    plan_sweeps,
    touch_plan,
    transit,
)
from calib.dh import NOMINAL_TABLES, forward_kinematics
from calib.errors import (
    FrameGrabberError,
    RobotConnectionError,
    RobotSetupError,
    RobotStoppedError,
    UscalError,
)
from calib.files.dataset import DatasetWriter
from calib.localize import LocalizerConfig, localize_sphere
from calib.pipeline import axial_scale as axial_scale_of
from calib.records import Touch

from .config.hw import HwConfig
from .config.plan_file import spare_poses, sphere_poses
from .progress import report
from .sequential import Chooser, StopRule

_HOLD_S = 0.3  # s between the operator's "done" and the touch reading

__all__ = [
    "AcquisitionSummary",
    "Operator",
    "acquire_dataset",
    "console_operator",
    "dashboard_operator",
]


@dataclass(frozen=True)
class AcquisitionSummary:
    directory: Path
    planned: int
    acquired: int
    skipped: int
    dry_run: bool
    seconds: float


def _plans(
    robot, cfg: HwConfig, taught_T: dict[str, np.ndarray]
) -> tuple[list[PlannedSweep], list[Replacement]]:
    """The sweeps as they will be visited, every pose checked (workspace box, step from
    the pose before it; each sphere's sweeps start from its taught pose, transits
    included); a sweep that does not pass is replaced by a spare of the plan file
    (:func:`calib.acquisition.protocol.clear_sweeps`)."""

    def check(sweep: PlannedSweep, here: np.ndarray) -> None:
        previous = here
        moves = [(f"transit {j}", T) for j, T in enumerate(sweep.approach)]
        moves += [(f"frame {j}", T) for j, T in enumerate(sweep.T_base_ee)]
        for what, T in moves:
            label = f"{sweep.target} sweep {sweep.pose_id} {what}"
            robot.check_pose(T, label)
            robot.check_step(previous, T, label)
            previous = T

    plan: list[PlannedSweep] = []
    replaced: list[Replacement] = []
    for target, T in taught_T.items():
        sweeps, changed = clear_sweeps(
            target,
            T,
            cfg.rig.T_ee_us_coarse,
            cfg.protocol,
            check,
            poses=sphere_poses(cfg.protocol, target),
            spares=spare_poses(cfg.protocol, target),
        )
        plan += sweeps
        replaced += changed
    return plan, replaced


class Operator:
    """Who hand-guides the arm for the touches: ``tell(action, detail)`` returns once the
    operator has done it. ``action`` is "mount" (detail: the tool) or "touch" (detail:
    (vertex, index, description)). :func:`console_operator` asks a person at the
    terminal; :func:`dashboard_operator` asks the loopback rig's emulated operator."""

    def __init__(self, tell: Callable[[str, Any], None]) -> None:
        self.tell = tell

    def place(self, vertex: str, index: int, R_base_ee: np.ndarray) -> None:
        """calib.acquisition.protocol.TouchGuide: the stylus tip onto a vertex, at about the planned
        orientation (the record is whatever the controller then reports)."""
        axis = R_base_ee[:3, 2]  # the stylus runs along the flange z axis
        tilt = np.degrees(np.arccos(np.clip(-axis[2], -1.0, 1.0)))
        azimuth = np.degrees(np.arctan2(-axis[1], -axis[0])) % 360
        how = f"stylus tilted {tilt:.0f}° with its top towards {azimuth:.0f}°"
        self.tell("touch", (vertex, index, how))


def console_operator(ask: Callable[[str], None]) -> Operator:
    """Prompts at the terminal; ``ask(message)`` returns when the person presses Enter."""

    def tell(action: str, detail: Any) -> None:
        if action == "mount":
            ask(f"Mount the {detail} on the flange, then press Enter")
        else:
            vertex, index, how = detail
            ask(
                f"Hand-guide the stylus tip onto {vertex} (touch {index + 1}; {how}) and hold "
                "it there, then press Enter"
            )

    return Operator(tell)


def dashboard_operator(host: str) -> Operator:
    """The loopback rig's emulated operator, through the controller's dashboard
    (``uscal twin serve``): for rehearsing the touch step without a person."""

    def tell(action: str, detail: Any) -> None:
        if action == "mount":
            command = f"twin mount {detail}"
        else:
            command = f"twin touch {detail[0]} {detail[1]}"
        try:
            with socket.create_connection((host, 29999), timeout=10) as s:
                f = s.makefile("rw")
                f.readline()
                f.write(command + "\n")
                f.flush()
                answer = f.readline().strip()
        except OSError as e:
            raise RobotConnectionError(f"loopback operator at {host}:29999: {e}") from None
        if not answer.startswith("twin: ") or answer.startswith("twin: error"):
            raise UscalError(f"loopback operator: {command!r} → {answer!r} (is this the twin?)")

    return Operator(tell)


def _touches(cfg: HwConfig, robot, writer: DatasetWriter, operator: Operator) -> int:
    """The touch step: each planned touch not yet recorded, saved as it is taken."""
    vertices = sorted(k for k in cfg.acquisition_info().landmarks if k.startswith("vertex_"))
    plan = [
        t for t in touch_plan(vertices, cfg.protocol) if not writer.has_touch(t.vertex, t.index)
    ]
    if not plan:
        return 0
    operator.tell("mount", "stylus")
    for done, planned in enumerate(plan):
        report("touches", done, len(plan))
        operator.place(planned.vertex, planned.index, planned.R_base_ee)
        # The arm is still now; give the controller's state stream a moment to show it.
        time.sleep(_HOLD_S)
        reading = robot.read()
        writer.add_touches([Touch(planned.vertex, planned.index, reading.q, reading.T_base_ee)])
    report("touches", len(plan), len(plan))
    operator.tell("mount", "probe")
    return len(plan)


def acquire_dataset(
    cfg: HwConfig,
    out: str | os.PathLike[str],
    resume: bool = False,
    dry_run: bool = False,
    confirm: Callable[[str], bool] | None = None,
    say: Callable[[str], None] = lambda _m: None,
    operator: Operator | None = None,
    until: StopRule | None = None,
    set_tcp_zero: bool = False,
) -> AcquisitionSummary:
    """Run the protocol on the rig of ``cfg`` into the dataset directory ``out``.

    ``confirm(message)`` is asked once before the first motion (None: no question).
    ``operator``: after the sweeps, the touches of every cone vertex (the protocol's
    ``touches_per_vertex`` each), hand-guided by it; None: no touches. ``until``: the
    sequential acquisition — about each sphere, the next sweep is the one of the plan
    (``protocol.plan``, or the paper's) that adds most to the sweeps localized so far,
    until the predicted 1 σ of ``T_ee_us`` is within the rule's limits
    (:mod:`bench.sequential`). ``set_tcp_zero``: a controller whose active TCP offset is
    not zero has it set to zero (else it is refused before anything moves, and a dataset
    directory this call created is removed again).
    """
    if until is not None and resume:
        raise UscalError(
            "--until-rotation-deg / --until-translation-mm: a sequential acquisition "
            "chooses each sweep from those before it and starts anew (no --resume)"
        )
    from hw.grabber import FrameGrabber
    from hw.robot import URRobot, describe_tcp

    t0 = time.perf_counter()
    out = Path(out)
    spheres = [f"sphere_{i}" for i in cfg.protocol.spheres]
    missing = [
        t
        for t, i in zip(spheres, cfg.protocol.spheres, strict=True)
        if cfg.rig.taught_deg(i) is None
    ]
    if missing:
        raise UscalError(
            f"{cfg.source}: no taught pose for {', '.join(missing)} (rig.taught_<sphere>_deg: "
            "jog the probe over each sphere and record the joint angles)"
        )
    taught_q = {
        t: np.radians(cfg.rig.taught_deg(i))
        for t, i in zip(spheres, cfg.protocol.spheres, strict=True)
    }
    # The plan from the controller's own model at the taught joint angles (for the real
    # move the controller's reported pose there is used: the same up to its factory
    # calibration, which the plan's ±10° corners do not notice).
    nominal = NOMINAL_TABLES[cfg.robot.model]
    taught_T = {t: forward_kinematics(nominal, q) for t, q in taught_q.items()}
    robot = URRobot(cfg.robot, dry_run=True)
    plan, replaced = _plans(robot, cfg, taught_T)
    for r in replaced:
        say(r.line())
    say(
        f"plan: {len(plan)} sweeps of {cfg.protocol.frames_per_sweep} frames over "
        f"{', '.join(spheres)}: every pose inside the workspace, every step within the limits"
    )
    if dry_run:
        return AcquisitionSummary(out, len(plan), 0, 0, True, time.perf_counter() - t0)

    image_meta = {
        "grabber": cfg.grabber.source,
        "roi_px": list(cfg.grabber.roi_px) if cfg.grabber.roi_px else None,
        "pixel_spacing_mm": list(cfg.grabber.pixel_spacing_mm),
        "depth_mm": cfg.rig.probe_depth_mm,
    }
    writer = DatasetWriter(out, cfg.rig.name, cfg.acquisition_info(), image_meta, resume)
    todo = [p for p in plan if not writer.has(p.target, p.pose_id)]
    skipped = len(plan) - len(todo)
    if skipped:
        say(f"resuming: {skipped} sweeps already recorded, {len(todo)} to go")
    if (
        confirm is not None
        and (todo or operator is not None)
        and not confirm(
            f"The robot at {cfg.robot.host} will move through {len(todo)} sweeps. Is the "
            "workspace clear and the emergency stop at hand?"
        )
    ):
        raise UscalError("acquisition cancelled before any motion")
    done = 0
    try:
        try:
            robot = URRobot(cfg.robot, set_tcp_zero=set_tcp_zero)
        except RobotSetupError:
            writer.discard_if_empty()
            raise
        if robot.tcp_offset_cleared is not None:
            was = describe_tcp(robot.tcp_offset_cleared)
            say(f"the controller's TCP offset was {was}: set to zero (--set-tcp-zero)")
        with robot, FrameGrabber(cfg.grabber) as grabber:
            report("acquire sweeps", skipped, len(plan))
            if until is not None:
                for target in spheres:
                    done += _acquire_until(
                        cfg, robot, grabber, writer, target, taught_q[target], until, say
                    )
                todo = []
            current = None
            for planned in todo:
                if planned.target != current:
                    current = planned.target
                    say(f"to the taught pose of {current}")
                    robot.move_joints(taught_q[current], f"taught pose of {current}")
                    # Re-plan this sphere's remaining sweeps (as checked, spares in
                    # place) from the reported taught pose.
                    T_taught = here = robot.read().T_base_ee
                    mine = [p for p in plan if p.target == current]
                    replanned = {
                        p.pose_id: replace(q, pose_id=p.pose_id)
                        for p, q in zip(
                            mine,
                            plan_sweeps(
                                current,
                                T_taught,
                                cfg.rig.T_ee_us_coarse,
                                cfg.protocol,
                                poses=[p.pose for p in mine],
                            ),
                            strict=True,
                        )
                    }
                # The transit from where the arm is: the taught pose, or the last sweep
                # recorded (a resumed acquisition skips the sweeps it has).
                sweep_plan = replanned[planned.pose_id]
                sweep_plan = replace(
                    sweep_plan,
                    approach=transit(here, sweep_plan.T_base_ee[0], cfg.protocol.transit_step_deg),
                )
                here = sweep_plan.T_base_ee[-1]
                stamps: list[float] = []
                (sweep,) = acquire(
                    robot,
                    grabber,
                    [sweep_plan],
                    on_frame=lambda _p, _j, log=stamps: log.append(time.time()),
                )
                writer.add_sweep(sweep, timestamps=np.array(stamps))
                done += 1
                report("acquire sweeps", skipped + done, len(plan))
            if operator is not None:
                say(f"{_touches(cfg, robot, writer, operator)} touches recorded")
    except (RobotConnectionError, RobotStoppedError, FrameGrabberError) as e:
        raise type(e)(
            f"{e}. {writer.n_sweeps} of {len(plan)} sweeps are saved in {out}; "
            "`uscal acquire --resume` continues"
        ) from None
    writer.finish()
    return AcquisitionSummary(out, len(plan), done, skipped, False, time.perf_counter() - t0)


def _acquire_until(cfg, robot, grabber, writer, target, q_taught, until, say) -> int:
    """One sphere's sequential scan on the rig: from the taught pose, the plan's sweep
    that adds most each time, localized with the sweeps before it, until the rule is
    met. Returns the sweeps acquired."""
    proto = cfg.protocol
    say(f"to the taught pose of {target}")
    robot.move_joints(q_taught, f"taught pose of {target}")
    T_taught = robot.read().T_base_ee
    coarse = cfg.rig.T_ee_us_coarse
    poses = sphere_poses(proto, target) or default_poses(proto)
    single = [plan_sweeps(target, T_taught, coarse, proto, poses=[p])[0] for p in poses]
    depth = proto.target_depth_mm * 1e-3
    cands = Candidates.build(
        np.array([s.T_base_ee[len(s.T_base_ee) // 2] for s in single]),
        coarse,
        np.array([p.target_in_image(depth) for p in poses]),
        np.zeros(len(poses), dtype=int),
        cfg.planning.noise(),
    )
    bias = bias_covariance(coarse, cfg.planning.localization_bias_mm)
    chooser = Chooser(target, cands, poses, until, np.eye(6), bias)
    info = cfg.acquisition_info()
    localizer = LocalizerConfig(expected_depth_mm=proto.target_depth_mm)
    chosen, mine = [], []
    while chooser.more():
        chosen.append(chooser.next())
        planned = plan_sweeps(target, T_taught, coarse, proto, poses=chosen)[-1]
        stamps: list[float] = []
        (sweep,) = acquire(
            robot, grabber, [planned], on_frame=lambda _p, _j, log=stamps: log.append(time.time())
        )
        writer.add_sweep(sweep, timestamps=np.array(stamps))
        mine.append(sweep)
        report("acquire sweeps", writer.n_sweeps, until.max_sweeps * len(proto.spheres))
        locs = localize_sphere(
            mine, None, info.sphere_radius_mm * 1e-3, localizer, axial_scale=axial_scale_of(info)
        )
        chooser.update([loc.accepted for loc in locs])
    scan = chooser.scan()
    say(
        f"{target}: {scan.sweeps} sweeps ({scan.localized} localized), predicted "
        f"{scan.rotation_deg:.3f}° / {scan.translation_mm:.3f} mm 1 σ"
        + ("" if scan.reached else f": the limits not reached in {until.max_sweeps} sweeps")
    )
    return scan.sweeps
