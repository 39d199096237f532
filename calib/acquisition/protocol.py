"""Multi-pose sphere acquisition (paper, "Multi-Pose Sphere Acquisition") and touch
measurements (paper, "Reference Target Localization and Kinematics Refinement").

From a nominal pose facing a sphere, the plan is the nominal orientation plus the eight
(±10°, ±10°, ±10°) corners about the probe axes (9 orientations), each crossed with the
nominal and four (±3, ±3) mm in-plane positions (5 positions): 45 poses, each a ±10 mm
elevational sweep of 21 frames. Rotations turn about the sphere centre so it stays in view.

With the stylus mounted, each cone vertex is touched from several distinct orientations
(the stylus tilted from vertical at evenly spread azimuths, turned about its own axis by
turns); the controller's joint angles are recorded at each touch.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import se3
from ..errors import CollisionError, UnreachablePoseError
from ..records import RobotReading, Sweep, Touch, UsFrame
from .planning import SweepPose, paper_poses, sweep_commands

__all__ = [
    "DeferredImager",
    "Imager",
    "PlanChecker",
    "PlannedSweep",
    "PlannedTouch",
    "ProtocolConfig",
    "Replacement",
    "Robot",
    "TouchGuide",
    "acquire",
    "acquire_touches",
    "check_plan",
    "clear_sweeps",
    "default_poses",
    "facing_pose",
    "in_plane_offsets",
    "orientation_offsets",
    "plan_parallel_sweeps",
    "plan_sweeps",
    "rotated_about_target",
    "sweep_axis_off_normal",
    "touch_plan",
    "transit",
]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ProtocolConfig:
    """The acquisition plan (defaults: the paper's numbers)."""

    spheres: tuple[int, ...] = field(
        default=(1, 2, 3, 4),
        metadata={
            "doc": "Spheres of the four-sphere phantom to scan (1–4), in order.",
            "ge": 1,
            "le": 4,
        },
    )
    rotation_deg: float = field(
        default=10.0,
        metadata={"doc": "Orientation corners: ± this about each probe axis.", "ge": 0, "le": 45},
    )
    tilt_deg: float | None = field(
        default=None,
        metadata={
            "doc": "Orientation corners about the image's lateral axis (the tilt that turns "
            "the beam along the elevation): ± this instead of rotation_deg (null: "
            "rotation_deg). A wire's echo fades with this tilt as a mirror's does (an "
            "N-wire phantom: a few degrees).",
            "ge": 0,
            "le": 45,
        },
    )
    translation_mm: float = field(
        default=3.0,
        metadata={
            "doc": "In-plane position corners: ± this laterally and axially.",
            "ge": 0,
            "le": 20,
        },
    )
    sweep_half_length_mm: float = field(
        default=10.0,
        metadata={"doc": "Each sweep runs ± this along the elevational axis.", "gt": 0, "le": 50},
    )
    frames_per_sweep: int = field(
        default=21, metadata={"doc": "Frames per sweep (evenly spaced).", "ge": 3, "le": 401}
    )
    target_depth_mm: float = field(
        default=20.0,
        metadata={
            "doc": "Depth of the target (sphere centre, cone apex) in the image at the "
            "nominal pose.",
            "gt": 0,
            "le": 200,
        },
    )
    teaching_error_mm: float = field(
        default=2.0,
        metadata={
            "doc": "Simulation: 1 σ error of the operator-taught nominal pose.",
            "ge": 0,
            "le": 20,
        },
    )
    transit_step_deg: float = field(
        default=40.0,
        metadata={
            "doc": "A move between sweeps that turns the probe more than this goes through "
            "intermediate poses, each turning at most this (the paper's plan never turns "
            "that far; a robot's step limit, e.g. robot.max_step_deg of a hw config, must "
            "not be below it).",
            "gt": 0,
            "le": 180,
        },
    )
    plan: str | None = field(
        default=None,
        metadata={
            "doc": "A plan file (`uscal plan --optimize --out PLAN.yaml`): the sweeps about "
            "each target (sphere, wire, N-wire, cone tip), relative to its taught pose, instead "
            "of the paper's 9 orientations "
            "× 5 positions (rotation_deg and translation_mm then do not apply); a relative "
            "path is read from the scenario file's folder."
        },
    )
    second_pass: bool = field(
        default=False,
        metadata={
            "doc": "Scan every sphere again once calibrated, each sweep planned through the "
            "calibrated T_ee_us (so it runs along the image normal), and calibrate on the "
            "second scan. The first runs along the coarse mount's elevational axis, off the "
            "normal by that mount's error (the paper's ±10°); at 10-13 mm targets a sweep "
            "tilted 7-9° in depth biased the rotation beyond its 95 % bound. "
            "Twice the robot time; one acquisition only (uscal run)."
        },
    )
    touches_per_vertex: int = field(
        default=6,
        metadata={
            "doc": "Stylus touches per cone vertex, each from its own orientation.",
            "ge": 1,
            "le": 50,
        },
    )
    touch_spin_deg: float = field(
        default=30.0,
        metadata={
            "doc": "Turn of the stylus about its own axis between touches (−, 0, +, …): "
            "varies the wrist joints, which the DH refinement needs.",
            "ge": 0,
            "le": 90,
        },
    )
    touch_tilt_deg: float = field(
        default=20.0,
        metadata={
            "doc": "Tilt of the stylus from vertical; the touches of a vertex spread it over "
            "evenly spaced azimuths.",
            "ge": 0,
            "le": 60,
        },
    )


def default_poses(cfg: ProtocolConfig) -> list[SweepPose]:
    """The protocol's sweeps about a target without a plan file: the paper's 9
    orientations × 5 positions at its rotation, tilt and translation."""
    return paper_poses(cfg.rotation_deg, cfg.translation_mm, cfg.tilt_deg)


def orientation_offsets(rotation_deg: float, tilt_deg: float | None = None) -> Array:
    """The nine orientations of the plan as rotations about the probe axes, (9, 3, 3).

    Index 0 is the nominal orientation; 1–8 the (±r, ±r, ±r) corners as extrinsic x-y-z
    Euler angles in the image frame (about x at ± ``tilt_deg`` when given).
    """
    r = np.radians([rotation_deg if tilt_deg is None else tilt_deg, rotation_deg, rotation_deg])
    corners = [np.zeros(3)] + [np.array(s) * r for s in itertools.product((-1, 1), repeat=3)]
    return se3.matrix_from_euler(np.array(corners))


def facing_pose(
    p_base_target: ArrayLike, depth: float, *, lateral_axis: ArrayLike = (0, 1, 0)
) -> Array:
    """``T_base_us`` (4, 4) of a probe looking straight down at a target.

    The image's axial axis (y) points down (−z of base), its lateral axis (x) along
    ``lateral_axis`` (projected horizontal), and the target lies on the image's centre
    line ``depth`` metres below the transducer face.
    """
    y = np.array([0.0, 0.0, -1.0])
    x = np.asarray(lateral_axis, dtype=float)
    x = x - x.dot(y) * y
    x /= np.linalg.norm(x)
    R = np.column_stack([x, y, np.cross(x, y)])
    return se3.make(R, np.asarray(p_base_target, dtype=float) - depth * y)


def rotated_about_target(T_base_us: Array, R_offset: Array, depth: float) -> Array:
    """Turn a facing pose by ``R_offset`` (about the image axes) about the target point at
    ``(0, depth, 0)`` in the image, so the target stays where it is in the image."""
    T_us_target = se3.make(np.eye(3), [0.0, depth, 0.0])
    return T_base_us @ T_us_target @ se3.make(R_offset, np.zeros(3)) @ se3.invert(T_us_target)


class Robot(Protocol):
    """What the protocol needs of a robot (the twin's SimRobot, or the real UR3)."""

    def move_to(self, T_base_ee: NDArray[np.float64], pose_label: str = "") -> RobotReading:
        """Move the flange to a pose (controller's model); the reading after settling."""
        ...

    def check_pose(self, T_base_ee: NDArray[np.float64], pose_label: str = "") -> None:
        """Raise UnreachablePoseError / CollisionError if the pose cannot be reached safely."""
        ...

    def read(self) -> RobotReading:
        """The controller's current joint angles and flange pose (no motion)."""
        ...


@runtime_checkable
class PlanChecker(Protocol):
    """A robot that checks many poses in one call (the twin: its inverse kinematics
    solves a plan's frame poses at once). :func:`check_plan` uses it when the robot has
    it; it raises as :meth:`Robot.check_pose` would for the first pose that fails."""

    def check_poses(self, T_base_ee: NDArray[np.float64], pose_labels: Sequence[str]) -> None:
        """Check poses (n, 4, 4) in order; ``pose_labels`` (n) name them in errors."""
        ...


class TouchGuide(Protocol):
    """Who brings the stylus tip onto a vertex: an operator hand-guiding the real arm, or
    the twin's emulation of one (which places the true tip on the true vertex)."""

    def place(self, vertex: str, index: int, R_base_ee: NDArray[np.float64]) -> None:
        """Put the tip on ``vertex`` with the flange at (about) orientation ``R_base_ee``."""
        ...


class Imager(Protocol):
    """What the protocol needs of a scanner (the twin's SimImager, or a frame grabber)."""

    def grab(self) -> UsFrame:
        """A fresh frame taken after the robot settled."""
        ...


@runtime_checkable
class DeferredImager(Protocol):
    """A scanner that can note each frame's instant and form the frames later, a sweep at
    a time (the twin: rendering a sweep in one call costs less than frame by frame).
    :func:`acquire` uses it when the imager has it; the frames are the ones ``grab`` would
    have returned at the same instants."""

    def capture(self) -> None:
        """Note a frame now (pose, time), in place of :meth:`Imager.grab`."""
        ...

    def develop(self) -> list[UsFrame]:
        """The frames noted since the last call, in order."""
        ...


@dataclass(frozen=True)
class PlannedSweep:
    """One sweep of the plan: flange commands for its frames, and where it was placed
    relative to the taught pose (:class:`calib.acquisition.planning.SweepPose`)."""

    target: str
    pose_id: int
    pose: SweepPose
    T_base_ee: NDArray[np.float64]  # (n_frames, 4, 4)
    #: Poses passed through (no frame grabbed) before the first frame: the transit from
    #: the previous sweep when it turns more than ``transit_step_deg``.
    approach: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4, 4)))


