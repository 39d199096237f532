"""The calibration for ROS 2: ``us_probe.urdf.xacro`` (a fixed joint from the flange link
to an ``us_image`` link carrying ``T_ee_us``) and the equivalent ``static_transform_
publisher`` command.

URDF's ``origin`` is ``xyz`` (metres) and ``rpy`` (radians): roll, pitch, yaw about the
parent's fixed x, y, z axes, i.e. ``R = Rz(yaw) Ry(pitch) Rx(roll)`` — scipy's extrinsic
``"xyz"`` Euler angles. Numbers are written with ``repr`` (shortest round-trip text), so
the transform composed back from the file is ``T_ee_us`` to the last bits of the Euler
conversion (≈ 1e-16).
"""

from __future__ import annotations

import warnings
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

__all__ = ["URDF_FILE", "rpy_of", "static_transform_command", "urdf_xacro"]

URDF_FILE = "us_probe.urdf.xacro"


def rpy_of(T: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """``(xyz, rpy)`` of a transform as URDF's ``origin`` takes them."""
    T = np.asarray(T, dtype=float)
    with warnings.catch_warnings():
        # At pitch ±90° roll and yaw share one axis: scipy sets yaw to 0 and warns; the
        # angles still compose to the same rotation, which is all URDF needs.
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(T[:3, :3]).as_euler("xyz")
    return T[:3, 3].copy(), rpy


def _numbers(v: ArrayLike) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(v))


def urdf_xacro(T_ee_us: ArrayLike, parent: str = "tool0", child: str = "us_image") -> str:
    """The xacro file: a macro ``us_probe`` (``parent``, ``prefix``) adding the ``child``
    link on a fixed joint, and, unless the includer sets the ``us_probe_standalone``
    argument to false, a standalone robot (the parent link and the macro) that
    ``xacro`` turns into a complete URDF."""
    xyz, rpy = rpy_of(T_ee_us)
    return f"""<?xml version="1.0"?>
<!-- uscal calibration: T_ee_us, the ultrasound image frame (us: origin at the centre of
     the transducer face, x lateral along increasing columns, y axial = depth,
     z = x × y) in the flange frame, as a fixed joint.
     Standalone:  xacro {URDF_FILE} > us_probe.urdf
     In a robot description (e.g. ur_description's ur.urdf.xacro):
       <xacro:arg name="us_probe_standalone" default="false"/>
       <xacro:include filename="{URDF_FILE}"/>
       <xacro:us_probe parent="tool0" prefix=""/> -->
<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="us_probe">
  <xacro:macro name="us_probe" params="parent:={parent} prefix:=''">
    <link name="${{prefix}}{child}"/>
    <joint name="${{prefix}}{child}_joint" type="fixed">
      <parent link="${{parent}}"/>
      <child link="${{prefix}}{child}"/>
      <origin xyz={quoteattr(_numbers(xyz))} rpy={quoteattr(_numbers(rpy))}/>
    </joint>
  </xacro:macro>
  <xacro:arg name="us_probe_standalone" default="true"/>
  <xacro:if value="$(arg us_probe_standalone)">
    <link name="{parent}"/>
    <xacro:us_probe parent="{parent}"/>
  </xacro:if>
</robot>
"""


def static_transform_command(
    T_ee_us: ArrayLike, parent: str = "tool0", child: str = "us_image"
) -> str:
    """The ROS 2 command that publishes ``T_ee_us`` as a static transform (quaternion:
    no Euler convention to get wrong)."""
    T = np.asarray(T_ee_us, dtype=float)
    x, y, z = (repr(float(v)) for v in T[:3, 3])
    qx, qy, qz, qw = (repr(float(v)) for v in Rotation.from_matrix(T[:3, :3]).as_quat())
    return (
        f"ros2 run tf2_ros static_transform_publisher --x {x} --y {y} --z {z} "
        f"--qx {qx} --qy {qy} --qz {qz} --qw {qw} --frame-id {parent} --child-frame-id {child}"
    )
