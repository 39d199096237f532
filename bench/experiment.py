"""Experiment assembly: from a validated scenario to the twin (and, later, the pipeline)."""

from __future__ import annotations

import numpy as np

from twin.imager import SimImager
from twin.world import Twin, build_twin

from .scenario import Scenario

__all__ = ["RNG_STREAMS", "make_imager", "make_twin", "stage_rngs"]

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
