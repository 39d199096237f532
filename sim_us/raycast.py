"""Ray casting against the scene's meshes with Embree.

The scene is a set of closed meshes in one frame (``scene``, e.g. the robot base), each
with a material name. Rays are traced through all surfaces they meet (entering and
leaving solids) until they leave the imaged depth or their echoes fall below the display
floor.

Embree is called through ``embreex`` directly rather than through trimesh's
``RayMeshIntersector``: trimesh's multi-hit loop re-casts every ray at every pass and
costs ≈ 14 ms for one frame's rays, while per-ray distance limits and early termination
here bring it to ≈ 1 ms per pass (measured by ``benchmarks/sim_us.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from numpy.typing import NDArray

__all__ = ["AcousticScene", "Hits", "RayCaster", "ScenePart"]

Array = NDArray[np.float64]

_SMOOTH_MAX_ANGLE = np.radians(20.0)


@dataclass(frozen=True, eq=False)
class ScenePart:
    """A closed mesh of one material, in the scene frame (metres)."""

    name: str
    mesh: trimesh.Trimesh
    material: str


@dataclass(frozen=True, eq=False)
class AcousticScene:
    """What the probe can see: solid parts in one frame. Ground truth stays with the
    caller; the simulator only renders."""

    parts: tuple[ScenePart, ...]


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays.

    ``t`` distance (m; inf for a miss), ``part`` index into the scene's parts (−1 for a
    miss), ``normal`` outward unit surface normal (smooth: interpolated vertex normals).
    """

    t: Array
    part: NDArray[np.int64]
    normal: Array


class RayCaster:
    """An Embree scene of an :class:`AcousticScene`."""

    def __init__(self, scene: AcousticScene) -> None:
        self.parts = scene.parts
        self._faces: list[NDArray[np.int64]] = []
        self._vertex_normals: list[Array | None] = []
        self._face_normals: list[Array] = []
        self._scene = rtcore_scene.EmbreeScene() if scene.parts else None
        if not scene.parts:  # an empty scene (e.g. a gel block): every ray misses
            self.origin = np.zeros(3)
            return
        # Embree works in float32: shift coordinates to the scene's centre so the
        # precision (≈ 1e-8 m at 0.3 m) is spent where the geometry is.
        lo = np.min([p.mesh.bounds[0] for p in scene.parts], axis=0)
        hi = np.max([p.mesh.bounds[1] for p in scene.parts], axis=0)
        self.origin = (lo + hi) / 2
        for part in scene.parts:
            TriangleMesh(
                scene=self._scene,
                vertices=(part.mesh.vertices - self.origin).astype(np.float32),
                indices=part.mesh.faces.astype(np.int32),
            )
            self._faces.append(np.asarray(part.mesh.faces))
            # Smooth (interpolated vertex) normals only for smooth surfaces such as the
            # spheres; a box's or cone's vertex normals average across its sharp edges.
            smooth = part.mesh.face_adjacency_angles.max() < _SMOOTH_MAX_ANGLE
            self._vertex_normals.append(np.asarray(part.mesh.vertex_normals) if smooth else None)
            self._face_normals.append(np.asarray(part.mesh.face_normals))

    def first_hits(self, origins: Array, directions: Array, max_dist: Array) -> Hits:
        """Nearest surface along each ray within ``max_dist`` (m).

        Parameters
        ----------
        origins, directions : (n, 3) float, scene frame (directions unit length)
        max_dist : (n,) float, metres
        """
        n = len(origins)
        t = np.full(n, np.inf)
        part = np.full(n, -1, dtype=np.int64)
        normal = np.zeros((n, 3))
        if n == 0 or self._scene is None:
            return Hits(t, part, normal)
        res = self._scene.run(
            (origins - self.origin).astype(np.float32),
            directions.astype(np.float32),
            dists=np.asarray(max_dist, dtype=np.float32),
            output=1,
        )
        hit = res["geomID"] >= 0
        idx = np.nonzero(hit)[0]
        t[idx] = res["tfar"][idx]
        geom = res["geomID"][idx].astype(np.int64)
        part[idx] = geom
        prim, u, v = res["primID"][idx], res["u"][idx], res["v"][idx]
        for g in np.unique(geom):
            sel = geom == g
            vn = self._vertex_normals[g]
            if vn is None:
                normal[idx[sel]] = self._face_normals[g][prim[sel]]
                continue
            tri = self._faces[g][prim[sel]]
            nrm = (
                (1.0 - u[sel] - v[sel])[:, None] * vn[tri[:, 0]]
                + u[sel][:, None] * vn[tri[:, 1]]
                + v[sel][:, None] * vn[tri[:, 2]]
            )
            normal[idx[sel]] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        return Hits(t, part, normal)
