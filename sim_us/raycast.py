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

from .materials import Material
from .wires import Wire

__all__ = ["AcousticScene", "Hits", "RayCaster", "ScenePart"]

Array = NDArray[np.float64]

_SMOOTH_MAX_ANGLE = np.radians(20.0)


@dataclass(frozen=True, eq=False)
class ScenePart:
    """A closed mesh of one material (a name from :data:`~sim_us.materials.MATERIALS`, or
    a :class:`~sim_us.materials.Material` of its own), in the scene frame (metres).

    A textured part (a printed surface: layer lines, roughness) also carries the surface
    the sound's specular lobe follows: ``acoustic_vertices`` (V, 3), the part's vertices
    before the texture (same faces as ``mesh``; the part's shape error included), and
    ``texture_rms_m`` (V,), the rms height of the texture along the normal at each vertex
    (m), with ``texture_length_m`` its roughness's correlation length along the surface (m;
    its facets tilt by ``rms / length`` rms). A printed part's share of that variance which
    is its layer staircase, ``texture_layer_share`` (V,), with the layer height ``layer_m``
    (m) and the build direction ``build_axis`` (3,), scene frame: the staircase's treads
    are small mirrors facing the build direction. The echo's position stays on ``mesh``;
    its normal and its coherent share come from these (see :mod:`sim_us.propagation`).
    None: an untextured part.
    """

    name: str
    mesh: trimesh.Trimesh
    material: str | Material
    acoustic_vertices: Array | None = None
    texture_rms_m: Array | None = None
    texture_length_m: float = 4e-4
    texture_layer_share: Array | None = None
    layer_m: float = 0.0
    build_axis: Array | None = None


@dataclass(frozen=True, eq=False)
class AcousticScene:
    """What the probe can see: solid parts in one frame, and wires (thinner than the
    beam: drawn as line targets, :mod:`sim_us.wires`, not ray-cast). Ground truth stays
    with the caller; the simulator only renders."""

    parts: tuple[ScenePart, ...]
    wires: tuple[Wire, ...] = ()


@dataclass(frozen=True)
class Hits:
    """First hits of a batch of rays.

    ``t`` distance (m; inf for a miss), ``part`` index into the scene's parts (−1 for a
    miss), ``normal`` outward unit surface normal (smooth: interpolated vertex normals;
    textured: the un-textured surface's). ``texture_rms`` (n,) the rms texture height at
    the hit (m, 0 off textured parts), ``texture_slope`` (n,) the rms tilt of its
    roughness's facets (rad) and ``layer_share`` (n,) the layer staircase's share of its
    variance; None when no part of the scene is textured.
    """

    t: Array
    part: NDArray[np.int64]
    normal: Array
    texture_rms: Array | None = None
    texture_slope: Array | None = None
    layer_share: Array | None = None