def in_plane_offsets(translation_mm: float) -> NDArray[np.float64]:
    """(5, 2) in-plane (lateral, axial) offsets in metres: nominal, then the corners."""
    t = translation_mm * 1e-3
    corners = [(0.0, 0.0)] + [(sx * t, sy * t) for sx, sy in itertools.product((-1, 1), repeat=2)]
    return np.array(corners)


def plan_sweeps(
    target: str,
    T_base_ee_taught: ArrayLike,
    T_ee_us_coarse: ArrayLike,
    cfg: ProtocolConfig,
    *,
    poses: Sequence[SweepPose] | None = None,
) -> list[PlannedSweep]:
    """The sweeps about one sphere: the paper's 9 orientations × 5 positions, or the
    ``poses`` of a chosen plan (:mod:`calib.acquisition.planning`).

    The taught pose puts the sphere on the image centre line at ``target_depth_mm`` as the
    coarse ``T_ee_us`` predicts it; orientations turn about that point, positions shift the
    probe in its image plane, and each sweep runs along the estimated elevational axis.
    """
    if poses is None:
        poses = default_poses(cfg)
    depth = cfg.target_depth_mm * 1e-3
    half = cfg.sweep_half_length_mm * 1e-3
    plan = []
    here = np.asarray(T_base_ee_taught, dtype=float)
    for k, pose in enumerate(poses):
        frames = sweep_commands(
            T_base_ee_taught,
            T_ee_us_coarse,
            depth,
            pose,
            half_length=half,
            n_frames=cfg.frames_per_sweep,
        )
        plan.append(
            PlannedSweep(target, k, pose, frames, transit(here, frames[0], cfg.transit_step_deg))
        )
        here = frames[-1]
    return plan


