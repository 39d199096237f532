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
import difflib
import math
import os
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import yaml

from calib import se3
from calib.errors import ScenarioError, UnreachablePoseError
from calib.localization import LocalizerConfig
from calib.protocol import ProtocolConfig, facing_pose, orientation_offsets, rotated_about_target
from calib.settings import CalibrationConfig, EvaluationConfig, ReconstructionConfig
from sim_us import MediumConfig, ProbeConfig
from twin import PhantomConfig, RobotConfig, ToolsConfig
from twin.ik import solve_ik
from twin.phantoms import build_phantom, build_tank
from twin.scene import Scene, SceneModel

__all__ = [
    "MAX_DATASETS",
    "SECTIONS",
    "OutputConfig",
    "Scenario",
    "acquisition_pixels",
    "apply_overrides",
    "check_geometry",
    "frames_memory_bytes",
    "layout_sigma_mm",
    "load_scenario",
    "scenario_from_mapping",
    "scenarios_markdown",
    "validate_overrides",
]


@dataclass(frozen=True)
class OutputConfig:
    """Where and what a run writes."""

    dir: str = field(default="out", metadata={"doc": "Output directory of a run."})


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
    output: OutputConfig = field(default_factory=OutputConfig)
    source: str = "<default>"

    def rngs(self, n: int) -> list[np.random.Generator]:
        """``n`` independent generators from the seed, one per stage (DESIGN.md §3)."""
        return np.random.default_rng(self.seed).spawn(n)


# --------------------------------------------------------------------------- YAML reading


class _StrictLoader(yaml.SafeLoader):
    """Safe loader that refuses duplicate keys (PyYAML silently keeps the last one)."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    mapping: dict[Any, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node)
        if key in mapping:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        mapping[key] = loader.construct_object(value_node, deep=True)
    return mapping


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _read_yaml(path: str) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise ScenarioError("no such file", source=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"cannot read the file ({exc})", source=path) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ScenarioError(f"invalid YAML: {problem}", source=path, line=line) from None


# --------------------------------------------------------------------------- validation


def _did_you_mean(key: str, allowed: typing.Iterable[str]) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def _type_text(tp: Any, meta: dict[str, Any]) -> str:
    """Human description of what a field accepts (also used in the docs)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return f"{_type_text(inner[0], meta)} or null"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        n = meta.get("len") if args[-1] is Ellipsis else len(args)
        if typing.get_origin(args[0]) is Literal:
            return "list of values from " + ", ".join(repr(a) for a in typing.get_args(args[0]))
        elem = _type_text(args[0], {})
        return f"list of {n} {elem}s" if n else f"list of {elem}s"
    return {float: "number", int: "integer", bool: "true/false", str: "string"}[tp]


def _bounds_text(meta: dict[str, Any]) -> str:
    ops = {"ge": "≥", "gt": ">", "le": "≤", "lt": "<"}
    return ", ".join(f"{ops[k]} {meta[k]:g}" for k in ops if k in meta)


def _check_bounds(x: float, meta: dict[str, Any]) -> bool:
    return not (
        ("ge" in meta and x < meta["ge"])
        or ("gt" in meta and x <= meta["gt"])
        or ("le" in meta and x > meta["le"])
        or ("lt" in meta and x >= meta["lt"])
    )


