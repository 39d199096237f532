"""Experiment assembly: from a validated scenario to the twin (and, later, the pipeline)."""

from __future__ import annotations

import contextlib
import ctypes
import gc
import mmap
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from threadpoolctl import threadpool_limits

from calib import se3
from calib.image import pixel_to_us
from calib.protocol import (
    PlannedSweep,
    PlannedTouch,
    acquire,
    acquire_touches,
    check_plan,
    facing_pose,
    in_plane_offsets,
    orientation_offsets,
    plan_sweeps,
    touch_plan,
)
from calib.records import Dataset, Sweep, Touch
from calib.settings import CalibrationConfig
from sim_us.materials import water_speed_m_s
from twin.arm_errors import robot_stream
from twin.imager import SimImager
from twin.touch import SimTouchGuide
from twin.world import Twin, build_twin

from .progress import report
from .scenario import Scenario
from .sessions import stage_rngs

__all__ = [
    "SimulatedAcquisition",
    "axial_scale",
    "coarse_estimate",
    "frames_to_file",
    "image_points",
    "make_imager",
    "make_twin",
    "one_blas_thread",
    "simulate_acquisition",
    "simulate_touches",
]


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

    ``T_base_ee_true[(target, pose_id)]`` holds the true flange pose of every frame.
    """

    dataset: Dataset
    T_ee_us_coarse: NDArray[np.float64]
    T_base_ee_true: dict[tuple[str, int], NDArray[np.float64]]


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
    plan = touch_plan(sorted(vertices), scenario.protocol, lean)
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
        return acquire_touches(twin.robot, guide, plan, on_touch)
    finally:
        twin.mount("probe")


def simulate_acquisition(
    scenario: Scenario,
    twin: Twin,
    imager: SimImager,
    name: str = "sim",
    protocol_rng: np.random.Generator | None = None,
    touches: Sequence[Touch] = (),
    progress: str | None = None,
    frames_dir: Path | None = None,
) -> SimulatedAcquisition:
    """Teach, plan, check and acquire the scenario's spheres with the twin.

    Teaching is emulated from the true scene: the true probe faces the sphere at the
    protocol's target depth, off by the teaching error; the robot records what its
    controller reports there. ``protocol_rng`` replaces the teaching-error stream;
    ``touches`` go into the dataset as they are; ``progress`` names the task whose
    sweep counts :func:`bench.progress.report` receives. ``frames_dir``: each sphere's
    frames go to a file there as soon as it is scanned and the sweeps map it
    (:func:`frames_to_file`), so a long acquisition never holds its frames and the twin
    in memory at once.
    """
    rngs = stage_rngs(scenario)
    if protocol_rng is not None:
        rngs["protocol"] = protocol_rng
    proto = scenario.protocol
    T_ee_us = twin.truth.T_ee_us
    coarse = coarse_estimate(T_ee_us, scenario.calibration, rngs["calibration"])
    depth = proto.target_depth_mm * 1e-3
    sweeps: list[Sweep] = []
    truth: dict[tuple[str, int], list[NDArray[np.float64]]] = {}
    per_sphere = len(orientation_offsets(proto.rotation_deg)) * len(
        in_plane_offsets(proto.translation_mm)
    )
    total = len(proto.spheres) * per_sphere
    label = progress or f"{name}: acquire sweeps"
    report(label, 0, total)
    for index in proto.spheres:
        target = f"sphere_{index}"
        centre = twin.truth.landmarks_base[target]
        miss = rngs["protocol"].normal(0.0, proto.teaching_error_mm * 1e-3, 3)
        T_face = facing_pose(centre + miss, depth)
        taught = twin.robot.teach(T_face @ se3.invert(T_ee_us), f"taught pose at {target}")
        plan = plan_sweeps(target, taught.T_base_ee, coarse, proto)
        check_plan(twin.robot, plan)

        def log(planned: PlannedSweep, j: int) -> None:
            truth.setdefault((planned.target, planned.pose_id), []).append(
                twin.robot.truth.T_base_ee
            )
            if j == len(planned.T_base_ee) - 1:
                report(label, len(truth), total)

        scanned = acquire(twin.robot, imager, plan, on_frame=log)
        if frames_dir is not None:
            scanned = frames_to_file(scanned, frames_dir / f"{name}_{target}.npy")
        sweeps += scanned
    meta = {
        "temperature_c": scenario.medium.temperature_c,
        "assumed_speed_m_s": scenario.imaging.assumed_speed_m_s,
        "sphere_radius_mm": scenario.phantom.sphere_radius_mm,
    }
    return SimulatedAcquisition(
        Dataset(name, tuple(sweeps), meta, tuple(touches)),
        coarse,
        {k: np.array(v) for k, v in truth.items()},
    )


def frames_to_file(sweeps: Sequence[Sweep], path: Path) -> list[Sweep]:
    """Write the sweeps' frames (all of one shape) to ``path`` (``.npy``) and return the
    sweeps with their frames mapped from it (:func:`with_frames`)."""
    shape = (len(sweeps), *sweeps[0].images.shape)
    for s in sweeps:  # checked before anything is written
        if s.images.shape != shape[1:]:
            raise ValueError(f"sweep {s.pose_id}: frames {s.images.shape}, not {shape[1:]}")
    # Written, not through a writable map: a map takes a page fault per 4 KiB written
    # (≈ 1 s of CPU per dataset's 577 MB).
    with open(path, "wb") as f:
        header = {"descr": "|u1", "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(f, header)
        for s in sweeps:
            f.write(np.ascontiguousarray(s.images, dtype=np.uint8).data)
    return with_frames(sweeps, path)


def with_frames(sweeps: Sequence[Sweep], path: Path) -> list[Sweep]:
    """The sweeps with their frames mapped from the ``.npy`` file ``path`` (one frame
    stack per sweep, in order), copy-on-write: the pages are the page cache's, shared by
    every process that maps them, read as the pipeline touches them, and writable, so the
    localizer's compiled kernels take them as any frame array. Nothing else changes."""
    frames = np.load(path, mmap_mode="c")
    return [replace(s, images=frames[i]) for i, s in enumerate(sweeps)]


