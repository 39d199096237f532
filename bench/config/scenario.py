"""Scenario files: YAML in, validated frozen settings out.

The only module that reads scenario YAML. Each section maps onto the frozen settings
dataclass its package owns; the dataclass fields *are* the schema: type hints give the
type, ``field(metadata=...)`` gives the documentation (``doc``), bounds (``ge``, ``gt``,
``le``, ``lt``, applied to numbers and to every element of a list) and list lengths
(``len``). ``docs/scenarios.md`` is generated from the same fields
(``uscal docs scenarios``), and a test keeps it current.

Any problem raises one :class:`ScenarioError` naming the file, the key path, the value and
what is allowed; unknown keys get a did-you-mean; YAML syntax errors and duplicate keys
give the line.
"""

from __future__ import annotations

import dataclasses
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calib.acquisition.planning import PlanningConfig
from calib.acquisition.protocol import ProtocolConfig
from calib.calibration.markers import CalibrationConfig
from calib.errors import ScenarioError
from calib.evaluation.cross_validation import EvaluationConfig
from calib.evaluation.reconstruct import ReconstructionConfig
from calib.localize import LocalizerConfig
from sim_us import MediumConfig, ProbeConfig
from twin import PhantomConfig, RobotConfig, ToolsConfig

from .geometry import TARGET_PHANTOMS, acquisition_targets, check_geometry
from .plan_file import check_plan_targets, plan_beside, read_plan
from .schema import apply_overrides, build_section, did_you_mean, read_yaml

__all__ = [
    "MAX_DATASETS",
    "SECTIONS",
    "OutputConfig",
    "Scenario",
    "acquisition_pixels",
    "frames_memory_bytes",
    "layout_sigma_mm",
    "load_scenario",
    "scenario_from_mapping",
    "sweep_pixels",
    "sweeps_per_target",
    "validate_overrides",
]


@dataclass(frozen=True)
class OutputConfig:
    """Where and what a run writes."""

    dir: str = field(default="out", metadata={"doc": "Output directory of a run."})
    ros_parent_link: str = field(
        default="tool0",
        metadata={
            "doc": "The flange link of the robot's URDF that us_probe.urdf.xacro and the "
            "static_transform_publisher line attach the image to (ur_description: tool0)."
        },
    )
    ros_image_link: str = field(
        default="us_image",
        metadata={"doc": "The link (TF frame) us_probe.urdf.xacro gives the image frame."},
    )


#: Scenario sections in file order and the settings class each maps onto.
SECTIONS: dict[str, type] = {
    "robot": RobotConfig,
    "tools": ToolsConfig,
    "phantom": PhantomConfig,
    "medium": MediumConfig,
    "imaging": ProbeConfig,
    "protocol": ProtocolConfig,
    "localization": LocalizerConfig,
    "calibration": CalibrationConfig,
    "evaluation": EvaluationConfig,
    "reconstruction": ReconstructionConfig,
    "planning": PlanningConfig,
    "output": OutputConfig,
}

_TOP_LEVEL = ("seed", *SECTIONS)