def _coerce(value: Any, tp: Any, meta: dict[str, Any], where: dict[str, Any]) -> Any:
    """Validate ``value`` against a field type; return the value to store."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    def fail(what: str) -> typing.NoReturn:
        allowed = _type_text(tp, meta)
        bounds = _bounds_text(meta)
        raise ScenarioError(
            what, value=value, allowed=allowed + (f", {bounds}" if bounds else ""), **where
        )

    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = next(a for a in args if a is not type(None))
        return _coerce(value, inner, meta, where)
    if origin is Literal:
        if value not in args:
            fail("not an allowed value" + _did_you_mean(str(value), map(str, args)))
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            fail("expected a list")
        n = meta.get("len") if args[-1] is Ellipsis else len(args)
        if n is not None and len(value) != n:
            fail(f"expected {n} values, got {len(value)}")
        elem_tp = args[0]
        if typing.get_origin(elem_tp) is Literal:
            for v in value:
                if v not in typing.get_args(elem_tp):
                    fail(f"{v!r} is not an allowed value")
            return tuple(value)
        return tuple(_coerce_scalar(v, elem_tp, meta, fail) for v in value)
    return _coerce_scalar(value, tp, meta, fail)


def _coerce_scalar(value: Any, tp: Any, meta: dict[str, Any], fail: Any) -> Any:
    if tp is bool:
        if not isinstance(value, bool):
            fail("expected true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            fail("expected a string")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail("expected an integer")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            fail("expected a number")
        if not math.isfinite(value):
            fail("expected a finite number")
        value = float(value)
    if not _check_bounds(value, meta):
        fail("out of range")
    return value


def _build_section(cls: type, data: Any, section: str, source: str) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("expected a mapping of keys", source=source, key=section, value=data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        path = f"{section}.{key}"
        if key not in fields:
            raise ScenarioError(
                "unknown key" + _did_you_mean(str(key), fields),
                source=source,
                key=path,
                allowed=", ".join(fields),
            )
        kwargs[key] = _coerce(
            value, hints[key], dict(fields[key].metadata), {"source": source, "key": path}
        )
    return cls(**kwargs)


def scenario_from_mapping(data: Any, source: str = "<scenario>") -> Scenario:
    """Validate a parsed scenario mapping and build the :class:`Scenario`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    for key in data:
        if key not in _TOP_LEVEL:
            raise ScenarioError(
                "unknown section" + _did_you_mean(str(key), _TOP_LEVEL),
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
        name: _build_section(cls, data.get(name), name, source) for name, cls in SECTIONS.items()
    }
    if sections["localization"].expected_depth_mm is None:
        # The plan says where the sphere will be: the localizer searches there.
        sections["localization"] = dataclasses.replace(
            sections["localization"], expected_depth_mm=sections["protocol"].target_depth_mm
        )
    scenario = Scenario(seed=seed, source=source, **sections)
    _check_consistency(scenario)
    return scenario


def apply_overrides(data: Any, overrides: typing.Sequence[str], source: str) -> dict[str, Any]:
    """Apply ``key.path=value`` overrides (values parsed as YAML) to a parsed mapping."""
    data = dict(data or {})
    for item in overrides:
        if "=" not in item:
            raise ScenarioError("an override must read key.path=value", source="--set", key=item)
        path, _, text = item.partition("=")
        keys = path.strip().split(".")
        try:
            value = yaml.load(text, Loader=_StrictLoader)
        except yaml.YAMLError:
            raise ScenarioError(
                "value is not valid YAML", source="--set", key=path, value=text
            ) from None
        node = data
        for k in keys[:-1]:
            child = node.get(k)
            child = dict(child) if isinstance(child, dict) else {}
            node[k] = child
            node = child
        node[keys[-1]] = value
    return data


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
    data = {} if path is None else _read_yaml(source)
    if data is not None and not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    if overrides:
        data = apply_overrides(data, overrides, source)
        source += " (with --set)"
    scenario = scenario_from_mapping(data, source)
    if check_reach:
        check_geometry(scenario)
    return scenario


def validate_overrides(
    path: str | os.PathLike[str], override_sets: typing.Iterable[typing.Sequence[str]]
) -> int:
    """Validate the scenario at ``path`` with each set of overrides in turn (every key and
    value, the cross-key checks; not reach and collisions, which :func:`check_geometry`
    decides for a whole scenario): the file is read once, ≈ 1 ms a set. Returns how many
    sets were checked; raises the first :class:`ScenarioError`."""
    source = os.fspath(path)
    data = _read_yaml(source)
    if data is not None and not isinstance(data, dict):
        raise ScenarioError("a scenario must be a mapping of sections", source=source)
    n = 0
    for overrides in override_sets:
        scenario_from_mapping(apply_overrides(data, overrides, source), source + " (with --set)")
        n += 1
    return n


# --------------------------------------------------------------------------- geometry


def _check_consistency(s: Scenario) -> None:
    """Cross-key checks that need no kinematics."""
    src = s.source
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
    return _SWEEPS_PER_TARGET * targets * sweep_pixels(s)


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


def _targets(s: Scenario) -> dict[str, np.ndarray]:
    """Imaging targets of the phantom in base (CAD at the true pose)."""
    phantom = build_phantom(s.phantom)
    marks = phantom.landmarks_in(s.phantom.T_base_phantom)
    keep = {"spheres": "sphere_", "cone": "apex", "prism": "ridge_"}[s.phantom.kind]
    return {k: v for k, v in marks.items() if k.startswith(keep)}


