"""Experiment assembly: from a validated scenario to the twin (and, later, the pipeline)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.protocol import PlannedSweep, acquire, check_plan, facing_pose, plan_sweeps
from calib.records import Dataset, Sweep
from calib.settings import CalibrationConfig
from twin.imager import SimImager
from twin.world import Twin, build_twin

from .scenario import Scenario

__all__ = [
    "RNG_STREAMS",
    "SimulatedAcquisition",
    "coarse_estimate",
    "make_imager",
    "make_twin",
    "simulate_acquisition",
    "stage_rngs",
]

#: One generator per stage, spawned from the scenario seed in this order. Appending a
#: stream keeps every earlier stream (and so every earlier result) unchanged.
RNG_STREAMS = ("dh", "phantom", "joints", "imaging", "protocol", "calibration")


def stage_rngs(scenario: Scenario) -> dict[str, np.random.Generator]:
    """The scenario's per-stage generators by name (DESIGN.md §3)."""
    return dict(zip(RNG_STREAMS, scenario.rngs(len(RNG_STREAMS)), strict=True))


def make_twin(scenario: Scenario) -> Twin:
    """Build the twin of a scenario: truth drawn from its seed."""
    rngs = stage_rngs(scenario)
    return build_twin(
        scenario.robot,
        scenario.tools,
        scenario.phantom,
        rngs["dh"],
        rngs["phantom"],
        rngs["joints"],
    )


def make_imager(scenario: Scenario, twin: Twin) -> SimImager:
    """The simulated scanner of a scenario, looking through the twin's true probe mount."""
    return SimImager(
        twin.robot,
        twin.truth.T_ee_us,
        scenario.imaging,
        scenario.medium,
        stage_rngs(scenario)["imaging"],
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


def simulate_acquisition(
    scenario: Scenario, twin: Twin, imager: SimImager, name: str = "sim"
) -> SimulatedAcquisition:
    """Teach, plan, check and acquire the scenario's spheres with the twin.

    Teaching is emulated from the true scene: the true probe faces the sphere at the
    protocol's target depth, off by the teaching error; the robot records what its
    controller reports there.
    """
    rngs = stage_rngs(scenario)
    proto = scenario.protocol
    T_ee_us = twin.truth.T_ee_us
    coarse = coarse_estimate(T_ee_us, scenario.calibration, rngs["calibration"])
    depth = proto.target_depth_mm * 1e-3
    sweeps: list[Sweep] = []
    truth: dict[tuple[str, int], list[NDArray[np.float64]]] = {}
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

        sweeps += acquire(twin.robot, imager, plan, on_frame=log)
    meta = {
        "temperature_c": scenario.medium.temperature_c,
        "assumed_speed_m_s": scenario.imaging.assumed_speed_m_s,
        "sphere_radius_mm": scenario.phantom.sphere_radius_mm,
    }
    return SimulatedAcquisition(
        Dataset(name, tuple(sweeps), meta),
        coarse,
        {k: np.array(v) for k, v in truth.items()},
    )
