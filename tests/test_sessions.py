"""The random streams of a session: every spawn key declared once, none shared."""

from __future__ import annotations

import numpy as np
import pytest

from bench import sessions
from twin import arm_errors, printing


def _keys(value) -> list[int]:
    return list(value) if isinstance(value, range) else [value]


def test_no_two_streams_share_a_spawn_key():
    """The bench's keys (datasets as their range, the reconstruction's sessions, the
    remount, the touch guide, the session shift) and the twin's (the robot's errors, the
    printed phantom) are all different: two stages drawing from one stream would make
    their errors correlated without anyone having asked for it."""
    declared = {name: _keys(v) for name, v in sessions.STREAM_KEYS.items()}
    declared["robot"] = [arm_errors.ROBOT_STREAM_KEY]
    declared["printing"] = [
        printing.ROUGHNESS_SPAWN_KEY,
        printing.SHAPE_SPAWN_KEY,
        printing.ROUNDNESS_SPAWN_KEY,
        printing.SAG_SPAWN_KEY,
    ]
    seen: dict[int, str] = {}
    for name, keys in declared.items():
        for k in keys:
            assert k not in seen, f"spawn key {k}: {seen.get(k)} and {name}"
            seen[k] = name
    assert len(seen) > 60


def test_a_dataset_stream_is_its_own_and_repeatable():
    from bench.config.scenario import load_scenario

    s = load_scenario("scenarios/quick.yaml", check_reach=False)
    a = sessions.dataset_rngs(s, 1)["imaging"].normal(size=4)
    b = sessions.dataset_rngs(s, 1)["imaging"].normal(size=4)
    c = sessions.dataset_rngs(s, 2)["imaging"].normal(size=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_more_datasets_than_the_streams_allow_are_refused():
    from bench.config.scenario import load_scenario
    from calib.errors import ScenarioError

    names = "[" + ", ".join(f"D{i}" for i in range(sessions.MAX_DATASETS + 1)) + "]"
    with pytest.raises(ScenarioError, match=r"evaluation\.datasets"):
        load_scenario("scenarios/quick.yaml", [f"evaluation.datasets={names}"], check_reach=False)
