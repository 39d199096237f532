"""The sequential acquisition on the twin (``uscal run --until-rotation-deg X
--until-translation-mm Y``): each next sweep is the candidate that adds most to the
sweeps localized so far (:func:`calib.planning.next_sweep`), and a sphere's scan stops as
soon as its predicted 1 σ of ``T_ee_us`` (:func:`calib.planning.predict`, with the
session's shared offset) is within both limits — or at ``max_sweeps``.

Every sweep is localized as soon as it is acquired (with the sweeps of its sphere so
far, whose agreement the localizer checks); a rejected sweep adds nothing and its pose
is not tried again. The sweeps are the twin's, as in :func:`bench.acquire_sim.
simulate_acquisition`: taught with the teaching error, moved through transits, timed by
the controller's clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.localize import localize_sphere
from calib.planning import bias_covariance, image_metric, next_sweep, predict
from calib.protocol import PlannedSweep, acquire, check_plan, plan_sweeps
from calib.records import Dataset, Sweep
from twin.imager import SimImager
from twin.world import Twin

from .acquire_sim import SimulatedAcquisition, coarse_estimate, teach_at
from .candidates import PlanSphere, candidate_sweeps, observations
from .config.scenario import Scenario
from .pipeline import axial_scale, image_points
from .progress import report
from .sessions import stage_rngs

__all__ = ["StopRule", "acquire_until"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class StopRule:
    """When a sphere's scan stops: its predicted 1 σ of rotation (°) and translation
    (mm) both within the limits, after at least ``min_sweeps`` localized sweeps; or
    after ``max_sweeps`` sweeps, whatever the prediction."""

    rotation_deg: float = float("inf")
    translation_mm: float = float("inf")
    max_sweeps: int = 45
    min_sweeps: int = 6


@dataclass(frozen=True)
class SphereScan:
    """How a sphere's sequential scan went (``metrics.json``'s ``acquisition.
    sequential``)."""

    target: str
    sweeps: int
    localized: int
    rotation_deg: float
    translation_mm: float
    reached: bool
    history: list[dict[str, float]] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            "sweeps": self.sweeps,
            "localized": self.localized,
            "predicted_rotation_deg": self.rotation_deg,
            "predicted_translation_mm": self.translation_mm,
            "reached": self.reached,
            "history": self.history,
        }


def acquire_until(
    scenario: Scenario,
    twin: Twin,
    imager: SimImager,
    rule: StopRule,
    name: str = "sim",
    progress: str | None = None,
) -> tuple[SimulatedAcquisition, list[SphereScan]]:
    """Acquire the scenario's spheres one chosen sweep at a time (see the module doc)."""
    clock_start = twin.robot.clock_s
    rngs = stage_rngs(scenario)
    proto = scenario.protocol
    coarse = coarse_estimate(twin.truth.T_ee_us, scenario.calibration, rngs["calibration"])
    depth = proto.target_depth_mm * 1e-3
    radius = scenario.phantom.sphere_radius_mm * 1e-3
    scale = axial_scale(scenario)
    M = image_metric(coarse, image_points(scenario))
    bias = bias_covariance(coarse, scenario.planning.localization_bias_mm)
    dense = scenario.planning.candidates()
    label = progress or f"{name}: acquire sweeps"
    total = rule.max_sweeps * len(proto.spheres)
    sweeps: list[Sweep] = []
    truth: dict[tuple[str, int], list[Array]] = {}
    scans = []
    for index in proto.spheres:
        target = f"sphere_{index}"
        taught = teach_at(
            twin,
            twin.truth.landmarks_base[target],
            depth,
            f"taught pose at {target}",
            rngs["protocol"],
            proto.teaching_error_mm,
        )
        centre = se3.apply(taught.T_base_ee @ coarse, np.array([0.0, depth, 0.0]))
        sphere = PlanSphere(target, 0, taught.T_base_ee, centre)
        found, _ = candidate_sweeps(scenario, twin, [sphere], coarse, lambda s: dense, True)
        cands = observations(scenario, coarse, [sphere], found, False)
        poses, mine, tried, localized, history = [], [], [], [], []
        reached = False
        prediction = None
        while len(poses) < min(rule.max_sweeps, len(found)):
            k = next_sweep(cands, localized, tried, "D", M)
            tried.append(k)
            poses.append(found[k][1])
            # The new sweep, with its transit from the previous one's last frame.
            planned: PlannedSweep = plan_sweeps(target, taught.T_base_ee, coarse, proto, poses)[-1]
            check_plan(twin.robot, [planned])

            def log(p: PlannedSweep, j: int) -> None:
                truth.setdefault((p.target, p.pose_id), []).append(twin.robot.truth.T_base_ee)

            (sweep,) = acquire(twin.robot, imager, [planned], on_frame=log)
            mine.append(sweep)
            report(label, len(sweeps) + len(mine), total)
            # Every sweep of the sphere so far, localized together (their agreement is
            # part of the test); a sweep counts once it is accepted.
            locs = localize_sphere(mine, None, radius, scenario.localization, scale)
            localized = [tried[j] for j, loc in enumerate(locs) if loc.accepted]
            if len(localized) < rule.min_sweeps:
                continue
            prediction = predict(cands, localized, M, bias)
            history.append(
                {
                    "sweeps": len(mine),
                    "rotation_deg": prediction.rotation_deg,
                    "translation_mm": prediction.translation_mm,
                }
            )
            if (
                prediction.rotation_deg <= rule.rotation_deg
                and prediction.translation_mm <= rule.translation_mm
            ):
                reached = True
                break
        sweeps += mine
        scans.append(
            SphereScan(
                target,
                len(mine),
                len(localized),
                prediction.rotation_deg if prediction else float("nan"),
                prediction.translation_mm if prediction else float("nan"),
                reached,
                history,
            )
        )
    meta = {
        "temperature_c": scenario.medium.temperature_c,
        "assumed_speed_m_s": scenario.imaging.assumed_speed_m_s,
        "sphere_radius_mm": scenario.phantom.sphere_radius_mm,
    }
    acq = SimulatedAcquisition(
        Dataset(name, tuple(sweeps), meta),
        coarse,
        {k: np.array(v) for k, v in truth.items()},
        twin.robot.clock_s - clock_start,
    )
    return acq, scans
