"""``uscal plan``: a scenario's acquisition plan checked and scored before anything moves.

For every sphere: teach (emulated), plan the sweeps, check every frame pose for reach and
collisions, and score the plan's information about ``T_ee_us`` for a sphere (point)
constraint and for a wire (line) constraint through the same poses (paper, "Geometric
Analysis of Calibration Targets"). Nothing is imaged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib import se3
from calib.acquisition.observability import (
    Observability,
    information,
    jacobians,
    observability,
    planned_observations,
)
from calib.acquisition.protocol import check_plan, plan_sweeps

from ..acquire_sim import coarse_estimate, make_twin, teach_at
from ..config.geometry import acquisition_targets, lateral_axis
from ..config.scenario import Scenario
from ..sessions import stage_rngs

__all__ = ["PlanReport", "plan_report"]


@dataclass(frozen=True, eq=False)
class PlanReport:
    """Per sphere: the number of frame poses checked, and the sphere and wire scores."""

    sphere: str
    n_sweeps: int
    n_poses: int
    point: Observability
    wire: Observability
    wire_direction: np.ndarray


def plan_report(scenario: Scenario, noise_mm: float = 0.1) -> list[PlanReport]:
    """Plan, check and score the scenario's sphere acquisitions (see the module doc)."""
    rngs = stage_rngs(scenario)
    twin = make_twin(scenario)
    proto = scenario.protocol
    coarse = coarse_estimate(twin.truth.T_ee_us, scenario.calibration, rngs["calibration"])
    depth = proto.target_depth_mm * 1e-3
    out = []
    for name in acquisition_targets(scenario.phantom.kind, scenario.protocol):
        taught = teach_at(
            twin,
            twin.truth.landmarks_base[name],
            depth,
            f"taught at {name}",
            lateral_axis=lateral_axis(scenario.phantom),
        )
        plan = plan_sweeps(name, taught.T_base_ee, coarse, proto)
        check_plan(twin.robot, plan)
        # The plan as the pipeline sees it: the sphere where the coarse estimate puts it.
        T_ref = np.array([p.T_base_ee[len(p.T_base_ee) // 2] for p in plan])
        target = se3.apply(taught.T_base_ee @ coarse, np.array([0.0, depth, 0.0]))
        P = planned_observations(T_ref, coarse, target)
        G = jacobians(T_ref, coarse, P)
        wire = (taught.T_base_ee @ coarse)[:3, 2]  # perpendicular to the nominal image
        out.append(
            PlanReport(
                name,
                len(plan),
                sum(len(p.T_base_ee) for p in plan),
                observability(information(G), noise_mm=noise_mm),
                observability(information(G, line_direction=wire), noise_mm=noise_mm),
                wire,
            )
        )
    return out
