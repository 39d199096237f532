"""The sequential acquisition on the twin (``uscal run --until-rotation-deg X
--until-translation-mm Y``): each next sweep is the candidate that adds most to the
sweeps localized so far (:func:`calib.acquisition.planning.next_sweep`), and a sphere's
scan stops as soon as its predicted 1 σ of ``T_ee_us``
(:func:`calib.acquisition.planning.predict`, with the session's shared offset) is within
both limits — or at ``max_sweeps``.

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

from calib.acquisition.planning import (
    Candidates,
    SweepPose,
    bias_covariance,
    image_metric,
    next_sweep,
    predict,
)
from calib.acquisition.protocol import PlannedSweep, acquire, check_plan, plan_sweeps
from calib.localize import localize_sphere
from calib.records import Dataset, Sweep
from twin.imager import SimImager
from twin.world import Twin

from .acquire_sim import SimulatedAcquisition, coarse_estimate, dataset_meta
from .candidates import candidate_sweeps, clear, observations, taught_target
from .config.method import axial_scale, image_points, stated_radius
from .config.scenario import Scenario
from .progress import report
from .sessions import stage_rngs

__all__ = ["Chooser", "SphereScan", "StopRule", "acquire_until"]

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


class Chooser:
    """One sphere's sequential choice: the candidates' information, the sweeps tried and
    those localized; :meth:`next` names the next sweep, :meth:`update` takes the
    localizations of every sweep so far and says whether the rule is met."""

    def __init__(self, target: str, cands: Candidates, poses, rule: StopRule, M, bias) -> None:
        self.target, self.cands, self.poses, self.rule = target, cands, list(poses), rule
        self.M, self.bias = M, bias
        self.tried: list[int] = []
        self.skipped: list[int] = []  # chosen, then left out unacquired (a transit)
        self.localized: list[int] = []
        self.history: list[dict[str, float]] = []
        self.prediction = None
        self.reached = False

    def more(self) -> bool:
        """Whether another sweep may be taken."""
        untried = len(self.tried) + len(self.skipped) < len(self.poses)
        left = len(self.tried) < self.rule.max_sweeps and untried
        return left and not self.reached

    def next(self) -> SweepPose:
        k = next_sweep(
            self.cands, self.localized, exclude=self.tried + self.skipped, criterion="D", M=self.M
        )
        self.tried.append(k)
        return self.poses[k]

    def skip(self) -> None:
        """The sweep :meth:`next` just named is not acquired after all."""
        self.skipped.append(self.tried.pop())

    def update(self, accepted: list[bool]) -> bool:
        """The localizations of every sweep tried so far, in order; True once the
        predicted 1 σ is within the rule's limits."""
        self.localized = [k for k, ok in zip(self.tried, accepted, strict=True) if ok]
        if len(self.localized) < self.rule.min_sweeps:
            return False
        self.prediction = p = predict(self.cands, self.localized, self.M, bias=self.bias)
        self.history.append(
            {"sweeps": len(self.tried), "rotation_deg": p.rotation_deg,
             "translation_mm": p.translation_mm}
        )  # fmt: skip
        self.reached = p.rotation_deg <= self.rule.rotation_deg and (
            p.translation_mm <= self.rule.translation_mm
        )
        return self.reached

    def scan(self) -> SphereScan:
        p = self.prediction
        return SphereScan(
            self.target,
            len(self.tried),
            len(self.localized),
            p.rotation_deg if p else float("nan"),
            p.translation_mm if p else float("nan"),
            self.reached,
            self.history,
        )


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
    radius = stated_radius(scenario)
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
        sphere = taught_target(scenario, twin, coarse, target, 0, rngs["protocol"])
        found, _ = candidate_sweeps(scenario, twin, [sphere], coarse, lambda s: dense, True)
        cands = observations(scenario, coarse, [sphere], found, False)
        chooser = Chooser(target, cands, [pose for _, pose, _ in found], rule, M, bias)
        poses: list[SweepPose] = []
        mine: list[Sweep] = []
        while chooser.more():
            pose = chooser.next()
            # The new sweep, with its transit from the previous one's last frame, which
            # keeps the clearance too (else the next best sweep is taken instead).
            planned: PlannedSweep = plan_sweeps(
                target, sphere.taught, coarse, proto, poses=[*poses, pose]
            )[-1]
            if len(planned.approach) and not clear(scenario, twin, planned.approach):
                chooser.skip()
                continue
            poses.append(pose)
            check_plan(twin.robot, [planned])

            def log(p: PlannedSweep, j: int) -> None:
                truth.setdefault((p.target, p.pose_id), []).append(twin.robot.truth.T_base_ee)

            (sweep,) = acquire(twin.robot, imager, [planned], on_frame=log)
            mine.append(sweep)
            report(label, len(sweeps) + len(mine), total)
            # Every sweep of the sphere so far, localized together (their agreement is
            # part of the test); a sweep counts once it is accepted.
            locs = localize_sphere(mine, None, radius, scenario.localization, axial_scale=scale)
            chooser.update([loc.accepted for loc in locs])
        sweeps += mine
        scans.append(chooser.scan())
    acq = SimulatedAcquisition(
        Dataset(name, tuple(sweeps), dataset_meta(scenario)),
        coarse,
        {k: np.array(v) for k, v in truth.items()},
        twin.robot.clock_s - clock_start,
    )
    return acq, scans
