"""Scenario validation: the shipped files, every kind of mistake, overrides, docs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.config.docs import scenarios_markdown
from bench.config.geometry import check_geometry
from bench.config.scenario import SECTIONS, Scenario, load_scenario, scenario_from_mapping
from calib.errors import ScenarioError

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["paper.yaml", "quick.yaml"])
def test_shipped_scenarios_are_valid(name):
    s = load_scenario(ROOT / "scenarios" / name)
    assert isinstance(s, Scenario)
    assert s.source.endswith(name)


def test_paper_scenario_holds_the_papers_numbers():
    s = load_scenario(ROOT / "scenarios" / "paper.yaml", check_reach=False)
    assert (s.phantom.sphere_radius_mm, s.phantom.sphere_spacing_mm) == (5.0, 50.0)
    assert (s.phantom.cone_base_diameter_mm, s.phantom.cone_height_mm) == (60.0, 44.64)
    assert (s.protocol.rotation_deg, s.protocol.translation_mm) == (10.0, 3.0)
    assert (s.protocol.sweep_half_length_mm, s.protocol.frames_per_sweep) == (10.0, 21)
    assert (s.robot.dh_rms_theta_deg, s.robot.dh_rms_d_mm) == (2.51, 0.24)
    assert (s.robot.dh_rms_a_mm, s.robot.dh_rms_alpha_deg) == (1.51, 0.27)


def test_default_scenario_equals_paper_defaults():
    assert load_scenario(None, check_reach=False).phantom.sphere_radius_mm == 5.0


def test_the_localizer_searches_where_the_plan_puts_the_sphere():
    """Unset, the localizer's expected depth follows the protocol's target depth (also
    when a sweep overrides it); set, it stays as set."""
    s = load_scenario(None, ["protocol.target_depth_mm=30", "imaging.depth_mm=45"], False)
    assert s.localization.expected_depth_mm == 30.0
    s = load_scenario(None, ["localization.expected_depth_mm=25"], check_reach=False)
    assert s.localization.expected_depth_mm == 25.0


def test_the_search_window_follows_the_plan_unless_set():
    """A wider plan widens the window the user never touched (shown as derived in
    `uscal check`); a window the user set short is refused, naming what it needs."""
    wide = ["protocol.rotation_deg=15", "protocol.translation_mm=8"]
    s = load_scenario(ROOT / "scenarios" / "quick.yaml", wide, check_reach=False)
    need = 8 + 3 * s.protocol.teaching_error_mm
    assert s.localization.expected_window_mm == need
    assert ("localization.expected_window_mm", need) in [(k, v) for k, v, _ in s.derived]
    with pytest.raises(ScenarioError, match=rf"expected_window_mm = 10.*≥ .* = {need:g}"):
        load_scenario(
            ROOT / "scenarios" / "quick.yaml",
            [*wide, "localization.expected_window_mm=10"],
            check_reach=False,
        )
    # The default plan needs less than the default window: nothing derived.
    s = load_scenario(ROOT / "scenarios" / "quick.yaml", check_reach=False)
    assert s.localization.expected_window_mm == 10.0
    assert "localization.expected_window_mm" not in [k for k, _, _ in s.derived]


def write(tmp_path, text):
    path = tmp_path / "s.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "text,pattern",
    [
        (
            "robot:\n  dh_eror_scale: 1\n",
            r"s\.yaml: robot\.dh_eror_scale: unknown key; did you "
            r"mean 'dh_error_scale'\?",
        ),
        ("robots: {}\n", r"robots: unknown section; did you mean 'robot'\?"),
        ("robot:\n  dh_error_scale: -1\n", r"robot\.dh_error_scale = -1: out of range.*≥ 0"),
        ("robot:\n  dh_error_scale: lots\n", r"robot\.dh_error_scale = 'lots': expected a number"),
        ("robot:\n  model: ur5\n", r"robot\.model = 'ur5': not an allowed value.*'ur3', 'ur3e'"),
        (
            "protocol:\n  frames_per_sweep: 2.5\n",
            r"protocol\.frames_per_sweep = 2\.5: expected "
            r"an integer",
        ),
        (
            "imaging:\n  sound_speed_correction: 1\n",
            r"sound_speed_correction = 1: expected true or false",
        ),
        (
            "tools:\n  stylus_tip_mm: [1, 2]\n",
            r"tools\.stylus_tip_mm = \[1, 2\]: expected 3 "
            r"values",
        ),
        ("imaging:\n  pixel_spacing_mm: [0.1, 0]\n", r"imaging\.pixel_spacing_mm.*out of range"),
        ("seed: -3\n", r"seed = -3: invalid seed"),
        (
            "seed: 1\nrobot:\n  model: ur3\n  model: ur3e\n",
            r"s\.yaml:4: invalid YAML: duplicate "
            r"key 'model'",
        ),
        ("seed: 1\nrobot: [\n", r"s\.yaml:3: invalid YAML"),
        ("- 1\n- 2\n", r"a scenario must be a mapping"),
        ("phantom:\n  water_level_mm: 200\n", r"phantom\.water_level_mm = 200.*overflow"),
        ("phantom:\n  sphere_spacing_mm: 8\n", r"sphere_spacing_mm = 8.*overlap"),
        ("imaging:\n  depth_mm: 15\n", r"protocol\.target_depth_mm = 20.*below the imaged depth"),
        (
            "localization:\n  expected_window_mm: 5\n",
            r"expected_window_mm = 5.*would not cover where the plan puts the sphere.*≥ .* = 9",
        ),
        ("medium:\n  temperature_c: .nan\n", r"temperature_c = nan: expected a finite number"),
        (
            "imaging:\n  plane_waves_deg: [-8, 0, 5]\n",
            r"imaging\.plane_waves_deg = \[-8\.0, 0\.0, 5\.0\]: .*not symmetric about 0",
        ),
        ("imaging:\n  plane_waves_deg: [40]\n", r"imaging\.plane_waves_deg.*out of range"),
        ("imaging:\n  apodization: hamming\n", r"apodization.*not an allowed"),
    ],
)
def test_invalid_scenarios_raise_one_clear_error(tmp_path, text, pattern):
    with pytest.raises(ScenarioError, match=pattern):
        load_scenario(write(tmp_path, text), check_reach=False)


@pytest.mark.parametrize(
    "overrides,pattern",
    [
        (["phantom.position_mm=[500, 0, 0]"], r"does not fit inside the tank"),
        (["phantom.position_mm=[300, 0, -20]"], r"does not fit inside the tank"),
        (["phantom.water_level_mm=20"], r"not under water"),
        (
            ["phantom.tank_position_mm=[620, 0, 0]", "phantom.position_mm=[620, 0, 0]"],
            r"out of the robot's reach: pose facing sphere_\d \(orientation \d\)",
        ),
        (
            ["phantom.tank_position_mm=[150, 0, 0]", "phantom.position_mm=[150, 0, 0]"],
            r"would put link\d_\w .* into tank_wall",
        ),
    ],
)
def test_impossible_geometry_is_rejected(overrides, pattern):
    with pytest.raises(ScenarioError, match=pattern):
        load_scenario(ROOT / "scenarios" / "quick.yaml", overrides)


def test_overrides_apply_with_validation():
    s = load_scenario(
        ROOT / "scenarios" / "quick.yaml",
        ["robot.dh_error_scale=0", "phantom.rotation_deg=[0, 0, 10]", "seed=7"],
    )
    assert s.robot.dh_error_scale == 0.0
    assert s.phantom.rotation_deg == (0.0, 0.0, 10.0)
    assert s.seed == 7
    assert "(with --set)" in s.source
    with pytest.raises(ScenarioError, match=r"--set: nokey: an override must read"):
        load_scenario(None, ["nokey"])
    with pytest.raises(ScenarioError, match=r"robot\.modle: unknown key; did you mean 'model'"):
        load_scenario(None, ["robot.modle=ur3e"])


def test_cone_and_prism_scenarios_pass_geometry():
    for kind in ("cone", "prism"):
        s = scenario_from_mapping({"phantom": {"kind": kind}})
        check_geometry(s)


def test_seed_streams_are_reproducible():
    a, b = Scenario(seed=3), Scenario(seed=3)
    assert [g.random() for g in a.rngs(4)] == [g.random() for g in b.rngs(4)]
    assert a.rngs(1)[0].random() != Scenario(seed=4).rngs(1)[0].random()
    assert np.isfinite(a.rngs(2)[1].random())


def test_docs_are_generated_from_the_schema_and_current():
    text = scenarios_markdown()
    assert (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8") == text, (
        "docs/scenarios.md is stale: run `uscal docs scenarios -o docs/scenarios.md`"
    )
    import dataclasses

    for section, cls in SECTIONS.items():
        assert f"## {section}" in text
        for f in dataclasses.fields(cls):
            assert f"| `{f.name}` |" in text
            assert f.metadata.get("doc"), f"{section}.{f.name} has no documentation"


def test_a_scenario_that_cannot_fit_in_memory_is_refused_at_validation(monkeypatch):
    """Frames of 6 µm pixels, 300 mm deep, 401 per sweep would need terabytes: refused
    when the scenario is read, naming the keys, not by a MemoryError minutes in. The
    estimate is the frames a run holds; for the paper scenario it is close to the run's
    measured peak (1.5–1.7 GB), and a machine with less memory refuses it too."""
    import bench.config.scenario as scenario_module
    from bench.config.scenario import frames_memory_bytes, load_scenario

    overrides = [
        "imaging.pixel_spacing_mm=[0.006, 0.006]",
        "imaging.depth_mm=300",
        "protocol.frames_per_sweep=401",
    ]
    with pytest.raises(ScenarioError) as e:
        load_scenario("scenarios/quick.yaml", overrides, check_reach=False)
    msg = str(e.value)
    assert "would not fit in memory" in msg and "\n" not in msg
    for key in ("imaging.pixel_spacing_mm", "imaging.depth_mm", "protocol.frames_per_sweep"):
        assert key in msg
    paper = load_scenario("scenarios/paper.yaml", check_reach=False)
    assert 1.0e9 < frames_memory_bytes(paper) < 2.5e9
    monkeypatch.setattr(scenario_module, "_physical_memory_bytes", lambda: 1_000_000_000)
    with pytest.raises(ScenarioError, match="would not fit in memory"):
        load_scenario("scenarios/paper.yaml", check_reach=False)
    load_scenario("scenarios/quick.yaml", check_reach=False)  # 0.1 GB: fits
