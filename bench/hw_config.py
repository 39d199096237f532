"""The hw config: a YAML file that describes a real rig, validated like scenarios.

Sections: ``robot`` (:class:`hw.config.URRobotConfig`), ``grabber``
(:class:`hw.config.GrabberConfig`), ``rig`` (:class:`RigConfig`: the coarse probe
mount from the holder's CAD, the medium, the taught pose at each sphere, the stylus),
``phantom`` (the scenario's phantom section: its CAD gives the sphere and vertex
positions) and ``protocol`` (the scenario's protocol section: which spheres, how many
frames). Unknown keys, wrong types and out-of-range values fail with one line naming
the file and key.

:func:`loopback_hw_config` writes one for the twin's loopback controller (``uscal twin
serve --hw-config``), with taught poses where an operator would have taught them.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from calib import se3
from calib.dataset_files import AcquisitionInfo
from calib.errors import ScenarioError
from calib.protocol import ProtocolConfig, facing_pose, touch_plan
from hw.config import GrabberConfig, URRobotConfig
from twin.phantoms import PhantomConfig, build_phantom
from twin.touch import SimTouchGuide

from .experiment import coarse_estimate, make_twin
from .output import write_text_atomic
from .scenario import Scenario, _build_section, _read_yaml, apply_overrides
from .sessions import TOUCH_GUIDE_KEY, stage_rngs, stream

__all__ = ["HwConfig", "RigConfig", "emulated_operator", "load_hw_config", "loopback_hw_config"]

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
}


@dataclass(frozen=True)
class HwConfig:
    robot: URRobotConfig
    grabber: GrabberConfig
    rig: RigConfig
    phantom: PhantomConfig
    protocol: ProtocolConfig
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
    data = _read_yaml(source)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("a hw config must be a mapping of sections", source=source)
    if overrides:
        data = apply_overrides(data, overrides, source)
        source += " (with --set)"
    for key in data:
        if key not in _SECTIONS:
            raise ScenarioError(
                "unknown section", source=source, key=str(key), allowed=", ".join(_SECTIONS)
            )
    sections = {k: _build_section(cls, data.get(k), k, source) for k, cls in _SECTIONS.items()}
    if "host" not in (data.get("robot") or {}):
        raise ScenarioError("the controller's address is required", source=source, key="robot.host")
    cfg = HwConfig(**sections, source=source)
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


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value)
    return value


def loopback_hw_config(
    path: str | os.PathLike[str],
    scenario: Scenario,
    twin,
    host: str,
    frames: str | os.PathLike[str] | None,
) -> Path:
    """Write the hw config of the loopback rig: the controller at ``host``, the frame
    file as the grabber's source, the scenario's phantom and protocol, the coarse mount
    the simulation hands the pipeline, and for each sphere the joint angles an operator
    would have taught (the true probe facing it at the protocol's depth, off by the
    teaching error). Computed on a copy of the twin: the served arm does not move."""
    if frames is None:
        raise ScenarioError("--hw-config needs --frames (the grabber's source)", key="--frames")
    rngs = stage_rngs(scenario)
    teacher = make_twin(scenario)
    truth = teacher.truth
    coarse = coarse_estimate(truth.T_ee_us, scenario.calibration, rngs["calibration"])
    depth = scenario.protocol.target_depth_mm * 1e-3
    taught: dict[str, list[float]] = {}
    for index in scenario.protocol.spheres:
        target = f"sphere_{index}"
        miss = rngs["protocol"].normal(0.0, scenario.protocol.teaching_error_mm * 1e-3, 3)
        T_face = facing_pose(truth.landmarks_base[target] + miss, depth)
        reading = teacher.robot.teach(T_face @ se3.invert(truth.T_ee_us), f"taught at {target}")
        taught[f"taught_{target}_deg"] = [float(v) for v in np.degrees(reading.q)]
    doc = {
        "robot": {
            "host": host,
            "speed_m_s": 0.25,
            "acceleration_m_s2": 1.5,
            # The controller's state stream may trail its command handshake by a few
            # packets under load: a short settle keeps the recorded pose the new one.
            "settle_s": 0.02,
            "connect_timeout_s": 3.0,
        },
        "grabber": {
            "source": os.fspath(Path(frames).resolve()),
            "pixel_spacing_mm": _plain(scenario.imaging.pixel_spacing_mm),
            "flush_frames": 0,
        },
        "rig": {
            "name": "loopback",
            "coarse_position_mm": _plain(coarse[:3, 3] * 1e3),
            "coarse_rotation_xyz_deg": _plain(np.degrees(se3.euler_from_matrix(coarse[:3, :3]))),
            "probe_depth_mm": float(scenario.imaging.depth_mm),
            "medium": scenario.medium.kind,
            "temperature_c": scenario.medium.temperature_c,
            "assumed_speed_m_s": scenario.imaging.assumed_speed_m_s,
            "sound_speed_correction": scenario.imaging.sound_speed_correction,
            "stylus_tip_mm": _plain(scenario.evaluation.stylus_tip_cad_mm),
            **taught,
        },
        "phantom": {k: _plain(v) for k, v in dataclasses.asdict(scenario.phantom).items()},
        "protocol": {k: _plain(v) for k, v in dataclasses.asdict(scenario.protocol).items()},
    }
    header = (
        f"# hw config of the loopback rig: the twin of {scenario.source} served on {host}\n"
        "# (uscal twin serve). Validate with `uscal acquire --dry-run`.\n"
    )
    return write_text_atomic(path, header + yaml.safe_dump(doc, sort_keys=False))


def emulated_operator(scenario: Scenario, twin) -> Callable[[list[str]], str]:
    """The loopback rig's emulated operator (dashboard ``twin ...`` commands of
    :class:`twin.ur_controller.LoopbackController`): ``mount stylus|probe`` changes the
    tool; ``touch <vertex> <index>`` hand-guides the true stylus tip onto the true vertex,
    leaning towards the phantom's middle, with the scenario's contact noise — as
    :func:`bench.experiment.simulate_touches` does."""
    vertices = {k: v for k, v in twin.truth.landmarks_base.items() if k.startswith("vertex_")}
    middle = np.mean(list(vertices.values()), axis=0)
    lean = {k: (middle - v) * np.array([1.0, 1.0, 0.0]) for k, v in vertices.items()}
    plan = {
        (t.vertex, t.index): t.R_base_ee
        for t in touch_plan(sorted(vertices), scenario.protocol, lean)
    }
    rng = stream(scenario.seed, TOUCH_GUIDE_KEY)
    guide = SimTouchGuide(
        twin.robot, vertices, twin.truth.p_ee_tip, scenario.tools.contact_noise_mm, rng
    )

    def operator(args: list[str]) -> str:
        if len(args) == 2 and args[0] == "mount" and args[1] in ("probe", "stylus"):
            twin.mount(args[1])
            return f"twin: {args[1]} mounted"
        if len(args) == 3 and args[0] == "touch":
            vertex, index = args[1], int(args[2])
            if (vertex, index) not in plan:
                raise ValueError(f"no touch {index} of {vertex} in the touch plan")
            guide.place(vertex, index, plan[(vertex, index)])
            return f"twin: tip on {vertex} (touch {index})"
        raise ValueError("commands: mount probe|stylus, touch <vertex> <index>")

    return operator