def transit(T_from: ArrayLike, T_to: ArrayLike, max_turn_deg: float) -> NDArray[np.float64]:
    """Intermediate flange poses (m, 4, 4) of a move that turns more than
    ``max_turn_deg``: evenly spaced along the geodesic (rotation about one axis, straight
    translation), so that no step turns more than that; none for a smaller turn."""
    T0, T1 = np.asarray(T_from, dtype=float), np.asarray(T_to, dtype=float)
    n = int(np.ceil(float(np.degrees(se3.rotation_angle(T0, T1))) / max_turn_deg - 1e-9))
    if n <= 1:
        return np.zeros((0, 4, 4))
    xi = se3.log(se3.invert(T0) @ T1)
    return np.array([T0 @ se3.exp(xi * k / n) for k in range(1, n)])


def plan_parallel_sweeps(
    target: str,
    T_base_ee_taught: ArrayLike,
    T_ee_us_coarse: ArrayLike,
    cfg: ProtocolConfig,
    *,
    travel: ArrayLike,
) -> list[PlannedSweep]:
    """The paper's prism protocol: the same 45 starting poses as :func:`plan_sweeps`
    (9 orientations about the target × 5 in-plane positions), but every sweep travels
    along one fixed base-frame direction ``travel`` (the ridge), so the 45 sweeps are
    mutually parallel whatever the probe's orientation."""
    d = np.asarray(travel, dtype=float)
    d = d / np.linalg.norm(d)
    half = cfg.sweep_half_length_mm * 1e-3
    steps = np.linspace(-half, half, cfg.frames_per_sweep)
    shifts = se3.make(np.eye(3), steps[:, None] * d[None, :])  # (n, 4, 4), base frame
    plan = []
    for p in plan_sweeps(target, T_base_ee_taught, T_ee_us_coarse, cfg):
        T_centre = p.T_base_ee[len(p.T_base_ee) // 2]  # the starting pose, mid-sweep
        plan.append(PlannedSweep(p.target, p.pose_id, p.pose, shifts @ T_centre))
    return plan


def sweep_axis_off_normal(sweeps: Sequence[Sweep], T_ee_us: ArrayLike) -> dict[str, float]:
    """How far the sweeps ran off the image normal of ``T_ee_us``: the median over the
    sweeps of the angle (°) between the way the flange moved (first frame to last) and
    the image's elevational axis, with its part in depth (the tilt towards the image's
    axial axis, which moves a target's depth from frame to frame) and across the image
    (towards its lateral axis). A sweep planned through a coarse mount runs along that
    mount's axis, off the calibrated one by the mount's error."""
    X = np.asarray(T_ee_us, dtype=float)
    u = []
    for s in sweeps:
        T = np.asarray(s.T_base_ee, dtype=float)
        move = T[-1, :3, 3] - T[0, :3, 3]
        if len(T) < 2 or not np.linalg.norm(move) > 0:
            continue
        R = T[s.reference_index, :3, :3] @ X[:3, :3]  # the image's axes in the base frame
        v = R.T @ (move / np.linalg.norm(move))
        u.append(v if v[2] >= 0 else -v)  # a sweep run backwards runs along the same axis
    if not u:
        return {"angle_deg": float("nan"), "in_depth_deg": float("nan"), "across_deg": float("nan")}
    U = np.array(u)
    return {
        "angle_deg": float(np.degrees(np.median(np.arccos(np.clip(U[:, 2], -1.0, 1.0))))),
        "in_depth_deg": float(np.degrees(np.median(np.arctan2(U[:, 1], U[:, 2])))),
        "across_deg": float(np.degrees(np.median(np.arctan2(U[:, 0], U[:, 2])))),
    }


def check_plan(robot: Robot, plan: Sequence[PlannedSweep]) -> None:
    """Reachability and collision checks of every pose before any motion (transits
    included, in the order they are moved to); the error names the sweep and frame that
    fails."""
    poses = [
        (T, f"{s.target} sweep {s.pose_id} {what}")
        for s in plan
        for what, T in [(f"transit {j}", T) for j, T in enumerate(s.approach)]
        + [(f"frame {j}", T) for j, T in enumerate(s.T_base_ee)]
    ]
    if isinstance(robot, PlanChecker):
        if poses:
            robot.check_poses(np.array([T for T, _ in poses]), [label for _, label in poses])
        return
    for T, label in poses:
        robot.check_pose(T, label)


@dataclass(frozen=True)
class Replacement:
    """A planned sweep that did not clear in this session, and what took its place: the
    plan's ``spare`` (index into its spares) or nothing (``spare`` None: no spare clears,
    the sweep is left out)."""

    target: str
    pose_id: int
    reason: str
    spare: int | None
    pose: SweepPose | None = None

    def line(self) -> str:
        if self.spare is None or self.pose is None:
            return f"{self.target} sweep {self.pose_id} left out ({self.reason}; no spare clears)"
        rx, ry, rz = self.pose.rotation_deg
        return (
            f"{self.target} sweep {self.pose_id} replaced by spare {self.spare} "
            f"(turned {rx:g}°, {ry:g}°, {rz:g}°, shifted {self.pose.lateral_mm:g} / "
            f"{self.pose.axial_mm:g} mm): {self.reason}"
        )


def clear_sweeps(
    target: str,
    T_base_ee_taught: ArrayLike,
    T_ee_us_coarse: ArrayLike,
    cfg: ProtocolConfig,
    check: Callable[[PlannedSweep, Array], None],
    *,
    poses: Sequence[SweepPose] | None = None,
    spares: Sequence[SweepPose] = (),
) -> tuple[list[PlannedSweep], list[Replacement]]:
    """The sweeps about one sphere as this session will move through them, each checked
    before anything moves: ``check(sweep, T_from)`` raises
    :class:`~calib.errors.UnreachablePoseError` or :class:`~calib.errors.CollisionError`
    when a frame or the transit to it from ``T_from`` (the last frame before it) does not
    clear. Such a sweep is replaced by the first unused spare that clears (the plan's
    next-best, :mod:`bench.jobs.plan_optimize`), or left out when none does — one sweep
    never stops the acquisition. Returns the sweeps (each keeps its slot's ``pose_id``)
    and a :class:`Replacement` for every sweep that did not go as planned. A plan of
    which half the sweeps or more would be left out does not suit the session: the first
    sweep's error is raised, with the count, before anything moves."""
    if poses is None:
        poses = default_poses(cfg)
    here = np.asarray(T_base_ee_taught, dtype=float)
    unused = list(enumerate(spares))
    out: list[PlannedSweep] = []
    changed: list[Replacement] = []
    first: UnreachablePoseError | CollisionError | None = None

    def planned(k: int, pose: SweepPose) -> PlannedSweep:
        frames = sweep_commands(
            T_base_ee_taught,
            T_ee_us_coarse,
            cfg.target_depth_mm * 1e-3,
            pose,
            half_length=cfg.sweep_half_length_mm * 1e-3,
            n_frames=cfg.frames_per_sweep,
        )
        return PlannedSweep(target, k, pose, frames, transit(here, frames[0], cfg.transit_step_deg))

    for k, pose in enumerate(poses):
        sweep = planned(k, pose)
        try:
            check(sweep, here)
        except (UnreachablePoseError, CollisionError) as e:
            reason = str(e)
            for j, (index, spare) in enumerate(unused):
                sweep = planned(k, spare)
                try:
                    check(sweep, here)
                except (UnreachablePoseError, CollisionError):
                    continue
                changed.append(Replacement(target, k, reason, index, spare))
                del unused[j]
                break
            else:
                changed.append(Replacement(target, k, reason, None))
                first = first or e
                continue
        out.append(sweep)
        here = sweep.T_base_ee[-1]
    left_out = len(poses) - len(out)
    if first is not None and 2 * left_out >= len(poses):
        raise type(first)(
            f"{left_out} of the {len(poses)} sweeps about {target} do not clear (first: "
            f"{first}): the plan does not suit this session"
        )
    return out, changed


@dataclass(frozen=True)
class PlannedTouch:
    """One touch of the plan: a vertex and the flange orientation to touch it from."""

    vertex: str
    index: int
    R_base_ee: NDArray[np.float64]  # (3, 3)


def touch_plan(
    vertices: Sequence[str],
    cfg: ProtocolConfig,
    *,
    lean: Mapping[str, ArrayLike] | None = None,
) -> list[PlannedTouch]:
    """``touches_per_vertex`` orientations per vertex.

    The flange points down (its z axis, along which the stylus runs, along −z of base),
    tilted by ``touch_tilt_deg`` so the top of the stylus leans towards evenly spread
    horizontal directions, and turned about its own axis by −spin, 0, +spin in turn. The
    heading stays, so the wrist does not wind up. ``lean[vertex]`` (a horizontal direction
    in base, e.g. towards the phantom's middle, away from the tank walls) keeps the lean
    directions within ±90° of it; without it they go all round.
    """
    n = cfg.touches_per_vertex
    R_down = np.diag([1.0, -1.0, -1.0])
    tilt = np.radians(cfg.touch_tilt_deg)
    plan = []
    for vertex in vertices:
        if lean is not None and vertex in lean:
            d = np.asarray(lean[vertex], dtype=float)
            centre = np.arctan2(d[1], d[0])
            azimuths = centre + np.pi * (np.arange(n) / max(n - 1, 1) - 0.5)
        else:
            azimuths = 2 * np.pi * np.arange(n) / n
        for k, azimuth in enumerate(azimuths):
            towards = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
            spin = np.radians(cfg.touch_spin_deg) * ((k % 3) - 1)
            R = (
                se3.matrix_from_rotvec(tilt * np.cross([0.0, 0.0, 1.0], towards))
                @ R_down
                @ se3.matrix_from_euler(np.array([0.0, 0.0, spin]))
            )
            plan.append(PlannedTouch(vertex, k, R))
    return plan


def acquire_touches(
    robot: Robot,
    guide: TouchGuide,
    plan: Sequence[PlannedTouch],
    *,
    on_touch: Callable[[PlannedTouch], None] | None = None,
) -> list[Touch]:
    """For each planned touch: the guide brings the tip onto the vertex, then the
    controller's joint angles and flange pose are recorded."""
    touches = []
    for planned in plan:
        guide.place(planned.vertex, planned.index, planned.R_base_ee)
        reading = robot.read()
        touches.append(Touch(planned.vertex, planned.index, reading.q, reading.T_base_ee))
        if on_touch is not None:
            on_touch(planned)
    return touches


def acquire(
    robot: Robot,
    imager: Imager,
    plan: Sequence[PlannedSweep],
    *,
    on_frame: Callable[[PlannedSweep, int], None] | None = None,
) -> list[Sweep]:
    """Run the plan: move, let the robot settle, grab, for every frame of every sweep.

    ``on_frame(sweep, j)`` is called after each frame (progress, or a simulator's truth
    log); it receives nothing the pipeline may not see. A :class:`DeferredImager` notes
    each frame's instant and forms the sweep's frames after its last move.
    """
    deferred = isinstance(imager, DeferredImager)
    sweeps = []
    for planned in plan:
        images, qs, poses, spacing = [], [], [], None
        for j, T in enumerate(planned.approach):
            robot.move_to(T, f"{planned.target} sweep {planned.pose_id} transit {j}")
        try:
            for j, T in enumerate(planned.T_base_ee):
                label = f"{planned.target} sweep {planned.pose_id} frame {j}"
                reading = robot.move_to(T, label)
                if deferred:
                    imager.capture()
                else:
                    frame = imager.grab()
                    images.append(frame.image)
                    spacing = frame.spacing
                qs.append(reading.q)
                poses.append(reading.T_base_ee)
                if on_frame is not None:
                    on_frame(planned, j)
        except BaseException:
            if deferred:
                # The frames noted before the failure are formed (and dropped) as grabbing
                # would have formed them, so the imager starts the next sweep clean.
                imager.develop()
            raise
        if deferred:
            frames = imager.develop()
            images = [f.image for f in frames]
            spacing = frames[-1].spacing if frames else None
        sweeps.append(
            Sweep(
                planned.target,
                planned.pose_id,
                np.array(images),
                spacing,
                np.array(qs),
                np.array(poses),
            )
        )
    return sweeps
