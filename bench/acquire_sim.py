"""Experiment assembly: from a validated scenario to the twin (and, later, the pipeline)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.protocol import (
    PlannedSweep,
    PlannedTouch,
    Replacement,
    acquire,
    acquire_touches,
    check_plan,
    clear_sweeps,
    facing_pose,
    touch_plan,
)
from calib.calibration.markers import CalibrationConfig
from calib.errors import CollisionError
from calib.files.dataset import AcquisitionInfo, ConeTipPhantom, DatasetWriter, WirePhantom
from calib.files.plus_config import NWire, NWirePattern, NWirePhantom
from calib.records import Dataset, Sweep, Touch
from twin.arm_errors import robot_stream
from twin.imager import GainSeriesImager, SimImager
from twin.touch import SimTouchGuide
from twin.world import Twin, build_twin

from .config.geometry import acquisition_targets, lateral_axis
from .config.method import stated_radius
from .config.plan_file import spare_poses, sphere_poses, sweeps_about
from .config.scenario import Scenario
from .files import frames_to_file
from .progress import report
from .sessions import stage_rngs

__all__ = [
    "SimulatedAcquisition",
    "acquisition_info",
    "coarse_estimate",
    "dataset_meta",
    "image_meta",
    "make_imager",
    "make_twin",
    "save_dataset",
    "simulate_acquisition",
    "simulate_acquisition_at_gains",
    "simulate_touches",
    "teach_at",
    "twin_nwire_phantom",
]

Array = NDArray[np.float64]


def make_twin(scenario: Scenario, joints_rng: np.random.Generator | None = None) -> Twin:
    """Build the twin of a scenario: truth drawn from its seed (``joints_rng`` replaces
    the joint-noise stream, e.g. for another dataset of the same robot)."""
    rngs = stage_rngs(scenario)
    return build_twin(
        scenario.robot,
        scenario.tools,
        scenario.phantom,
        rngs["dh"],
        rngs["phantom"],
        rngs["joints"] if joints_rng is None else joints_rng,
        robot_stream(scenario.seed),
    )


def make_imager(
    scenario: Scenario, twin: Twin, rng: np.random.Generator | None = None
) -> SimImager:
    """The simulated scanner of a scenario, looking through the twin's true probe mount."""
    return SimImager(
        twin.robot,
        twin.truth.T_ee_us,
        scenario.imaging,
        scenario.medium,
        stage_rngs(scenario)["imaging"] if rng is None else rng,
    )


@dataclass(frozen=True, eq=False)
class SimulatedAcquisition:
    """A simulated acquisition: the dataset the pipeline sees, and the truth kept apart.

    ``T_base_ee_true[(target, pose_id)]`` holds the true flange pose of every frame;
    ``replaced`` the planned sweeps that did not clear in this session and what took
    their place (:func:`calib.acquisition.protocol.clear_sweeps`).
    """

    dataset: Dataset
    T_ee_us_coarse: NDArray[np.float64]
    T_base_ee_true: dict[tuple[str, int], NDArray[np.float64]]
    robot_time_s: float = 0.0  # the twin controller's session clock over the sweeps
    replaced: tuple[Replacement, ...] = ()


def coarse_estimate(
    T_ee_us_true: NDArray[np.float64], cfg: CalibrationConfig, rng: np.random.Generator
) -> NDArray[np.float64]:
    """The coarse ``T_ee_us`` a user would take from the holder's CAD: the truth off by up
    to ± ``initial_error_mm`` per axis and ± ``initial_error_deg`` about each axis."""
    dt = rng.uniform(-1, 1, 3) * cfg.initial_error_mm * 1e-3
    dr = np.radians(rng.uniform(-1, 1, 3) * cfg.initial_error_deg)
    return T_ee_us_true @ se3.make(se3.matrix_from_euler(dr), dt)


