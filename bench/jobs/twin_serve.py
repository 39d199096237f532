"""``uscal twin serve`` and ``uscal twin export``: the twin as a loopback UR controller
(RTDE, dashboard and script ports; the simulated scanner's frames to a file; an emulated
operator for the touches) with a hw config for ``uscal acquire`` against it, and the
twin's scene as MJCF + STL meshes with its ground truth (``truth.yaml``)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib import se3
from calib.acquisition.protocol import touch_plan
from calib.errors import ScenarioError
from twin.scene import export_scene
from twin.touch import SimTouchGuide
from twin.ur_controller import ControllerFaults, LoopbackController
from twin.world import GroundTruth

from ..acquire_sim import coarse_estimate, make_imager, make_twin, teach_at
from ..config.scenario import Scenario
from ..files import atomic_output_dir, write_text_atomic
from ..sessions import TOUCH_GUIDE_KEY, stage_rngs, stream

__all__ = ["emulated_operator", "export_twin", "loopback_hw_config", "serve_twin"]


def serve_twin(
    scenario: Scenario,
    host: str,
    frames: str | None,
    hw_config: str | None,
    faults: ControllerFaults,
    tcp_offset: Sequence[float] = (0.0,) * 6,
) -> LoopbackController:
    """A started loopback controller whose arm is the scenario's twin (and, with
    ``hw_config``, the hw config that reaches it written); ``tcp_offset`` its installation's
    active TCP ([x, y, z, rx, ry, rz], metres and a rotation vector)."""
    twin = make_twin(scenario)
    imager = make_imager(scenario, twin) if frames else None
    controller = LoopbackController(
        twin.robot, imager, frames, host, faults, emulated_operator(scenario, twin), tcp_offset
    )
    controller.start()
    if hw_config:
        loopback_hw_config(hw_config, scenario, twin, host, frames)
    return controller


def truth_document(scenario: Scenario, truth: GroundTruth) -> dict[str, Any]:
    """``truth.yaml``: the twin's true landmarks, sphere radii, mount, stylus tip and DH
    table (mm where the key says so)."""
    table = truth.dh_table
    return {
        "scenario": scenario.source,
        "seed": scenario.seed,
        "landmarks_base_mm": landmarks_mm(truth),
        "sphere_radii_mm": {k: round(1e3 * v, 4) for k, v in truth.sphere_radii.items()},
        "T_ee_us": np.round(truth.T_ee_us, 9).tolist(),
        "stylus_tip_ee_mm": np.round(1e3 * truth.p_ee_tip, 4).tolist(),
        "dh_true": {
            k: list(v)
            for k, v in zip(
                ("theta_rad", "d_m", "a_m", "alpha_rad"),
                (table.theta, table.d, table.a, table.alpha),
                strict=True,
            )
        },
    }


def landmarks_mm(truth: GroundTruth) -> dict[str, list[float]]:
    """The true landmarks in the base frame, mm."""
    return {k: [round(1e3 * float(v), 4) for v in p] for k, p in truth.landmarks_base.items()}


def export_twin(
    scenario: Scenario, outdir: str | os.PathLike[str], force: bool
) -> tuple[list[str], GroundTruth]:
    """The scene as MJCF + STL meshes and ``truth.yaml``, in a new directory; returns
    the files and the truth."""
    twin = make_twin(scenario)
    with atomic_output_dir(outdir, force=force) as tmp:
        files = export_scene(twin.scene.scene, tmp)
        doc = truth_document(scenario, twin.truth)
        (tmp / "truth.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        files.append("truth.yaml")
    return files, twin.truth


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
        reading = teach_at(
            teacher,
            truth.landmarks_base[target],
            depth,
            f"taught at {target}",
            rngs["protocol"],
            scenario.protocol.teaching_error_mm,
        )
        taught[f"taught_{target}_deg"] = [float(v) for v in np.degrees(reading.q)]
    doc = {
        "robot": {
            "host": host,
            "speed_m_s": 0.25,
            "acceleration_m_s2": 1.5,
            # The controller's state stream may trail its command handshake by a few
            # packets under load: a short settle keeps the recorded pose the new one.
            "settle_s": 0.005,
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
    :func:`bench.acquire_sim.simulate_touches` does."""
    vertices = {k: v for k, v in twin.truth.landmarks_base.items() if k.startswith("vertex_")}
    middle = np.mean(list(vertices.values()), axis=0)
    lean = {k: (middle - v) * np.array([1.0, 1.0, 0.0]) for k, v in vertices.items()}
    plan = {
        (t.vertex, t.index): t.R_base_ee
        for t in touch_plan(sorted(vertices), scenario.protocol, lean=lean)
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


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value)
    return value
