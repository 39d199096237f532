"""Plan files: the sweeps to acquire about each target, relative to its taught nominal
pose (``uscal plan --optimize --out PLAN.yaml``; used through ``protocol.plan: PLAN.yaml``
by ``uscal run`` and ``uscal acquire``). A plain YAML list per target (a sphere
``sphere_N``, the wires' centre ``wire`` or ``nwire``, the cone's tip ``apex``), units
in the key names::

    kind: uscal-plan
    targets:                     # files before targets other than spheres: spheres
      sphere_1:
        - {rotation_xyz_deg: [10, -20, 0], lateral_mm: 4, axial_mm: -2}
        - ...
    spares:                      # optional: best first
      sphere_1:
        - {rotation_xyz_deg: [-5, 15, 0], lateral_mm: 0, axial_mm: 3}

At acquisition a sweep that no longer clears (another session's taught pose or mount
moves the arm by millimetres) is replaced by the first spare of its target that does
(:func:`calib.acquisition.protocol.clear_sweeps`). Everything else in the file (how it was chosen,
what it predicts) is for the reader.
Problems give one :class:`~calib.errors.ScenarioError` naming the file and the entry.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from calib.acquisition.planning import SweepPose, paper_poses
from calib.acquisition.protocol import ProtocolConfig
from calib.errors import ScenarioError

from ..files import write_text_atomic
from .schema import read_yaml

__all__ = [
    "MAX_ROTATION_DEG",
    "MAX_SHIFT_MM",
    "TARGET_NAMES",
    "check_plan_targets",
    "plan_beside",
    "read_plan",
    "read_spares",
    "spare_poses",
    "sphere_poses",
    "sweeps_about",
    "write_plan",
]

KIND = "uscal-plan"
#: Bounds of a sweep's placement (as for the candidates a plan is chosen from).
MAX_ROTATION_DEG = 45.0
MAX_SHIFT_MM = 30.0
_KEYS = ("rotation_xyz_deg", "lateral_mm", "axial_mm")
#: The targets a plan may name besides the spheres (``sphere_N``).
TARGET_NAMES = ("wire", "nwire", "apex")
#: The section of the planned sweeps (``spheres`` in files that knew only spheres).
_PLAN_KEY, _OLD_PLAN_KEY = "targets", "spheres"


def _is_target(name: object) -> bool:
    return isinstance(name, str) and (name.startswith("sphere_") or name in TARGET_NAMES)


def _number(value: Any, where: str, source: str, limit: float, key: str) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or abs(value) > limit:
        raise ScenarioError(
            "not a number within the bounds",
            source=source,
            key=f"{where}.{key}",
            value=value,
            allowed=f"a number within ± {limit:g}",
        )
    return float(value)


def _read_doc(path: str | os.PathLike[str]) -> tuple[str, dict]:
    source = os.fspath(path)
    doc = read_yaml(source)
    if not isinstance(doc, dict) or doc.get("kind") != KIND:
        raise ScenarioError(
            f"not a plan file (it must be a mapping with kind: {KIND})", source=source
        )
    return source, doc


def _sweep_lists(doc: dict, key: str, source: str) -> dict[str, tuple[SweepPose, ...]]:
    """{target name: its sweeps} of one section (``targets`` or ``spares``)."""
    if key == _PLAN_KEY and _PLAN_KEY not in doc and _OLD_PLAN_KEY in doc:
        key = _OLD_PLAN_KEY
    targets = doc.get(key)
    if not isinstance(targets, dict) or not targets:
        raise ScenarioError(
            "no sweeps", source=source, key=key, allowed="<target>: [sweeps...] per target"
        )
    out: dict[str, tuple[SweepPose, ...]] = {}
    for name, sweeps in targets.items():
        where = f"{key}.{name}"
        if not _is_target(name):
            raise ScenarioError(
                "not a target's name",
                source=source,
                key=where,
                allowed=f"sphere_N, {', '.join(TARGET_NAMES)}",
            )
        if not isinstance(sweeps, list) or (key != "spares" and not sweeps):
            raise ScenarioError("expected a list of sweeps", source=source, key=where)
        poses = []
        for k, sweep in enumerate(sweeps):
            at = f"{where}[{k}]"
            if not isinstance(sweep, dict) or set(sweep) != set(_KEYS):
                raise ScenarioError(
                    "a sweep is a mapping of exactly these keys",
                    source=source,
                    key=at,
                    value=sweep,
                    allowed=", ".join(_KEYS),
                )
            angles = sweep["rotation_xyz_deg"]
            if not isinstance(angles, list) or len(angles) != 3:
                raise ScenarioError(
                    "expected three angles", source=source, key=f"{at}.rotation_xyz_deg"
                )
            rot = tuple(
                _number(a, at, source, MAX_ROTATION_DEG, "rotation_xyz_deg") for a in angles
            )
            poses.append(
                SweepPose(
                    rot,  # type: ignore[arg-type]
                    _number(sweep["lateral_mm"], at, source, MAX_SHIFT_MM, "lateral_mm"),
                    _number(sweep["axial_mm"], at, source, MAX_SHIFT_MM, "axial_mm"),
                )
            )
        out[name] = tuple(poses)
    return out


def read_plan(path: str | os.PathLike[str]) -> dict[str, tuple[SweepPose, ...]]:
    """{target name: its sweeps, in acquisition order} of a plan file."""
    source, doc = _read_doc(path)
    return _sweep_lists(doc, _PLAN_KEY, source)


def read_spares(path: str | os.PathLike[str]) -> dict[str, tuple[SweepPose, ...]]:
    """{target name: its spare sweeps, best first} of a plan file (none: an empty dict):
    what the acquisition puts in place of a sweep that no longer clears."""
    source, doc = _read_doc(path)
    if "spares" not in doc:
        return {}
    spares = _sweep_lists(doc, "spares", source)
    plan = _sweep_lists(doc, _PLAN_KEY, source)
    extra = sorted(set(spares) - set(plan))
    if extra:
        raise ScenarioError(
            f"spares for {', '.join(extra)}, which the plan does not scan",
            source=source,
            key="spares",
            allowed=", ".join(plan),
        )
    return spares


def write_plan(
    path: str | os.PathLike[str],
    poses: Mapping[str, Sequence[SweepPose]],
    about: Mapping[str, Any],
    spares: Mapping[str, Sequence[SweepPose]] | None = None,
) -> Path:
    """Write a plan file (atomically); ``about`` goes in as the reader's information,
    ``spares`` (per target, best first) as the sweeps an acquisition may put in place of
    one that no longer clears."""

    def plain(x: float) -> float:
        return round(float(x), 6) + 0.0  # no -0.0

    def listed(sweeps: Sequence[SweepPose]) -> list[dict]:
        return [
            {
                "rotation_xyz_deg": [plain(a) for a in p.rotation_deg],
                "lateral_mm": plain(p.lateral_mm),
                "axial_mm": plain(p.axial_mm),
            }
            for p in sweeps
        ]

    doc = {
        "kind": KIND,
        **dict(about),
        _PLAN_KEY: {name: listed(sweeps) for name, sweeps in poses.items()},
    }
    if spares:
        doc["spares"] = {name: listed(sweeps) for name, sweeps in spares.items()}
    header = (
        "# uscal plan: the sweeps about each target, relative to its taught nominal pose\n"
        "# (turned about the target by rotation_xyz_deg about the image axes, then shifted\n"
        "# in the image plane). Use it with protocol.plan: <this file>. A sweep that no\n"
        "# longer clears in a session is replaced by the first of its target's spares that does.\n"
    )
    text = header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    write_text_atomic(Path(path), text)
    return Path(path)


def sphere_poses(protocol: ProtocolConfig, target: str) -> tuple[SweepPose, ...] | None:
    """The sweeps of ``protocol.plan`` about ``target`` (None: the paper's plan)."""
    if protocol.plan is None:
        return None
    poses = read_plan(protocol.plan)
    if target not in poses:
        raise ScenarioError(
            f"the plan has no sweeps for {target}",
            source=protocol.plan,
            allowed=", ".join(poses),
        )
    return poses[target]


def spare_poses(protocol: ProtocolConfig, target: str) -> tuple[SweepPose, ...]:
    """The spare sweeps of ``protocol.plan`` about ``target``, best first (none for the
    paper's plan or a plan file without spares)."""
    if protocol.plan is None:
        return ()
    return read_spares(protocol.plan).get(target, ())


def sweeps_about(protocol: ProtocolConfig, target: str) -> int:
    """How many sweeps the protocol takes about ``target``."""
    poses = sphere_poses(protocol, target)
    return len(poses) if poses is not None else len(paper_poses(0.0, 0.0))


def plan_beside(data: Any, folder: Path) -> Any:
    """A settings file's ``protocol.plan``, when relative, read from the file's folder
    (an override's is from the current one)."""
    protocol = data.get("protocol") if isinstance(data, dict) else None
    plan = protocol.get("plan") if isinstance(protocol, dict) else None
    if not isinstance(plan, str) or Path(plan).is_absolute():
        return data
    return {**data, "protocol": {**protocol, "plan": str(folder / plan)}}


def check_plan_targets(protocol: ProtocolConfig, source: str, targets: Sequence[str]) -> None:
    """A plan file holds sweeps for exactly the ``targets`` the protocol scans."""
    if protocol.plan is None:
        return
    poses = read_plan(protocol.plan)
    if sorted(poses) != sorted(targets):
        spheres = all(t.startswith("sphere_") for t in targets)
        raise ScenarioError(
            f"the plan has sweeps for {', '.join(poses)}; the protocol scans {', '.join(targets)}",
            source=source,
            key="protocol.plan",
            value=protocol.plan,
            allowed="a plan of the protocol's spheres (or set protocol.spheres to the plan's)"
            if spheres
            else "a plan made for this phantom (uscal plan --optimize on this scenario)",
        )