def simulate_touches(
    scenario: Scenario,
    twin: Twin,
    contact_rng: np.random.Generator,
    on_touch: Callable[[PlannedTouch], None] | None = None,
) -> list[Touch]:
    """Mount the stylus and touch each cone vertex from the protocol's orientations.

    The emulated operator leans the stylus towards the middle of the phantom (away from
    the tank walls) and places the true tip on the true vertex, with contact noise.
    """
    vertices = {k: v for k, v in twin.truth.landmarks_base.items() if k.startswith("vertex_")}
    middle = np.mean(list(vertices.values()), axis=0)
    lean = {k: (middle - v) * np.array([1.0, 1.0, 0.0]) for k, v in vertices.items()}
    plan = touch_plan(sorted(vertices), scenario.protocol, lean=lean)
    guide = SimTouchGuide(
        twin.robot,
        vertices,
        twin.truth.p_ee_tip,
        scenario.tools.contact_noise_mm,
        contact_rng,
        scenario.tools.stylus_bending_m,
    )
    twin.mount("stylus")
    try:
        return acquire_touches(twin.robot, guide, plan, on_touch=on_touch)
    finally:
        twin.mount("probe")


def teach_at(
    twin: Twin,
    point: NDArray[np.float64],
    depth: float,
    label: str,
    miss_rng: np.random.Generator | None = None,
    teaching_error_mm: float = 0.0,
    lateral_axis: NDArray[np.float64] | tuple[float, float, float] = (0, 1, 0),
):
    """The operator teaches the nominal pose at a target, as on the rig: jogs until
    ``point`` (base frame, the truth) sits on the image's centre line ``depth`` below
    the face — off by the teaching error (isotropic, ``teaching_error_mm`` 1 σ, drawn
    from ``miss_rng``) — and the robot records the joint angles and the pose its
    controller reports there (:meth:`twin.robot.SimRobot.teach`)."""
    miss = np.zeros(3)
    if miss_rng is not None:
        miss = miss_rng.normal(0.0, teaching_error_mm * 1e-3, 3)
    T_face = facing_pose(point + miss, depth, lateral_axis=lateral_axis)
    try:
        return twin.robot.teach(T_face @ se3.invert(twin.truth.T_ee_us), label)
    except CollisionError as e:
        raise CollisionError(
            f"{e}: the probe's face cannot be {1e3 * depth:g} mm above that target without "
            "touching the phantom; a deeper target depth (protocol.target_depth_mm) leaves "
            "it room"
        ) from None


