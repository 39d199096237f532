"""ROS 2 output: ``us_probe.urdf.xacro`` expanded by the real ``xacro`` and parsed by ROS's
URDF parser (``urdf_parser_py``), composed back to ``T_ee_us``; the static transform
command; what a run writes."""

from __future__ import annotations

import shlex

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from bench.outputs.ros import URDF_FILE, static_transform_command, urdf_xacro
from calib import se3

xacro = pytest.importorskip("xacro")
urdf = pytest.importorskip("urdf_parser_py.urdf")


def _joint_transform(robot, child: str) -> np.ndarray:
    """The fixed joint into ``child``, as URDF defines origin: R = Rz(y) Ry(p) Rx(r)."""
    (joint,) = [j for j in robot.joints if j.child == child]
    assert joint.type == "fixed"
    r, p, y = joint.origin.rpy
    R = (
        Rotation.from_rotvec([0, 0, y]) * Rotation.from_rotvec([0, p, 0])
        * Rotation.from_rotvec([r, 0, 0])
    )  # fmt: skip
    return se3.make(R.as_matrix(), joint.origin.xyz)


def _transforms(rng: np.random.Generator) -> list[np.ndarray]:
    Ts = [se3.make(se3.matrix_from_rotvec(rng.normal(0, 1.5, 3)), rng.normal(0, 0.1, 3))
          for _ in range(20)]  # fmt: skip
    # Pitch at ±90° (gimbal lock) and the identity.
    Ts.append(se3.make(Rotation.from_euler("xyz", [0.3, np.pi / 2, -1.0]).as_matrix(), [0, 0, 0.2]))
    Ts.append(se3.make(Rotation.from_euler("xyz", [0.0, -np.pi / 2, 2.0]).as_matrix(), [0.1, 0, 0]))
    Ts.append(np.eye(4))
    return Ts


def test_standalone_urdf_round_trips_to_the_transform(tmp_path, rng):
    for k, T in enumerate(_transforms(rng)):
        path = tmp_path / f"{k}.urdf.xacro"
        path.write_text(urdf_xacro(T), encoding="utf-8")
        robot = urdf.URDF.from_xml_string(xacro.process_file(str(path)).toxml())
        assert robot.get_root() == "tool0"
        back = _joint_transform(robot, "us_image")
        assert np.max(np.abs(back - T)) <= 1e-9, k


def test_included_in_a_robot_description_with_its_own_flange(tmp_path, rng):
    T = _transforms(rng)[0]
    (tmp_path / URDF_FILE).write_text(urdf_xacro(T, "flange", "probe_image"), encoding="utf-8")
    (tmp_path / "robot.urdf.xacro").write_text(
        '<?xml version="1.0"?>\n<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="ur3">\n'
        '  <xacro:arg name="us_probe_standalone" default="false"/>\n'
        f'  <xacro:include filename="{URDF_FILE}"/>\n'
        '  <link name="base_link"/><link name="left_tool0"/>\n'
        '  <joint name="arm" type="fixed"><parent link="base_link"/>'
        '<child link="left_tool0"/></joint>\n'
        '  <xacro:us_probe parent="left_tool0" prefix="left_"/>\n</robot>\n',
        encoding="utf-8",
    )
    doc = xacro.process_file(str(tmp_path / "robot.urdf.xacro"))
    robot = urdf.URDF.from_xml_string(doc.toxml())
    assert sorted(link.name for link in robot.links) == [
        "base_link", "left_probe_image", "left_tool0"
    ]  # fmt: skip
    (joint,) = [j for j in robot.joints if j.child == "left_probe_image"]
    assert joint.parent == "left_tool0"
    assert np.max(np.abs(_joint_transform(robot, "left_probe_image") - T)) <= 1e-9


def test_static_transform_command_is_the_transform(rng):
    T = _transforms(rng)[1]
    words = shlex.split(static_transform_command(T, "tool0", "us_image"))
    assert words[:4] == ["ros2", "run", "tf2_ros", "static_transform_publisher"]
    opts = dict(zip(words[4::2], words[5::2], strict=True))
    assert opts["--frame-id"] == "tool0" and opts["--child-frame-id"] == "us_image"
    q = [float(opts[f"--q{a}"]) for a in "xyzw"]
    back = se3.make(Rotation.from_quat(q).as_matrix(), [float(opts[f"--{a}"]) for a in "xyz"])
    assert np.max(np.abs(back - T)) <= 1e-12


def test_a_run_writes_the_urdf_and_the_command(quick_run):
    out, _, m, _ = quick_run
    T = np.array(m["calibration"]["single"]["T_ee_us"])
    robot = urdf.URDF.from_xml_string(xacro.process_file(str(out / URDF_FILE)).toxml())
    assert np.max(np.abs(_joint_transform(robot, "us_image") - T)) <= 1e-9
    doc = yaml.safe_load((out / "calibration.yaml").read_text(encoding="utf-8"))
    command = doc["ros"]["static_transform_publisher"]
    assert command == static_transform_command(T)
    assert command in (out / "report.md").read_text(encoding="utf-8")


def test_link_names_are_validated(capsys):
    from .conftest import QUICK
    from .test_cli import uscal_here

    r = uscal_here(capsys, "check", str(QUICK), "--set", "output.ros_parent_link=tool 0")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "output.ros_parent_link" in r.stderr
