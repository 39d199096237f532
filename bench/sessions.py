"""The random streams of a simulated session, declared in one place.

Every random draw of the twin comes from a generator derived from the scenario's seed
(``np.random.SeedSequence(seed, spawn_key=...)``): the same seed gives the same results,
and a stream added later leaves every other stream, and so every earlier result,
unchanged. The spawn keys of the bench are named here; the twin's own (the robot's
errors, the printed phantom) are in :mod:`twin.arm_errors` and :mod:`twin.printing`, and
``tests/test_sessions.py`` checks that no two streams share a key.

- **Stages** (:func:`stage_rngs`): the scenario's per-stage generators, spawned from the
  seed in the order of :data:`RNG_STREAMS`.
- **Datasets** (:func:`dataset_rngs`): each dataset of the evaluation (a session: new
  joint, imaging, teaching and touch noise and phantom placement; the same robot, print
  and mount) has key ``DATASET_KEY + index``; the reconstruction's scans have session
  indices past any evaluation dataset's (:data:`SESSIONS`).
- **Placements** (:func:`dataset_scenario`, :func:`scan_scenario`): where the phantom
  was put back for a dataset, and how far it moved between the touches and the sweeps.
- **Remount** (:data:`REMOUNT_KEY`) and the **touch guide** of the hardware dry run
  (:data:`TOUCH_GUIDE_KEY`).
- **Other sessions** a plan is checked in (:data:`PLAN_SESSIONS_KEY`): the taught pose
  and coarse mount another day may bring (:mod:`bench.jobs.plan_optimize`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .config.scenario import MAX_DATASETS, Scenario

__all__ = [
    "DATASET_KEY",
    "DATASET_STREAMS",
    "MAX_DATASETS",
    "PLAN_SESSIONS_KEY",
    "REMOUNT_KEY",
    "RNG_STREAMS",
    "SESSIONS",
    "SESSION_SHIFT_KEY",
    "STREAM_KEYS",
    "TOUCH_GUIDE_KEY",
    "dataset_rngs",
    "dataset_scenario",
    "scan_scenario",
    "stage_rngs",
    "stream",
]

#: Spawn key of the evaluation's dataset 0; dataset ``i`` has ``DATASET_KEY + i``.
DATASET_KEY = 100
#: Session indices (``dataset_rngs``) of the reconstruction's scans, past every
#: evaluation dataset's: one per phantom; the re-calibration scan of sphere N has
#: ``recalibration + N``.
SESSIONS = {"cone": 51, "prism": 52, "recalibration": 60}
#: Spawn key of the remount's own stream (the probe taken off and put back).
REMOUNT_KEY = 150
#: Spawn key of the hardware dry run's simulated touch guide.
TOUCH_GUIDE_KEY = 300
#: Spawn key of the phantom's displacement between a dataset's touches and its sweeps
#: (one stream per dataset: ``(SESSION_SHIFT_KEY, index)``).
SESSION_SHIFT_KEY = 430
#: Spawn key of the other sessions a plan is checked in (their teaching error and
#: coarse mount).
PLAN_SESSIONS_KEY = 510

#: Every first spawn key the bench uses, by name (the dataset keys as their range).
STREAM_KEYS = {
    "datasets": range(DATASET_KEY, DATASET_KEY + MAX_DATASETS),
    "cone": DATASET_KEY + SESSIONS["cone"],
    "prism": DATASET_KEY + SESSIONS["prism"],
    # the re-calibration scans of spheres 1–4
    "recalibration": range(
        DATASET_KEY + SESSIONS["recalibration"] + 1, DATASET_KEY + SESSIONS["recalibration"] + 5
    ),
    "remount": REMOUNT_KEY,
    "touch_guide": TOUCH_GUIDE_KEY,
    "session_shift": SESSION_SHIFT_KEY,
    "plan_sessions": PLAN_SESSIONS_KEY,
}


def stream(seed: int, *key: int) -> np.random.Generator:
    """The generator of spawn key ``key`` under ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


#: One generator per stage, spawned from the scenario seed in this order. Appending a
#: stream keeps every earlier stream (and so every earlier result) unchanged.
RNG_STREAMS = ("dh", "phantom", "joints", "imaging", "protocol", "calibration")


def stage_rngs(scenario: Scenario) -> dict[str, np.random.Generator]:
    """The scenario's per-stage generators by name (DESIGN.md §3)."""
    return dict(zip(RNG_STREAMS, scenario.rngs(len(RNG_STREAMS)), strict=True))


#: Streams of each dataset of the evaluation (new session: new joint, imaging, teaching
#: and touch noise, new phantom placement; same robot, phantom print and probe mount).
DATASET_STREAMS = ("joints", "imaging", "protocol", "touch_joints", "touch_contact", "placement")


def dataset_rngs(scenario: Scenario, index: int) -> dict[str, np.random.Generator]:
    """Per-dataset generators of the evaluation's ``index``-th dataset (independent of the
    scenario's stage streams and of each other)."""
    rng = stream(scenario.seed, DATASET_KEY + index)
    return dict(zip(DATASET_STREAMS, rng.spawn(len(DATASET_STREAMS)), strict=True))


def dataset_scenario(scenario: Scenario, index: int) -> Scenario:
    """The scenario of the evaluation's ``index``-th dataset: the first keeps the
    phantom placement, later ones put it back up to ± ``placement_shift_mm`` off in x and
    y and turned up to ± ``placement_rotation_deg`` about the vertical."""
    if index == 0:
        return scenario
    ev = scenario.evaluation
    rng = dataset_rngs(scenario, index)["placement"]
    dx, dy = rng.uniform(-1, 1, 2) * ev.placement_shift_mm
    dz_rot = rng.uniform(-1, 1) * ev.placement_rotation_deg
    ph = scenario.phantom
    x, y, z = ph.position_mm
    rx, ry, rz = ph.rotation_deg
    phantom = replace(ph, position_mm=(x + dx, y + dy, z), rotation_deg=(rx, ry, rz + dz_rot))
    return replace(scenario, phantom=phantom)


def scan_scenario(scenario: Scenario, index: int) -> Scenario:
    """The scenario of the ``index``-th dataset's sweeps: its touch-time placement
    (:func:`dataset_scenario`) moved by ``evaluation.session_shift_mm`` (1 σ per
    horizontal axis, its own stream), or unchanged when that is 0."""
    sc = dataset_scenario(scenario, index)
    sigma = scenario.evaluation.session_shift_mm
    if sigma == 0.0:
        return sc
    dx, dy = stream(scenario.seed, SESSION_SHIFT_KEY, index).normal(0.0, sigma, 2)
    x, y, z = sc.phantom.position_mm
    return replace(sc, phantom=replace(sc.phantom, position_mm=(x + dx, y + dy, z)))