def simulate_acquisition(
    scenario: Scenario,
    twin: Twin,
    imager: SimImager,
    name: str = "sim",
    protocol_rng: np.random.Generator | None = None,
    touches: Sequence[Touch] = (),
    progress: str | None = None,
    frames_dir: Path | None = None,
    T_ee_us_coarse: NDArray[np.float64] | None = None,
) -> SimulatedAcquisition:
    """Teach, plan, check and acquire the scenario's spheres with the twin.

    Teaching is emulated from the true scene: the true probe faces the sphere at the
    protocol's target depth, off by the teaching error; the robot records what its
    controller reports there. ``protocol_rng`` replaces the teaching-error stream;
    ``touches`` go into the dataset as they are; ``progress`` names the task whose
    sweep counts :func:`bench.progress.report` receives. ``frames_dir``: each sphere's
    frames go to a file there as soon as it is scanned and the sweeps map it
    (:func:`frames_to_file`), so a long acquisition never holds its frames and the twin
    in memory at once. ``T_ee_us_coarse``: the mount the sweeps are planned through
    (a second pass: the first pass's calibration) instead of the coarse estimate drawn
    from the scenario's error.
    """
    clock_start = twin.robot.clock_s
    rngs = stage_rngs(scenario)
    if protocol_rng is not None:
        rngs["protocol"] = protocol_rng
    proto = scenario.protocol
    T_ee_us = twin.truth.T_ee_us
    coarse = coarse_estimate(T_ee_us, scenario.calibration, rngs["calibration"])
    if T_ee_us_coarse is not None:
        coarse = np.asarray(T_ee_us_coarse, dtype=float)
    depth = proto.target_depth_mm * 1e-3
    sweeps: list[Sweep] = []
    replaced: list[Replacement] = []
    truth: dict[tuple[str, int], list[NDArray[np.float64]]] = {}
    targets = acquisition_targets(scenario.phantom.kind, proto)
    total = sum(sweeps_about(proto, t) for t in targets)
    label = progress or f"{name}: acquire sweeps"
    report(label, 0, total)
    for target in targets:
        centre = twin.truth.landmarks_base[target]
        taught = teach_at(
            twin,
            centre,
            depth,
            f"taught pose at {target}",
            rngs["protocol"],
            proto.teaching_error_mm,
            lateral_axis=lateral_axis(scenario.phantom),
        )
        # Every pose checked before the arm moves; a sweep that does not clear in this
        # session is replaced by a spare of the plan file, never stopping the acquisition.
        plan, changed = clear_sweeps(
            target,
            taught.T_base_ee,
            coarse,
            proto,
            lambda sweep, _here: check_plan(twin.robot, [sweep]),
            poses=sphere_poses(proto, target),
            spares=spare_poses(proto, target),
        )
        replaced += changed
        total -= sum(1 for c in changed if c.spare is None)

        def log(planned: PlannedSweep, j: int, total: int = total) -> None:
            truth.setdefault((planned.target, planned.pose_id), []).append(
                twin.robot.truth.T_base_ee
            )
            if j == len(planned.T_base_ee) - 1:
                report(label, len(truth), total)

        scanned = acquire(twin.robot, imager, plan, on_frame=log)
        if frames_dir is not None:
            scanned = frames_to_file(scanned, frames_dir / f"{name}_{target}.npy")
        sweeps += scanned
    return SimulatedAcquisition(
        Dataset(name, tuple(sweeps), dataset_meta(scenario), tuple(touches)),
        coarse,
        {k: np.array(v) for k, v in truth.items()},
        twin.robot.clock_s - clock_start,
        tuple(replaced),
    )


def simulate_acquisition_at_gains(
    scenarios: Sequence[Scenario], name: str = "sim"
) -> tuple[Twin, list[SimulatedAcquisition]]:
    """:func:`simulate_acquisition` of each scenario of a series that differ in the
    scanner's overall gain alone (``imaging.gain_db``), from one acquisition: the twin,
    its truth, the plan and every motion do not depend on the gain, and each frame's
    echoes are simulated once and displayed at every gain
    (:class:`twin.imager.GainSeriesImager`). The twin is the highest gain's; each
    acquisition is the one :func:`simulate_acquisition` makes of its scenario (same
    poses, same noise), except for echoes that only the highest gain's trace reaches,
    beneath a lower gain's display floor (:meth:`BmodeSimulator.render_at_gains`)."""
    gains = [float(s.imaging.gain_db) for s in scenarios]
    top = scenarios[int(np.argmax(gains))]
    for s in scenarios:
        if replace(s, imaging=replace(s.imaging, gain_db=top.imaging.gain_db)) != top:
            raise ValueError(f"{s.source}: differs from {top.source} in more than the gain")
    twin = make_twin(top)
    imager = GainSeriesImager(
        twin.robot,
        twin.truth.T_ee_us,
        top.imaging,
        top.medium,
        stage_rngs(top)["imaging"],
        gains_db=gains,
    )
    acq = simulate_acquisition(top, twin, imager, name)
    delivered = imager.delivered
    del imager  # the simulator's tables, before every gain's frames are stacked
    n = sum(s.n_frames for s in acq.dataset.sweeps)
    series = []
    for g in gains:
        frames = delivered.pop(g)
        if len(frames) != n:  # every sweep's frames, and no other
            raise RuntimeError(f"gain {g:g} dB: {len(frames)} frames for {n} acquired")
        sweeps, i = [], 0
        for sweep in acq.dataset.sweeps:
            sweeps.append(replace(sweep, images=np.array(frames[i : i + sweep.n_frames])))
            i += sweep.n_frames
        series.append(replace(acq, dataset=replace(acq.dataset, sweeps=tuple(sweeps))))
    return twin, series