class RayCaster:
    """An Embree scene of an :class:`AcousticScene`."""

    def __init__(self, scene: AcousticScene) -> None:
        self.parts = scene.parts
        self._faces: list[NDArray[np.int64]] = []
        self._vertex_normals: list[Array | None] = []
        self._face_normals: list[Array] = []
        # Textured parts: per face, whether its vertex normals are interpolated; the
        # texture's rms height per vertex.
        self._smooth_faces: list[NDArray[np.bool_] | None] = []
        self._texture_rms: list[Array | None] = []
        self._layer_share: list[Array | None] = []
        self.textured = any(p.acoustic_vertices is not None for p in scene.parts)
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
            # Plain arrays: the binding reads trimesh's tracked arrays element by element,
            # each read a subclass view (≈ 1 s per twin for the textured meshes).
            TriangleMesh(
                scene=self._scene,
                vertices=np.asarray(part.mesh.vertices - self.origin, dtype=np.float32).view(
                    np.ndarray
                ),
                indices=np.asarray(part.mesh.faces, dtype=np.int32).view(np.ndarray),
            )
            self._faces.append(np.asarray(part.mesh.faces))
            if part.acoustic_vertices is not None:
                self._add_textured(part)
                continue
            self._smooth_faces.append(None)
            self._texture_rms.append(None)
            self._layer_share.append(None)
            # Smooth (interpolated vertex) normals only for smooth surfaces such as the
            # spheres; a box's or cone's vertex normals average across its sharp edges.
            smooth = part.mesh.face_adjacency_angles.max() < _SMOOTH_MAX_ANGLE
            self._vertex_normals.append(np.asarray(part.mesh.vertex_normals) if smooth else None)
            self._face_normals.append(np.asarray(part.mesh.face_normals))

    def _add_textured(self, part: ScenePart) -> None:
        """Normals of a textured part from its un-textured surface: area-weighted vertex
        normals, interpolated on the faces where they stay within ``_SMOOTH_MAX_ANGLE`` of
        the face's own normal (a curved surface), the face normal where they do not (a
        face along a sharp edge of the shape: a cone's rim, a prism's end faces).
        Degenerate faces of the un-textured surface (a staircase's top tread on a ridge
        or apex) take the vertex normals."""
        faces = np.asarray(part.mesh.faces)
        tri = np.asarray(part.acoustic_vertices, dtype=float)[faces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # 2 × area × normal
        # Σ over a vertex's faces, per axis (bincount: ≈ 20× faster than np.add.at).
        n_v, corners = len(part.acoustic_vertices), faces.T.ravel()
        vn = np.column_stack(
            [np.bincount(corners, np.tile(cross[:, k], 3), minlength=n_v) for k in range(3)]
        )
        norm = np.linalg.norm(vn, axis=1, keepdims=True)
        vn = np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)
        area = np.linalg.norm(cross, axis=1, keepdims=True)
        fn = np.divide(cross, area, out=np.zeros_like(cross), where=area > 0)
        cos_min = np.cos(_SMOOTH_MAX_ANGLE)
        agree = np.ones(len(faces), dtype=bool)
        for j in range(3):
            agree &= np.einsum("fj,fj->f", vn[faces[:, j]], fn) > cos_min
        self._vertex_normals.append(vn)
        self._face_normals.append(fn)
        self._smooth_faces.append(agree | (area[:, 0] == 0))
        rms = part.texture_rms_m
        self._texture_rms.append(
            np.zeros(len(vn)) if rms is None else np.broadcast_to(np.asarray(rms, float), len(vn))
        )
        share = part.texture_layer_share
        self._layer_share.append(
            np.zeros(len(vn))
            if share is None
            else np.broadcast_to(np.asarray(share, float), len(vn))
        )

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
        rms = np.zeros(n) if self.textured else None
        slope = np.zeros(n) if self.textured else None
        share = np.zeros(n) if self.textured else None
        if n == 0 or self._scene is None:
            return Hits(t, part, normal, rms, slope, share)
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
            w0, w1, w2 = (1.0 - u[sel] - v[sel])[:, None], u[sel][:, None], v[sel][:, None]
            nrm = w0 * vn[tri[:, 0]] + w1 * vn[tri[:, 1]] + w2 * vn[tri[:, 2]]
            smooth = self._smooth_faces[g]
            if smooth is None:
                normal[idx[sel]] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
                continue
            # A textured part: its un-textured surface's normal, its texture's rms height.
            length = np.linalg.norm(nrm, axis=1, keepdims=True)
            flat = ~smooth[prim[sel]] | (length[:, 0] < 1e-6)
            nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
            nrm[flat] = self._face_normals[g][prim[sel][flat]]
            normal[idx[sel]] = nrm
            h = self._texture_rms[g]
            rms[idx[sel]] = (
                w0[:, 0] * h[tri[:, 0]] + w1[:, 0] * h[tri[:, 1]] + w2[:, 0] * h[tri[:, 2]]
            )
            q = self._layer_share[g]
            share[idx[sel]] = (
                w0[:, 0] * q[tri[:, 0]] + w1[:, 0] * q[tri[:, 1]] + w2[:, 0] * q[tri[:, 2]]
            )
            # The roughness's facets (the rest of the variance) tilt by σ_r / ℓ.
            sigma_r = rms[idx[sel]] * np.sqrt(np.clip(1.0 - share[idx[sel]], 0.0, 1.0))
            slope[idx[sel]] = sigma_r / self.parts[g].texture_length_m
        return Hits(t, part, normal, rms, slope, share)
