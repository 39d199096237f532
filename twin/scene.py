"""The MuJoCo scene: UR arm built from a DH table, the mounted tool, phantom and tank.

The arm is built programmatically with :class:`mujoco.MjSpec` from the *same* DH table
that the numpy kinematics use (no hand-written XML, no downloaded assets). Body ``link<i>``
carries hinge ``joint<i>`` (the six hinges are the model's first six joints, in order from
the base); its frame is DH frame i-1 turned by the joint's theta offset, so the hinge is
the body's local z axis::

    body 1 in world:   Rz(theta_1)
    body i in body i-1: Tz(d_{i-1}) Tx(a_{i-1}) Rx(alpha_{i-1}) Rz(theta_i)
    site ee in body 6:  Tz(d_6) Tx(a_6) Rx(alpha_6)

Collision filtering: arm and tool geoms have contype 1 / conaffinity 0, phantom and tank
geoms contype 0 / conaffinity 1, so only arm/tool against phantom/tank can collide.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mujoco
import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray

from calib import se3
from calib.dh import DHTable, link_transform

from .phantoms import Phantom
from .tools import ToolGeom, ToolsConfig, tool_geoms, tool_mass_kg

__all__ = ["Contact", "Scene", "SceneModel", "build_spec", "export_scene"]

Array = NDArray[np.float64]

#: Rough link radii of a UR3 (m): base, shoulder/upper arm, forearm, three wrists.
LINK_RADII_M = (0.064, 0.045, 0.038, 0.032, 0.032, 0.032)

#: Link masses (kg) and centres of mass (m, in DH frame i, i.e. after link i's transform)
#: as Universal Robots publishes them for kinematics and dynamics calculations. They give
#: the joints' gravity torques (:meth:`SceneModel.gravity_torque`); the link geoms only
#: give collisions.
_UR3_CENTRES_OF_MASS = (
    (0, -0.02, 0),
    (0.13, 0, 0.1157),
    (0.05, 0, 0.0238),
    (0, 0, 0.01),
    (0, 0, 0.01),
    (0, 0, -0.02),
)
LINK_DYNAMICS: dict[str, tuple[tuple[float, ...], tuple[tuple[float, float, float], ...]]] = {
    "ur3": ((2.0, 3.42, 1.26, 0.8, 0.8, 0.35), _UR3_CENTRES_OF_MASS),
    # The e-series publishes other masses and the same centres of mass.
    "ur3e": ((1.98, 3.4445, 1.437, 0.871, 0.805, 0.261), _UR3_CENTRES_OF_MASS),
}

_ROBOT = {"contype": 1, "conaffinity": 0}
_ENVIRONMENT = {"contype": 0, "conaffinity": 1}
_RGBA = {
    "robot": [0.7, 0.72, 0.75, 1.0],
    "tool": [0.2, 0.3, 0.6, 1.0],
    "pla": [0.95, 0.85, 0.55, 1.0],
    "acrylic": [0.6, 0.8, 0.95, 0.3],
}


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything the twin's MuJoCo world holds, as truth.

    Attributes
    ----------
    table : DHTable
        The arm's DH table (the true arm for the twin, nominal for a nominal model).
    tools : ToolsConfig
        Mounted tool and its true mounting.
    phantom : Phantom
        The (true) phantom, in its own frame.
    T_base_phantom : (4, 4) float
        True phantom pose.
    tank : Phantom
        The tank, in its own frame.
    T_base_tank : (4, 4) float
    arm_model : str
        Whose published link masses the arm carries (``LINK_DYNAMICS``).
    """

    table: DHTable
    tools: ToolsConfig
    phantom: Phantom
    T_base_phantom: Array
    tank: Phantom
    T_base_tank: Array
    arm_model: str = "ur3"


@dataclass(frozen=True)
class Contact:
    """A penetration between an arm/tool geom and a phantom/tank geom (depth in metres)."""

    robot_geom: str
    environment_geom: str
    depth: float