@dataclass(frozen=True)
class Scenario:
    """A validated scenario: one seed and the settings of every stage."""

    seed: int = 0
    robot: RobotConfig = field(default_factory=RobotConfig)
    tools: ToolsConfig = field(default_factory=ToolsConfig)
    phantom: PhantomConfig = field(default_factory=PhantomConfig)
    medium: MediumConfig = field(default_factory=MediumConfig)
    imaging: ProbeConfig = field(default_factory=ProbeConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    localization: LocalizerConfig = field(default_factory=LocalizerConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    reconstruction: ReconstructionConfig = field(default_factory=ReconstructionConfig)
    planning: PlanningConfig = field(default_factory=PlanningConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    source: str = "<default>"
    #: Settings the scenario did not set, derived from those it did (key, value, from).
    derived: tuple[tuple[str, float, str], ...] = ()

    def rngs(self, n: int) -> list[np.random.Generator]:
        """``n`` independent generators from the seed, one per stage (DESIGN.md §3)."""
        return np.random.default_rng(self.seed).spawn(n)


def scenario_from_mapping(data: Any, source: str = "<scenario>") -> Scenario:
    """Validate a parsed scenario mapping and build the :class:`Scenario`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    for key in data:
        if key not in _TOP_LEVEL:
            raise ScenarioError(
                "unknown section" + did_you_mean(str(key), _TOP_LEVEL),
                source=source,
                key=str(key),
                allowed=", ".join(_TOP_LEVEL),
            )
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ScenarioError(
            "invalid seed", source=source, key="seed", value=seed, allowed="an integer ≥ 0"
        )
    sections = {
        name: build_section(cls, data.get(name), name, source) for name, cls in SECTIONS.items()
    }
    derived: list[tuple[str, float, str]] = []
    loc, proto = sections["localization"], sections["protocol"]
    if loc.expected_depth_mm is None:
        # The plan says where the sphere will be: the localizer searches there.
        loc = dataclasses.replace(loc, expected_depth_mm=proto.target_depth_mm)
        derived.append(
            ("localization.expected_depth_mm", proto.target_depth_mm, "protocol.target_depth_mm")
        )
    if "expected_window_mm" not in (data.get("localization") or {}):
        # Not set: wide enough for the plan's offsets and the teaching error (a value the
        # user set is checked against the same need, and refused if short).
        need = proto.translation_mm + 3 * proto.teaching_error_mm
        if need > loc.expected_window_mm:
            loc = dataclasses.replace(loc, expected_window_mm=need)
            derived.append(
                (
                    "localization.expected_window_mm",
                    need,
                    "protocol.translation_mm + 3 × protocol.teaching_error_mm",
                )
            )
    sections["localization"] = loc
    scenario = Scenario(seed=seed, source=source, derived=tuple(derived), **sections)
    _check_consistency(scenario)
    if scenario.protocol.plan is not None:
        _check_plan(scenario)
    return scenario


def layout_sigma_mm(scenario: Scenario) -> float:
    """The multi-marker fit's layout prior (1 σ per axis, mm): the phantom's print
    tolerance, or 0 when the scenario takes the CAD layout as exact."""
    if scenario.calibration.layout == "estimated":
        return scenario.phantom.tolerance_position_mm
    return 0.0


def load_scenario(
    path: str | os.PathLike[str] | None,
    overrides: typing.Sequence[str] = (),
    check_reach: bool = True,
) -> Scenario:
    """Read, override and validate a scenario file (``None``: the built-in default).

    ``check_reach`` also runs :func:`check_geometry` (reachability and collisions).
    """
    source = "<default>" if path is None else os.fspath(path)
    data = {} if path is None else read_yaml(source)
    if data is not None and not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    if path is not None:
        data = plan_beside(data, Path(source).parent)
    if overrides:
        data = apply_overrides(data, overrides, source)
        source += " (with --set)"
    scenario = scenario_from_mapping(data, source)
    if check_reach:
        check_geometry(scenario)
    return scenario


def _check_plan(s: Scenario) -> None:
    """A plan file names the targets the protocol scans, and each of its sweeps keeps the
    target inside the image (as the plan puts it; a sphere wholly)."""
    check_plan_targets(s.protocol, s.source, acquisition_targets(s.phantom.kind, s.protocol))
    poses = read_plan(s.protocol.plan)
    radius = 0.0 if s.phantom.kind in TARGET_PHANTOMS else s.phantom.sphere_radius_mm
    depth, r = s.protocol.target_depth_mm * 1e-3, radius * 1e-3
    half_width, image_depth = s.imaging.width_mm * 5e-4, s.imaging.depth_mm * 1e-3
    for name, sweeps in poses.items():
        for k, pose in enumerate(sweeps):
            x, y, _ = pose.target_in_image(depth)
            if abs(x) + r > half_width or y - r < 0 or y + r > image_depth:
                raise ScenarioError(
                    f"sweep {k} of {name} puts the {'sphere' if radius else 'target'} at "
                    f"({-pose.lateral_mm:g}, "
                    f"{y * 1e3:g}) mm, not wholly inside the {s.imaging.width_mm:g} × "
                    f"{s.imaging.depth_mm:g} mm image",
                    source=s.source,
                    key="protocol.plan",
                    value=s.protocol.plan,
                    allowed="a plan made for this image and target depth (uscal plan --optimize)",
                )


def sweeps_per_target(s: Scenario) -> int:
    """Sweeps about each target: the plan file's most, or the paper's 45."""
    if s.protocol.plan is None:
        return _SWEEPS_PER_TARGET
    return max(len(v) for v in read_plan(s.protocol.plan).values())


def validate_overrides(
    path: str | os.PathLike[str], override_sets: typing.Iterable[typing.Sequence[str]]
) -> int:
    """Validate the scenario at ``path`` with each set of overrides in turn (every key and
    value, the cross-key checks; not reach and collisions, which :func:`check_geometry`
    decides for a whole scenario): the file is read once, ≈ 1 ms a set. Returns how many
    sets were checked; raises the first :class:`ScenarioError`."""
    source = os.fspath(path)
    data = read_yaml(source)
    if data is not None and not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    n = 0
    for overrides in override_sets:
        scenario_from_mapping(apply_overrides(data, overrides, source), source + " (with --set)")
        n += 1
    return n


# --------------------------------------------------------------------------- geometry


_LINK_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def _check_consistency(s: Scenario) -> None:
    """Cross-key checks that need no kinematics."""
    src = s.source
    for key in ("ros_parent_link", "ros_image_link"):
        name = getattr(s.output, key)
        if not _LINK_NAME.fullmatch(name):
            raise ScenarioError(
                "not a URDF link / TF frame name",
                source=src,
                key=f"output.{key}",
                value=name,
                allowed="letters, digits and _ (not first), parts joined by /",
            )
    if not s.imaging.plane_waves_symmetric:
        raise ScenarioError(
            "the plane waves' steering angles are not symmetric about 0",
            source=src,
            key="imaging.plane_waves_deg",
            value=list(s.imaging.plane_waves_deg),
            allowed="angles in ± pairs (and 0 or not), e.g. [-8, 0, 8]; [] = focused",
        )
    p = s.phantom
    if p.water_level_mm > p.tank_inner_mm[2]:
        raise ScenarioError(
            "the water would overflow the tank",
            source=src,
            key="phantom.water_level_mm",
            value=p.water_level_mm,
            allowed=f"≤ tank height {p.tank_inner_mm[2]:g}",
        )
    if p.kind == "spheres":
        r, half = p.sphere_radius_mm, p.sphere_spacing_mm / 2
        if p.sphere_spacing_mm <= 2 * r:
            raise ScenarioError(
                "spheres would overlap",
                source=src,
                key="phantom.sphere_spacing_mm",
                value=p.sphere_spacing_mm,
                allowed=f"> 2 × sphere_radius_mm = {2 * r:g}",
            )
        if p.center_height_mm - r <= p.plate_thickness_mm:
            raise ScenarioError(
                "spheres would sink into the base plate",
                source=src,
                key="phantom.center_height_mm",
                value=p.center_height_mm,
                allowed=f"> plate_thickness_mm + radius = {p.plate_thickness_mm + r:g}",
            )
        if p.vertex_offset_mm < half + r + 8:
            raise ScenarioError(
                "touch vertices would sit inside the sphere square",
                source=src,
                key="phantom.vertex_offset_mm",
                value=p.vertex_offset_mm,
                allowed=f"≥ spacing/2 + radius + 8 = {half + r + 8:g}",
            )
    loc, proto = s.localization, s.protocol
    need = proto.translation_mm + 3 * proto.teaching_error_mm
    if loc.method == "refined" and loc.expected_window_mm < need:
        raise ScenarioError(
            "the localizer's window would not cover where the plan puts the sphere",
            source=src,
            key="localization.expected_window_mm",
            value=loc.expected_window_mm,
            allowed=f"≥ protocol.translation_mm + 3 × protocol.teaching_error_mm = {need:g}",
        )
    if s.protocol.target_depth_mm >= s.imaging.depth_mm:
        raise ScenarioError(
            "the target would lie below the imaged depth",
            source=src,
            key="protocol.target_depth_mm",
            value=s.protocol.target_depth_mm,
            allowed=f"< imaging.depth_mm = {s.imaging.depth_mm:g}",
        )
    if len(s.evaluation.datasets) > MAX_DATASETS:
        raise ScenarioError(
            "too many datasets: each has its own random streams, and there are keys for "
            f"{MAX_DATASETS}",
            source=src,
            key="evaluation.datasets",
            value=len(s.evaluation.datasets),
            allowed=f"at most {MAX_DATASETS} names",
        )
    _check_memory(s)


#: Evaluation datasets a scenario may have (each has its own random streams,
#: :mod:`bench.sessions`).
MAX_DATASETS = 50
#: Sweeps per target in the paper's plan (9 orientations × 5 in-plane positions).
_SWEEPS_PER_TARGET = 45
#: Working memory of the simulator per pixel of the sweep it renders (its float32
#: intensities, complex64 echo and speckle buffers and their temporaries; measured with
#: tracemalloc at 15–60 bytes, the more for small frames).
_SIMULATION_BYTES_PER_PIXEL = 64


def sweep_pixels(s: Scenario) -> int:
    """Frame pixels of one sweep."""
    rows, cols = s.imaging.image_shape
    return s.protocol.frames_per_sweep * rows * cols


def acquisition_pixels(s: Scenario) -> int:
    """Frame pixels of one acquisition: the plan's sweeps of every target."""
    targets = len(s.protocol.spheres) if s.phantom.kind == "spheres" else 1
    return sweeps_per_target(s) * targets * sweep_pixels(s)


def frames_memory_bytes(s: Scenario) -> int:
    """Estimated peak memory (bytes) of the frames a run holds: every dataset's frames
    (uint8) in the worker processes that acquire them side by side, and one sweep being
    simulated in each. For the paper scenario ≈ 1.6 GB (measured peak of the whole run:
    1.5–1.7 GB, ``benchmarks/paper.py``)."""
    datasets = max(1, len(s.evaluation.datasets))
    side_by_side = min(datasets, os.cpu_count() or 1)
    per_worker = acquisition_pixels(s) + _SIMULATION_BYTES_PER_PIXEL * sweep_pixels(s)
    return side_by_side * per_worker


def _physical_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def _check_memory(s: Scenario) -> None:
    """A scenario whose frames cannot fit in this machine's memory is refused here, not
    by a MemoryError minutes into the simulation."""
    have = _physical_memory_bytes()
    need = frames_memory_bytes(s)
    if have is None or need <= have:
        return
    rows, cols = s.imaging.image_shape
    raise ScenarioError(
        f"the frames would not fit in memory: {s.protocol.frames_per_sweep} frames of "
        f"{rows} × {cols} pixels per sweep need ≈ {need / 1e9:,.0f} GB, this machine has "
        f"{have / 1e9:.0f} GB",
        source=s.source,
        key="imaging.pixel_spacing_mm, imaging.depth_mm, imaging.width_mm, "
        "protocol.frames_per_sweep",
        allowed="coarser pixels, a shallower or narrower image, or fewer frames per sweep",
    )