def drop_frame_pages(sweeps: Iterable[Sweep]) -> None:
    """Let go of the resident pages of the sweeps' frames mapped from scratch files
    (:func:`with_frames`), e.g. between folds that use different spheres: the frames
    stay valid, and the pages a later step touches are read back from the page cache
    (a minor fault each). Frames held in memory are left alone."""
    maps = {}
    for s in sweeps:
        m = getattr(s.images, "_mmap", None)
        if m is not None:
            maps[id(m)] = m
    for m in maps.values():
        m.madvise(mmap.MADV_DONTNEED)


def without_frames(sweeps: Sequence[Sweep]) -> tuple[Sweep, ...]:
    """The sweeps with their frames left out (while a file holds them), to cross a pipe."""
    empty = np.zeros((0, 0, 0), dtype=np.uint8)
    return tuple(replace(s, images=empty) for s in sweeps)


def true_centre_in_sweep(
    acq: SimulatedAcquisition, truth, target: str, sweep: Sweep
) -> NDArray[np.float64]:
    """Truth: a sphere's centre (3,) in the sweep's true reference frame (the true
    flange pose of its reference frame and the true mount), where a localization of it
    should land."""
    T = acq.T_base_ee_true[(target, sweep.pose_id)][sweep.reference_index] @ truth.T_ee_us
    return se3.apply(se3.invert(T), truth.landmarks_base[target])


def one_blas_thread() -> threadpool_limits:
    """Limit this process's BLAS (OpenBLAS) to one thread, until the returned limiter
    is exited (a ``with`` block) or for good.

    For a process that shares the cores with a pool's workers, or is one of them: an
    OpenBLAS thread per core in each process oversubscribes the cores, and its threads
    spin waiting for each other on the tiny matrices of the pipeline (the DH
    refinement's SVDs took 9.7 s of a paper run instead of 1 s)."""
    return threadpool_limits(1, user_api="blas")


def release_memory() -> None:
    """Collect garbage and give the heap's freed pages back to the system (glibc
    ``malloc_trim``).

    A pool worker's frames are freed when its task ends, but glibc keeps freed heap
    memory for reuse, so an idle worker went on holding ≈ 0.3-0.9 GB (measured) until
    the pool closed; with three workers that decided the run's peak memory."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def speed_ratio(
    correction: bool, medium: str, temperature_c: float, assumed_speed_m_s: float
) -> float:
    """c_medium / c_assumed when the speed-of-sound correction is on (the pipeline knows
    the water temperature a user reads off a thermometer), else 1; a medium other than
    water is taken at 1540 m/s."""
    if not correction:
        return 1.0
    c = water_speed_m_s(temperature_c) if medium == "water" else 1540.0
    return c / assumed_speed_m_s


def axial_scale(scenario: Scenario) -> float:
    """The axial spacing's correction factor of a scenario (:func:`speed_ratio`)."""
    return speed_ratio(
        scenario.imaging.sound_speed_correction,
        scenario.medium.kind,
        scenario.medium.temperature_c,
        scenario.imaging.assumed_speed_m_s,
    )


def image_points(scenario: Scenario, n: int = 21) -> NDArray[np.float64]:
    """An n × n grid of points (n², 3) covering the image, metres in the ``us`` frame."""
    probe = scenario.imaging
    spacing = (probe.width_mm * 1e-3 / (n - 1), probe.depth_mm * 1e-3 / (n - 1))
    P = pixel_to_us(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), n, spacing)
    return P.reshape(-1, 3)