def dataset_meta(scenario: Scenario) -> dict[str, float]:
    """The acquisition settings a simulated dataset carries for its reader."""
    return {
        "temperature_c": scenario.medium.temperature_c,
        "assumed_speed_m_s": scenario.imaging.assumed_speed_m_s,
        "sphere_radius_mm": stated_radius(scenario) * 1e3,
    }


def twin_nwire_phantom(twin) -> NWirePhantom:
    """What the pipeline knows of the twin's N-wire phantom: its CAD patterns (three
    wires each, in the phantom's order), its pose unknown (a robot rig)."""
    wires = twin.phantom_cad.wires
    patterns = tuple(
        NWirePattern(tuple(NWire(w.name, w.front, w.back) for w in wires[k : k + 3]))  # type: ignore[arg-type]
        for k in range(0, len(wires), 3)
    )
    return NWirePhantom(patterns, None)


def acquisition_info(scenario: Scenario, twin, T_ee_us_coarse: Array) -> AcquisitionInfo:
    """What a twin acquisition's dataset records besides its sweeps: what the pipeline
    knows (CAD landmarks, coarse mount, settings), never the truth."""
    nwire = twin_nwire_phantom(twin) if scenario.phantom.kind == "nwire" else None
    wire = None
    if scenario.phantom.kind == "wire":
        (w,) = twin.phantom_cad.wires
        wire = WirePhantom(NWire(w.name, w.front, w.back))
    cone_tip = None
    if scenario.phantom.kind == "cone":
        cone_tip = ConeTipPhantom(np.asarray(twin.phantom_cad.landmarks["apex"], dtype=float))
    return AcquisitionInfo(
        T_ee_us_coarse=np.asarray(T_ee_us_coarse, dtype=float),
        landmarks={k: np.asarray(v, dtype=float) for k, v in twin.phantom_cad.landmarks.items()},
        sphere_radius_mm=stated_radius(scenario) * 1e3,
        temperature_c=scenario.medium.temperature_c,
        assumed_speed_m_s=scenario.imaging.assumed_speed_m_s,
        sound_speed_correction=scenario.imaging.sound_speed_correction,
        medium=scenario.medium.kind,
        stylus_tip_cad_mm=tuple(scenario.evaluation.stylus_tip_cad_mm),
        source="twin",
        target_depth_mm=scenario.protocol.target_depth_mm,
        extra={"scenario": scenario.source, "seed": scenario.seed},
        nwire=nwire,
        wire=wire,
        cone_tip=cone_tip,
    )


def image_meta(scenario: Scenario) -> dict[str, Any]:
    """The probe settings a dataset's manifest keeps (for the reader's information)."""
    im = scenario.imaging
    H, W = im.image_shape
    return {
        "width_px": int(W),
        "height_px": int(H),
        "pixel_spacing_mm": [float(v) for v in im.pixel_spacing_mm],
        "depth_mm": float(im.depth_mm),
        "f_mhz": float(im.f_mhz),
        "gain_db": float(im.gain_db),
    }


def save_dataset(
    directory: str | os.PathLike[str], scenario: Scenario, twin, acq: SimulatedAcquisition
) -> Path:
    """Write a twin acquisition in the dataset format (:mod:`calib.files.dataset`).

    The twin has no acquisition clock; each frame's timestamp is its index in the
    dataset times a nominal frame period, so timestamps increase through the dataset.
    """
    writer = DatasetWriter(
        directory,
        acq.dataset.name,
        acquisition_info(scenario, twin, acq.T_ee_us_coarse),
        image_meta(scenario),
    )
    period = 0.5  # s per frame: settle and grab
    n = 0
    for sweep in acq.dataset.sweeps:
        writer.add_sweep(sweep, timestamps=period * (n + np.arange(sweep.n_frames)))
        n += sweep.n_frames
    writer.add_touches(acq.dataset.touches)
    writer.finish()
    return Path(directory)