def check_geometry(s: Scenario) -> None:
    """Impossible geometry → :class:`ScenarioError`.

    Checks that the phantom rests inside the tank, under water, and that the probe can face
    every target at the protocol's nine orientations (nominal inverse kinematics within joint
    limits) without the true arm or tool hitting the phantom or tank at the nominal ones.
    """
    src, p = s.source, s.phantom
    phantom = build_phantom(p)
    tank = build_tank(p)
    P_base = se3.apply(p.T_base_phantom, phantom.mesh().vertices)
    P_tank = se3.apply(se3.invert(p.T_base_tank), P_base)
    half = np.array(p.tank_inner_mm[:2]) * 1e-3 / 2
    if np.any(np.abs(P_tank[:, :2]) > half + 1e-9) or np.any(P_tank[:, 2] < -1e-4):
        raise ScenarioError(
            "the phantom does not fit inside the tank (it must rest on the floor within the walls)",
            source=src,
            key="phantom.position_mm",
            value=list(p.position_mm),
            allowed=f"a pose keeping the phantom within ±{1e3 * half[0]:.0f} × "
            f"±{1e3 * half[1]:.0f} mm of the tank centre, at or above its floor",
        )
    top = P_tank[:, 2].max() * 1e3
    if top >= p.water_level_mm:
        raise ScenarioError(
            f"the phantom (top {top:.1f} mm above the floor) is not under water",
            source=src,
            key="phantom.water_level_mm",
            value=p.water_level_mm,
            allowed=f"> {top:.1f}",
        )
    depth = s.protocol.target_depth_mm * 1e-3
    nominal = s.robot.nominal_table
    scene = SceneModel(Scene(nominal, s.tools, phantom, p.T_base_phantom, tank, p.T_base_tank))
    q_home = np.radians(s.robot.home_deg)
    T_ee_us_inv = se3.invert(s.tools.T_ee_us)
    for name, target in _targets(s).items():
        T_face = facing_pose(target, depth)
        for k, R in enumerate(orientation_offsets(s.protocol.rotation_deg)):
            T_base_ee = rotated_about_target(T_face, R, depth) @ T_ee_us_inv
            label = f"facing {name} (orientation {k})"
            try:
                q = solve_ik(nominal, T_base_ee, q_home, pose_label=label)
            except UnreachablePoseError as exc:
                raise ScenarioError(
                    f"out of the robot's reach: {exc}",
                    source=src,
                    key="phantom.position_mm",
                    value=list(p.position_mm),
                ) from None
            if k == 0 and s.tools.mounted == "probe":
                contacts = scene.collisions(q)
                if contacts:
                    c = contacts[0]
                    raise ScenarioError(
                        f"the probe facing {name} would put {c.robot_geom} "
                        f"{1e3 * c.depth:.1f} mm into {c.environment_geom}",
                        source=src,
                        key="phantom.position_mm",
                        value=list(p.position_mm),
                    )


# --------------------------------------------------------------------------- docs


def scenarios_markdown() -> str:
    """``docs/scenarios.md``: every key, its type, default, bounds and meaning."""
    lines = [
        "# Scenario files",
        "",
        "<!-- Generated by `uscal docs scenarios` from the settings dataclasses; "
        "do not edit by hand. -->",
        "",
        "A scenario is a YAML mapping. Every key is optional (the default applies) and "
        "carries its unit in its name. Unknown keys, wrong types and out-of-range values "
        "are rejected with the file, key path, value and what is allowed. Any key can be "
        "overridden on the command line with `--set section.key=value` (value in YAML "
        "syntax, e.g. `--set robot.dh_error_scale=0` or "
        "`--set phantom.position_mm=[300,0,0]`).",
        "",
        "Poses: positions are in the robot base frame; rotations are extrinsic x-y-z Euler "
        "angles in degrees.",
        "",
        "## seed",
        "",
        "Integer ≥ 0 (default 0). One seed per scenario; each stage draws its own "
        "generator from it, so the same scenario and seed give identical outputs.",
    ]
    for section, cls in SECTIONS.items():
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        lines += [
            "",
            f"## {section}",
            "",
            doc,
            "",
            "| key | type | default | meaning |",
            "|---|---|---|---|",
        ]
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            meta = dict(f.metadata)
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            shown = list(default) if isinstance(default, tuple) else default
            kind = _type_text(hints[f.name], meta)
            bounds = _bounds_text(meta)
            if bounds:
                kind += f" ({bounds})"
            shown_text = (
                "null"
                if shown is None
                else yaml.safe_dump(shown, default_flow_style=True)
                .strip()
                .removesuffix("...")
                .strip()
            )
            lines.append(f"| `{f.name}` | {kind} | `{shown_text}` | {meta.get('doc', '')} |")
    return "\n".join(lines) + "\n"
