"""The hw config: a YAML file that describes a real rig, validated like scenarios.

Sections: ``robot`` (:class:`hw.config.URRobotConfig`), ``grabber``
(:class:`hw.config.GrabberConfig`), ``rig`` (:class:`RigConfig`: the coarse probe
mount from the holder's CAD, the medium, the taught pose at each sphere, the stylus),
``phantom`` (the scenario's phantom section: its CAD gives the sphere and vertex
positions) and ``protocol`` (the scenario's protocol section: which spheres, how many
frames). Unknown keys, wrong types and out-of-range values fail with one line naming
the file and key.

:func:`bench.jobs.twin_serve.loopback_hw_config` writes one for the twin's loopback
controller (``uscal twin serve --hw-config``), with taught poses where an operator would
have taught them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.planning import PlanningConfig
from calib.acquisition.protocol import ProtocolConfig
from calib.errors import ScenarioError
from calib.files.dataset import AcquisitionInfo
from hw.config import GrabberConfig, URRobotConfig
from twin.phantoms import PhantomConfig, build_phantom

from .geometry import acquisition_targets
from .plan_file import check_plan_targets, plan_beside
from .schema import apply_overrides, build_section, read_yaml

__all__ = ["HwConfig", "RigConfig", "load_hw_config"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RigConfig:
    """What the operator knows about the rig (and teaches) before an acquisition."""

    name: str = field(default="lab", metadata={"doc": "Dataset name."})
    coarse_position_mm: tuple[float, float, float] = field(
        default=(0.0, 0.0, 150.0),
        metadata={"doc": "Probe mount from the holder's CAD: image origin in the flange frame."},
    )
    coarse_rotation_xyz_deg: tuple[float, float, float] = field(
        default=(90.0, 0.0, 0.0),
        metadata={"doc": "Probe mount orientation from the CAD (x-y-z Euler angles)."},
    )
    probe_depth_mm: float = field(
        default=40.0,
        metadata={"doc": "Imaging depth set on the scanner (recorded with the data).", "gt": 0},
    )
    medium: str = field(default="water", metadata={"doc": "Tank medium ('water' or other)."})
    temperature_c: float = field(
        default=20.0, metadata={"doc": "Water temperature (thermometer).", "ge": 0, "le": 60}
    )
    assumed_speed_m_s: float = field(
        default=1540.0,
        metadata={"doc": "Speed of sound the scanner assumes.", "ge": 1000, "le": 2000},
    )
    sound_speed_correction: bool = field(
        default=True,
        metadata={"doc": "Rescale the axial spacing by the water's true speed of sound."},
    )
    stylus_tip_mm: tuple[float, float, float] = field(
        default=(0.0, 0.0, 120.0), metadata={"doc": "Stylus tip in the flange frame (CAD)."}
    )
    taught_sphere_1_deg: tuple[float, ...] | None = field(
        default=None,
        metadata={
            "doc": "Joint angles of the pose taught at sphere 1 (probe over it, sphere in "
            "the image centre); null: taught by hand when the acquisition reaches it.",
            "len": 6,
        },
    )
    taught_sphere_2_deg: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Taught pose at sphere 2.", "len": 6}
    )
    taught_sphere_3_deg: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Taught pose at sphere 3.", "len": 6}
    )
    taught_sphere_4_deg: tuple[float, ...] | None = field(
        default=None, metadata={"doc": "Taught pose at sphere 4.", "len": 6}
    )

    def taught_deg(self, sphere: int) -> tuple[float, ...] | None:
        return getattr(self, f"taught_sphere_{sphere}_deg")

    @property
    def T_ee_us_coarse(self) -> Array:
        R = se3.matrix_from_euler(np.radians(self.coarse_rotation_xyz_deg))
        return se3.make(R, np.array(self.coarse_position_mm) * 1e-3)


_SECTIONS = {
    "robot": URRobotConfig,
    "grabber": GrabberConfig,
    "rig": RigConfig,
    "phantom": PhantomConfig,
    "protocol": ProtocolConfig,
    "planning": PlanningConfig,
}


@dataclass(frozen=True)
class HwConfig:
    robot: URRobotConfig
    grabber: GrabberConfig
    rig: RigConfig
    phantom: PhantomConfig
    protocol: ProtocolConfig
    planning: PlanningConfig = field(default_factory=PlanningConfig)
    source: str = "<hw config>"

    def acquisition_info(self) -> AcquisitionInfo:
        """What the dataset records besides the sweeps."""
        cad = build_phantom(self.phantom)
        return AcquisitionInfo(
            T_ee_us_coarse=self.rig.T_ee_us_coarse,
            landmarks={k: np.asarray(v, dtype=float) for k, v in cad.landmarks.items()},
            sphere_radius_mm=self.phantom.sphere_radius_mm,
            temperature_c=self.rig.temperature_c,
            assumed_speed_m_s=self.rig.assumed_speed_m_s,
            sound_speed_correction=self.rig.sound_speed_correction,
            medium=self.rig.medium,
            stylus_tip_cad_mm=self.rig.stylus_tip_mm,
            source="hardware",
            target_depth_mm=self.protocol.target_depth_mm,
            extra={"hw_config": self.source, "robot": self.robot.host},
        )


def load_hw_config(path: str | os.PathLike[str], overrides: list[str] | tuple = ()) -> HwConfig:
    """Read, override and validate a hw config file."""
    source = os.fspath(path)
    data = read_yaml(source)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("a hw config must be a mapping of sections", source=source)
    data = plan_beside(data, Path(source).parent)
    if overrides:
        data = apply_overrides(data, overrides, source)
        source += " (with --set)"
    for key in data:
        if key not in _SECTIONS:
            raise ScenarioError(
                "unknown section", source=source, key=str(key), allowed=", ".join(_SECTIONS)
            )
    sections = {k: build_section(cls, data.get(k), k, source) for k, cls in _SECTIONS.items()}
    if "host" not in (data.get("robot") or {}):
        raise ScenarioError("the controller's address is required", source=source, key="robot.host")
    cfg = HwConfig(**sections, source=source)
    if cfg.protocol.second_pass:
        raise ScenarioError(
            "a second pass on the rig is a second acquisition: calibrate the first, then "
            "acquire again with rig.coarse_position_mm and rig.coarse_rotation_xyz_deg set "
            "to its T_ee_us's position_mm and rotation_xyz_deg (calibration.yaml), so the "
            "sweeps run along its normal",
            source=source,
            key="protocol.second_pass",
            value=True,
            allowed="false",
        )
    check_plan_targets(cfg.protocol, source, acquisition_targets(cfg.phantom.kind, cfg.protocol))
    lo, hi = np.array(cfg.robot.workspace_min_mm), np.array(cfg.robot.workspace_max_mm)
    if np.any(lo >= hi):
        raise ScenarioError(
            "the workspace box is empty",
            source=source,
            key="robot.workspace_min_mm",
            value=list(lo),
            allowed=f"each below workspace_max_mm {list(hi)}",
        )
    return cfg
