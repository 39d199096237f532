"""Whether a scenario's world is possible: the phantom inside the tank and under water,
every target within the robot's reach at the protocol's orientations, and the probe clear
of the phantom and tank there (nominal inverse kinematics and the scene's collision
model)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from calib import se3
from calib.acquisition.protocol import (
    ProtocolConfig,
    facing_pose,
    orientation_offsets,
    rotated_about_target,
)
from calib.errors import ScenarioError, UnreachablePoseError
from twin import PhantomConfig, RobotConfig, ToolsConfig
from twin.ik import solve_ik
from twin.phantoms import build_phantom, build_tank
from twin.scene import Scene, SceneModel

__all__ = [
    "TARGET_PHANTOMS",
    "WIRED",
    "World",
    "acquisition_targets",
    "check_geometry",
    "lateral_axis",
]


class World(Protocol):
    """What the checks read of a scenario (:class:`bench.config.scenario.Scenario` is
    one): the arm, the tools, the phantom in its tank, the protocol's poses, and the file
    they come from, for the messages. Declared here rather than imported, so that this
    module sits below :mod:`bench.config.scenario`, which calls it."""

    @property
    def source(self) -> str: ...
    @property
    def robot(self) -> RobotConfig: ...
    @property
    def tools(self) -> ToolsConfig: ...
    @property
    def phantom(self) -> PhantomConfig: ...
    @property
    def protocol(self) -> ProtocolConfig: ...


#: The phantoms of wires: the N-wire phantom and the single wire (one target each, at
#: their wires' centre, the probe taught across the wires).
WIRED = ("nwire", "wire")
#: The phantoms `uscal run` calibrates from their own target, not from spheres: the wires
#: and the cone (its tip, :mod:`calib.localize.cone_tip`).
TARGET_PHANTOMS = (*WIRED, "cone")


def acquisition_targets(kind: str, protocol: ProtocolConfig) -> list[str]:
    """What an acquisition of a ``kind`` phantom sweeps about (and a plan file names):
    the protocol's spheres, the wires' centre (one target, ``nwire`` or ``wire``), or
    the cone's tip (``apex``)."""
    if kind in WIRED:
        return [kind]
    if kind == "cone":
        return ["apex"]
    return [f"sphere_{i}" for i in protocol.spheres]


def _targets(s: World) -> dict[str, np.ndarray]:
    """Imaging targets of the phantom in base (CAD at the true pose)."""
    phantom = build_phantom(s.phantom)
    marks = phantom.landmarks_in(s.phantom.T_base_phantom)
    keep = {
        "spheres": "sphere_",
        "cone": "apex",
        "prism": "ridge_",
        "nwire": "nwire",
        "wire": "wire",
    }
    return {k: v for k, v in marks.items() if k.startswith(keep[s.phantom.kind]) and (
        s.phantom.kind not in WIRED or k == s.phantom.kind)}  # fmt: skip


def lateral_axis(phantom: PhantomConfig) -> np.ndarray:
    """The image's lateral axis (base frame) the probe is taught with: across the wires of
    an N-wire or single-wire phantom (its x: the image plane cuts every wire), base y
    otherwise."""
    if phantom.kind in WIRED:
        return phantom.T_base_phantom[:3, 0].copy()
    return np.array([0.0, 1.0, 0.0])


def check_geometry(s: World) -> None:
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
        T_face = facing_pose(target, depth, lateral_axis=lateral_axis(p))
        for k, R in enumerate(orientation_offsets(s.protocol.rotation_deg, s.protocol.tilt_deg)):
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