def _quat_wxyz(R: Array) -> list[float]:
    """MuJoCo's (w, x, y, z) quaternion of a rotation matrix (kept inside twin/)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).ravel())
    return q.tolist()


def _place(element: object, T: Array) -> None:
    element.pos = T[:3, 3].tolist()  # type: ignore[attr-defined]
    element.quat = _quat_wxyz(T[:3, :3])  # type: ignore[attr-defined]


def _body_frames(table: DHTable) -> tuple[list[Array], Array]:
    """Poses of the six link bodies (each in its parent) and of the flange in body 6."""
    p = table.as_array()
    frames = []
    for i in range(6):
        before = np.eye(4) if i == 0 else link_transform(0.0, *p[i - 1, 1:])
        frames.append(before @ link_transform(p[i, 0], 0.0, 0.0, 0.0))
    return frames, link_transform(0.0, *p[5, 1:])


def _add_segment(
    body: mujoco.MjsBody, name: str, radius: float, a: Array, b: Array, shape: mujoco.mjtGeom
) -> None:
    if np.linalg.norm(b - a) < 1e-3:  # geometry only: skip sub-millimetre DH offsets
        return
    body.add_geom(
        name=name,
        type=shape,
        size=[radius, 0, 0],
        fromto=[*a.tolist(), *b.tolist()],
        rgba=_RGBA["robot"],
        **_ROBOT,
    )


def _add_arm(spec: mujoco.MjSpec, table: DHTable, model: str = "ur3") -> mujoco.MjsBody:
    """Six link bodies with hinges, capsules and the published masses; returns the last
    link body."""
    frames, T_6_flange = _body_frames(table)
    p = table.as_array()
    masses, centres = LINK_DYNAMICS[model]
    parent = spec.worldbody
    for i in range(6):
        body = parent.add_body(name=f"link{i + 1}")
        _place(body, frames[i])
        # Body i is DH frame i-1 turned by the joint; DH frame i sits at A_i(0) in it.
        body.explicitinertial = True
        body.mass = masses[i]
        body.ipos = se3.apply(link_transform(0.0, *p[i, 1:]), centres[i]).tolist()
        # UR: the rotational inertia of the small arms' links is negligible; a 3 cm
        # radius of gyration keeps the model valid (statics do not depend on it).
        body.inertia = [masses[i] * 0.03**2] * 3
        body.add_joint(
            name=f"joint{i + 1}",
            type=mujoco.mjtJoint.mjJNT_HINGE,
            axis=[0, 0, 1],
            range=[-2 * np.pi, 2 * np.pi],
        )
        # In body i the next DH origin sits at (a_i, 0, d_i): a segment up z, then along x.
        d, a = p[i, 1], p[i, 2]
        shape = mujoco.mjtGeom.mjGEOM_CYLINDER if i == 0 else mujoco.mjtGeom.mjGEOM_CAPSULE
        r = LINK_RADII_M[i]
        _add_segment(body, f"link{i + 1}_d", r, np.zeros(3), np.array([0, 0, d]), shape)
        _add_segment(
            body,
            f"link{i + 1}_a",
            r,
            np.array([0, 0, d]),
            np.array([a, 0, d]),
            mujoco.mjtGeom.mjGEOM_CAPSULE,
        )
        parent = body
    site = parent.add_site(name="ee")
    _place(site, T_6_flange)
    return parent


_SHAPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
}


def _volume(g: ToolGeom) -> float:
    if g.shape == "box":
        return 8.0 * g.size[0] * g.size[1] * g.size[2]
    r, half = g.size[0], g.size[1]
    return np.pi * r**2 * 2 * half + (4 / 3 * np.pi * r**3 if g.shape == "capsule" else 0.0)


def _add_tool(last_link: mujoco.MjsBody, T_6_flange: Array, tools: ToolsConfig) -> None:
    tool = last_link.add_body(name="tool")
    _place(tool, T_6_flange)
    geoms = tool_geoms(tools)
    # The tool's mass (the payload) spread uniformly over its shapes.
    density = tool_mass_kg(tools) / sum(_volume(g) for g in geoms)
    g: ToolGeom
    for g in geoms:
        geom = tool.add_geom(
            name=g.name,
            type=_SHAPES[g.shape],
            size=[*g.size, 0, 0][:3],
            rgba=_RGBA["tool"],
            density=density,
            **_ROBOT,
        )
        _place(geom, g.T_ee_geom)
    site = tool.add_site(name="us" if tools.mounted == "probe" else "tip")
    _place(site, tools.T_ee_us if tools.mounted == "probe" else se3.make(np.eye(3), tools.p_ee_tip))


def _add_meshes(spec: mujoco.MjSpec, phantom: Phantom, T_base: Array) -> None:
    body = spec.worldbody.add_body(name=phantom.name)
    _place(body, T_base)
    for part in phantom.parts:
        # MuJoCo collides a mesh's convex hull: a printed part gives its hull directly.
        mesh = part.mesh if part.collision_mesh is None else part.collision_mesh
        spec.add_mesh(
            name=part.name,
            uservert=mesh.vertices.ravel().tolist(),
            userface=mesh.faces.ravel().tolist(),
        )
        body.add_geom(
            name=part.name,
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=part.name,
            rgba=_RGBA.get(part.material, _RGBA["pla"]),
            **_ENVIRONMENT,
        )


def build_spec(scene: Scene) -> mujoco.MjSpec:
    """The scene as an :class:`mujoco.MjSpec` (meshes inline)."""
    spec = mujoco.MjSpec()
    spec.modelname = "uscal_twin"
    spec.compiler.degree = False
    last_link = _add_arm(spec, scene.table, scene.arm_model)
    _add_tool(last_link, _body_frames(scene.table)[1], scene.tools)
    _add_meshes(spec, scene.phantom, scene.T_base_phantom)
    _add_meshes(spec, scene.tank, scene.T_base_tank)
    spec.worldbody.add_light(pos=[0.3, 0, 1.5], dir=[0, 0, -1])
    return spec


class SceneModel:
    """A compiled scene: kinematics of the (true) arm and collision queries via MuJoCo."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.spec = build_spec(scene)
        self.model = self.spec.compile()
        self.data = mujoco.MjData(self.model)
        self._ee = self.model.site("ee").id
        # Geom ids that belong to the environment, for naming contacts.
        self._robot_geoms = {i for i in range(self.model.ngeom) if self.model.geom_contype[i] == 1}
        self._environment_geoms = [
            i for i in range(self.model.ngeom) if self.model.geom_conaffinity[i] == 1
        ]
        # For :meth:`clearance`: the arm's geoms each within a sphere about its origin
        # (MuJoCo's ``geom_rbound``), the environment's (fixed to the world) each within a
        # box along the scene's axes, from the corners of its own bounding box.
        self._arm = np.array(sorted(self._robot_geoms), dtype=np.int64)
        self._env = np.array(self._environment_geoms, dtype=np.int64)
        self._arm_reach = self.model.geom_rbound[self._arm]
        mujoco.mj_kinematics(self.model, self.data)
        corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
        lo, hi = [], []
        for g in self._env:
            centre, half = self.model.geom_aabb[g, :3], self.model.geom_aabb[g, 3:]
            R = self.data.geom_xmat[g].reshape(3, 3)
            world = (centre + corners * half) @ R.T + self.data.geom_xpos[g]
            # A plane is infinite; a geom on a moving body has no fixed box.
            moves = self.model.body_weldid[self.model.geom_bodyid[g]] != 0
            infinite = moves or self.model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
            lo.append(np.full(3, -np.inf) if infinite else world.min(axis=0))
            hi.append(np.full(3, np.inf) if infinite else world.max(axis=0))
        self._env_lo, self._env_hi = np.array(lo), np.array(hi)

    def set_q(self, q: ArrayLike) -> None:
        """Put the arm at joint angles ``q`` (6,), radians, and update kinematics."""
        self.data.qpos[:6] = np.asarray(q, dtype=float)
        mujoco.mj_kinematics(self.model, self.data)

    def site_pose(self, name: str) -> Array:
        """Pose of a site in the base (world) frame, (4, 4), at the current ``q``."""
        site = self.model.site(name)
        return se3.make(self.data.site_xmat[site.id].reshape(3, 3), self.data.site_xpos[site.id])

    def flange_pose(self, q: ArrayLike) -> Array:
        """``T_base_ee`` (4, 4) of the MuJoCo arm at ``q``."""
        self.set_q(q)
        return se3.make(self.data.site_xmat[self._ee].reshape(3, 3), self.data.site_xpos[self._ee])

    def gravity_torque(self, q: ArrayLike) -> Array:
        """Torques (6,) in N m the joints exert to hold the arm and its tool still at
        ``q`` against gravity: MuJoCo's bias force at zero velocity (recursive
        Newton–Euler over the published link masses and the tool's mass)."""
        self.data.qpos[:6] = np.asarray(q, dtype=float)
        self.data.qvel[:] = 0.0
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)
        tau = np.zeros(self.model.nv)
        mujoco.mj_rne(self.model, self.data, 0, tau)
        return tau[:6].copy()

    def collisions(self, q: ArrayLike, ignore: tuple[str, ...] = ()) -> list[Contact]:
        """Contacts (penetration ≥ 0) between arm/tool and phantom/tank at ``q``.

        ``ignore`` names geoms whose contacts do not count (e.g. the stylus tip touching a
        vertex on purpose).
        """
        self.data.qpos[:6] = np.asarray(q, dtype=float)
        mujoco.mj_forward(self.model, self.data)
        contacts = []
        for k in range(self.data.ncon):
            c = self.data.contact[k]
            if c.dist > 0:
                continue
            g1, g2 = int(c.geom1), int(c.geom2)
            if g1 not in self._robot_geoms:
                g1, g2 = g2, g1
            names = (self.model.geom(g1).name, self.model.geom(g2).name)
            if names[0] in ignore or names[1] in ignore:
                continue
            contacts.append(Contact(names[0], names[1], float(-c.dist)))
        return contacts

    def clearance(self, q: ArrayLike, within: float) -> float:
        """The smallest distance (m) between the arm or tool and the phantom or tank at
        ``q``, up to ``within`` (``within`` when nothing is nearer; negative when they
        overlap): MuJoCo's exact geom distances (``mj_geomDistance``).

        Pairs are taken nearest first by their bounds (a sphere about each arm geom, a box
        about each environment geom), and none is asked whose bounds are already further
        apart than the nearest distance found: the same
        result as asking every pair (tests/test_scene.py), at a few of the pairs' cost (a
        plan's candidates ask ≈ 10⁵ poses)."""
        self.set_q(q)
        nearest = float(within)
        centre = self.data.geom_xpos[self._arm]  # (A, 3)
        outside = np.maximum(
            self._env_lo[None] - centre[:, None], centre[:, None] - self._env_hi[None]
        )
        lower = np.linalg.norm(np.maximum(outside, 0.0), axis=2) - self._arm_reach[:, None]
        lower = lower.ravel()
        n_env = len(self._env)
        for k in np.argsort(lower):
            if lower[k] >= nearest:
                break
            g1, g2 = self._arm[k // n_env], self._env[k % n_env]
            d = mujoco.mj_geomDistance(self.model, self.data, int(g1), int(g2), nearest, None)
            nearest = min(nearest, float(d))
        return nearest


def export_scene(scene: Scene, outdir: str | os.PathLike[str]) -> list[str]:
    """Write ``outdir/scene.xml`` (MJCF via ``MjSpec.to_xml``) and ``outdir/meshes/*.stl``.

    The MJCF references the STL files, so it opens in MuJoCo's own viewer. Returns the
    written file names relative to ``outdir``. ``outdir`` must exist.
    """
    spec = build_spec(scene)
    mesh_dir = os.path.join(os.fspath(outdir), "meshes")
    os.makedirs(mesh_dir, exist_ok=True)
    written = []
    parts = {p.name: p.mesh for ph in (scene.phantom, scene.tank) for p in ph.parts}
    for mesh in spec.meshes:
        part: trimesh.Trimesh = parts[mesh.name]
        filename = f"{mesh.name}.stl"
        part.export(os.path.join(mesh_dir, filename))
        written.append(f"meshes/{filename}")
        mesh.file = filename
        mesh.uservert = []
        mesh.userface = []
    spec.meshdir = "meshes"
    # to_xml compiles the spec; relative mesh paths resolve against modelfiledir.
    spec.modelfiledir = os.path.abspath(os.fspath(outdir))
    with open(os.path.join(os.fspath(outdir), "scene.xml"), "w", encoding="utf-8") as fh:
        fh.write(spec.to_xml())
    return ["scene.xml", *written]
