"""What a 3-D printer makes of a phantom's CAD: layer lines, roughness, shape error.

The CAD frame of a phantom is also its build frame: origin at the centre of the bottom
face (on the build plate), z up = build direction. A printed surface differs from the CAD
by four effects, each a displacement of a finely meshed copy of the CAD surface:

- **Layer lines** (``layer`` h). A slicer cuts the CAD into layers of height h and prints
  layer k as the CAD's cross-section at its mid-height ``z_k = (k + 1/2) h`` (the usual
  "middle" slicing tolerance), extruded over the layer. A surface whose normal makes an
  angle α with z becomes a staircase: vertical risers through the CAD surface at ``z_k``
  and horizontal treads at the layer boundaries ``k h``. Over a locally planar surface
  the staircase is a graph along the CAD normal: an asymmetric triangle wave of amplitude
  ``±(h/2) cos α``, rising over the riser (a share ``sin² α`` of a layer, in CAD z) and
  falling over the tread (``cos² α``). It is largest where the surface is nearly
  horizontal and vanishes on vertical walls; every point of a tread lies exactly at a
  layer boundary, so a horizontal face prints at ``round(z / h) h``. Implemented as
  :func:`layer_offset`, exact on planes (the cone's and prism's faces) and to the mesh's
  resolution on curved surfaces (the spheres).
- **Roughness** (``ra``, ``roughness_length``). A stationary Gaussian height field along
  the normal with a Gaussian covariance of correlation length ℓ (≈ the extrusion width,
  0.4 mm for FDM), drawn as a sum of random Fourier modes (Rahimi & Recht) so that it
  can be evaluated at any point independently of the mesh; its 1 σ is ``Ra √(π/2)`` (the
  mean absolute height of a Gaussian field is σ √(2/π)).
- **Shape error** of the cone and prism, low order: linear shrinkage (in-plane ``shrink_xy``
  and along the build direction ``shrink_z``, about the bottom-face centre); warping of the
  base (its first layers curl up as the layers above cool and contract: a lift
  ``κ ρ² / 2`` growing with the distance from the centre, the base's far edges lifting by
  ``warp`` while its centre stays on the plate, fading over the first ≈ 5 mm of height
  because later layers are laid flat at the nozzle's height);
  and a sag or bulge of the prism's large flat faces (a half-sine pillow of amplitude
  ``sag`` along the face normal, zero at the face's edges, sign drawn per face).
- **Out-of-roundness** of the spheres: a radial deviation made of degree-2 and degree-3
  real spherical harmonics (ellipsoidal and trefoil-like shapes: the low orders that a
  printer's axis scaling, backlash and the overhang of the lower hemisphere produce),
  coefficients drawn so that the expected rms radial deviation is ``roundness``. Degrees 0
  and 1 (size and position) are left to the printing tolerances of the phantom.

A textured part also keeps what the ultrasound simulator needs to reflect from it as a
rough surface (Kirchhoff approximation, see ``sim_us.propagation``): in its mesh's
``metadata``, ``acoustic_vertices`` (its vertices before the texture, the shape error
included: the surface averaged over the beam's footprint) and ``texture_rms_m`` (the
texture's rms height along the normal per vertex, :func:`texture_rms`) with
``texture_layer_share`` (the layer staircase's share of it, :func:`layer_share`) and
``layer_m`` (the layer height).

Each printed part draws from its own random stream, a child of the phantom's generator's
seed sequence with a named spawn key per effect (``*_SPAWN_KEY`` below) and the part's
index, so turning one effect on changes no other draw. With every effect off nothing is
drawn and the phantom builder keeps today's meshes.
"""

from __future__ import annotations

import hashlib
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.special import sph_harm_y

from sim_us.disk_cache import write_whole

__all__ = [
    "PrintSettings",
    "fit_sphere",
    "forget_parts",
    "layer_offset",
    "layer_share",
    "part_stream",
    "printed_cone",
    "printed_prism",
    "printed_sphere",
    "roughness_height",
    "sphere_subdivisions",
    "texture_rms",
    "use_disk_cache",
]

Array = NDArray[np.float64]

#: Spawn keys of the printing streams (children of the phantom generator's seed sequence).
ROUGHNESS_SPAWN_KEY = 421
SHAPE_SPAWN_KEY = 422
ROUNDNESS_SPAWN_KEY = 423
SAG_SPAWN_KEY = 424

_ROUGHNESS_MODES = 128  # random Fourier modes: a sum of 128 cosines is near Gaussian
_MAX_SPHERE_SUBDIVISIONS = 7  # 327 680 faces, edges ≈ 47 µm at r = 5 mm (≈ 23 MB of mesh)
_MIN_SPHERE_SUBDIVISIONS = 4  # the CAD sphere's own resolution
_COARSE_STEP = 1e-3  # mesh step (m) for smooth shape error alone (quadratic, half-sine)
_COARSE_SECTIONS = 96  # facets around the cone, as the CAD
_WARP_HEIGHT = 5e-3  # height (m) over which the base's warp fades (≈ the first 25 layers)
# Faces of a cone's or prism's textured surface at most: fine layers (SLA) and roughness
# together would ask for ≈ 10 M; the roughness is then sampled more coarsely along the
# layers (its Ra at the vertices is kept, its shortest wavelengths are not).
_MAX_GRID_FACES = 1_500_000
_CACHE_SIZE = 12  # printed parts kept per process (two phantoms' worth)
_CHUNK = 16384  # points per block when summing Fourier modes (memory ≈ 32 MB)


@dataclass(frozen=True)
class PrintSettings:
    """The printing effects in SI units (metres, fractions); 0 = off."""

    layer: float = 0.0
    ra: float = 0.0
    roughness_length: float = 4e-4
    shrink_xy: float = 0.0
    shrink_z: float = 0.0
    warp: float = 0.0
    sag: float = 0.0
    roundness: float = 0.0

    @property
    def surface(self) -> bool:
        """Whether the surface texture (layer lines or roughness) is on."""
        return self.layer > 0 or self.ra > 0

    @property
    def shape(self) -> bool:
        """Whether the cone's and prism's shape error is on."""
        return self.shrink_xy != 0 or self.shrink_z != 0 or self.warp > 0 or self.sag > 0

    def step(self, layers: bool = True) -> float:
        """The mesh step (m) the texture needs: half a layer (``layers``: where the mesh
        does not follow the staircase's corners) and a correlation length (the field's
        spectrum is down to e^(-π²/2) < 1 % at that step's Nyquist frequency), or a
        coarse step when only smooth shape error is on."""
        steps = [_COARSE_STEP]
        if self.layer > 0 and layers:
            steps.append(self.layer / 2)
        if self.ra > 0:
            steps.append(self.roughness_length)
        return min(steps)


def part_stream(rng: np.random.Generator, key: int, index: int) -> np.random.Generator:
    """An independent generator for one effect (``key``) of one printed part (``index``):
    a child of ``rng``'s seed sequence, so ``rng``'s own draws are untouched."""
    seq = rng.bit_generator.seed_seq
    if not isinstance(seq, np.random.SeedSequence):
        raise TypeError("the phantom generator must be seeded from a SeedSequence")
    child = np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, key, index))
    return np.random.default_rng(child)


_DISK_CACHE: Path | None = None


def use_disk_cache(directory: str | os.PathLike[str] | None) -> None:
    """Also keep printed parts in ``directory`` (None: memory only), so that the worker
    processes of one run share them: the first process to build a part writes it, the
    others read it (≈ 10 ms instead of 0.3-1.5 s per part, 2.5 s per twin with textured
    spheres). The directory belongs to the run (e.g. its scratch directory)."""
    global _DISK_CACHE
    _DISK_CACHE = None if directory is None else Path(directory)


_MEMOS: list[dict] = []


def forget_parts() -> None:
    """Empty this process's memo of printed parts (a process done with its twins; parts
    in the disk cache are read back in ≈ 10 ms each)."""
    for memo in _MEMOS:
        memo.clear()


# What a cached part holds; raised when that changes (files of an older format are not read).
_PART_FORMAT = 2


def _cached(build):
    """Memoize a printed-part builder per process: a run builds its twin many times (one
    per dataset, per scan), and a textured part takes ≈ 0.3-1.5 s. The key is the
    part's inputs and its generator's seed sequence (what its streams derive from).
    Callers must not modify the returned meshes (the twin copies before transforming).
    With :func:`use_disk_cache` the parts are also shared through files.
    :func:`forget_parts` empties the memo (≈ 100 MB for four textured spheres)."""
    cache: dict[tuple, object] = {}
    _MEMOS.append(cache)

    def wrapper(*args):
        *inputs, rng = args
        seq = rng.bit_generator.seed_seq
        key = (
            tuple(np.asarray(a, dtype=float).tobytes() if np.ndim(a) else a for a in inputs),
            str(seq.entropy),
            tuple(seq.spawn_key),
        )
        if key not in cache:
            if len(cache) >= _CACHE_SIZE:
                cache.pop(next(iter(cache)))
            cache[key] = _from_disk(build, key, args)
        return cache[key]

    wrapper.__doc__ = build.__doc__
    wrapper.__name__ = build.__name__
    wrapper.__wrapped__ = build  # the uncached builder
    return wrapper


def _from_disk(build, key: tuple, args: tuple):
    """``build(*args)``, through the disk cache when one is set: read the part if a file
    holds it, else build it and write the file atomically (a process reading at the same
    time sees the whole file or none)."""
    if _DISK_CACHE is None:
        return build(*args)
    digest = hashlib.sha256(pickle.dumps((build.__name__, _PART_FORMAT, key))).hexdigest()[:32]
    path = _DISK_CACHE / f"{build.__name__}-{digest}.pkl"
    if path.exists():
        with path.open("rb") as f:
            return pickle.load(f)
    part = build(*args)
    write_whole(path, lambda f: pickle.dump(part, f, protocol=pickle.HIGHEST_PROTOCOL))
    return part


# ------------------------------------------------------------------------ texture


def layer_offset(z: Array, n_z: Array, layer: float) -> Array:
    """Displacement (m) along the CAD's outward normal of the slicer's staircase.

    Parameters
    ----------
    z : (n,) float, metres, height of the CAD point above the build plate
    n_z : (n,) float, z component of the CAD's outward unit normal there
    layer : float, layer height h (m)
    """
    z = np.asarray(z, dtype=float)
    n_z = np.clip(np.asarray(n_z, dtype=float), -1.0, 1.0)
    riser = 1.0 - n_z**2  # the riser's share of a layer period, in CAD z
    u = z / layer - np.floor(z / layer)  # position in the layer, 0 at its bottom
    du = u - 0.5  # from the layer's mid-height, where the riser crosses the CAD
    on_riser = np.abs(du) < riser / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = np.where(on_riser, 2.0 * du / riser, 0.0)
        v = np.mod(du - riser / 2, 1.0)  # from the tread's outer corner
        fall = 1.0 - 2.0 * v / (1.0 - riser)
    wave = np.where(on_riser, rise, np.where(riser < 1.0, fall, 0.0))
    return n_z * (layer / 2) * wave


def roughness_height(points: Array, ra: float, length: float, rng: np.random.Generator) -> Array:
    """A Gaussian height field (m) at ``points`` (n, 3), metres: mean absolute height
    ``ra``, covariance ``exp(-d² / 2ℓ²)`` with ℓ = ``length``."""
    k = rng.normal(0.0, 1.0 / length, (_ROUGHNESS_MODES, 3))
    phase = rng.uniform(0.0, 2 * np.pi, _ROUGHNESS_MODES)
    sigma = ra * np.sqrt(np.pi / 2)
    # The cosines are summed in float32 (numpy's SIMD cosine: ≈ 9× faster than float64,
    # ≈ 2 s of a paper run's phantom prints). The phases are taken about the points'
    # centre (k·p + φ = k·(p − c) + (φ + k·c), the latter in float64), so the float32
    # arguments stay within ≈ 100 rad and the field is the same to ≈ 1e-5 of its σ.
    points = np.asarray(points, dtype=float)
    centre = points.mean(axis=0) if len(points) else np.zeros(3)
    k32 = k.T.astype(np.float32)
    phase32 = np.mod(phase + k @ centre, 2 * np.pi).astype(np.float32)
    out = np.empty(len(points))
    for i in range(0, len(points), _CHUNK):
        local = (points[i : i + _CHUNK] - centre).astype(np.float32)
        out[i : i + _CHUNK] = np.cos(local @ k32 + phase32).sum(axis=1, dtype=np.float64)
    return sigma * np.sqrt(2.0 / _ROUGHNESS_MODES) * out


def texture_rms(n_z: Array, s: PrintSettings) -> Array:
    """RMS height (m) of the texture along the CAD normal, per point with the normal's z
    component ``n_z``: the layer staircase is a triangle wave of amplitude (h/2)|n_z|
    (rms: amplitude/√3, whatever its asymmetry), the roughness a Gaussian field of
    σ = Ra √(π/2); the two are independent and add in variance."""
    layer = s.layer / 2 * np.abs(np.asarray(n_z, dtype=float)) / np.sqrt(3.0)
    return np.sqrt(layer**2 + (s.ra * np.sqrt(np.pi / 2)) ** 2)


def layer_share(n_z: Array, s: PrintSettings) -> Array:
    """Share of the texture's variance (of the energy it scatters) that is the layer
    staircase's, per point with the normal's z component ``n_z`` (the rest is the
    roughness's): the simulator sends it back as the treads' echo, mirrors facing the
    build direction (sim_us.propagation)."""
    layer2 = (s.layer / 2 * np.abs(np.asarray(n_z, dtype=float)) / np.sqrt(3.0)) ** 2
    total = layer2 + (s.ra * np.sqrt(np.pi / 2)) ** 2
    return np.divide(layer2, total, out=np.zeros_like(total), where=total > 0)


def _acoustic(mesh: trimesh.Trimesh, smooth: Array, n_z: Array, s: PrintSettings) -> None:
    """Keep a textured mesh's un-textured vertices ``smooth`` and its texture's rms height
    in its metadata (nothing when the texture is off: the part renders as before)."""
    if s.surface:
        mesh.metadata["acoustic_vertices"] = smooth
        mesh.metadata["texture_rms_m"] = texture_rms(n_z, s)
        mesh.metadata["texture_layer_share"] = layer_share(n_z, s)
        mesh.metadata["layer_m"] = s.layer


def _kink_rows(z0: float, z1: float, n_z: float, s: PrintSettings) -> Array:
    """Heights of the mesh rows on a plane face with normal z component ``n_z``: the
    staircase's corners (so a piecewise-linear mesh is the exact staircase) and rows at
    most one mesh step apart."""
    step = s.step(layers=False)
    rows = [np.array([z0, z1])]
    if s.layer > 0:
        half = 0.5 * (1.0 - n_z**2) * s.layer
        mids = (np.arange(np.floor(z0 / s.layer), np.ceil(z1 / s.layer) + 1) + 0.5) * s.layer
        rows += [mids - half, mids + half]
    z = np.unique(np.clip(np.concatenate(rows), z0, z1))
    gaps = np.diff(z)
    fill = [
        np.linspace(a, b, int(np.ceil(g / step)) + 1)[1:-1]
        for a, b, g in zip(z[:-1], z[1:], gaps, strict=True)
        if g > step
    ]
    z = np.unique(np.concatenate([z, *fill]))
    return z[np.concatenate([[True], np.diff(z) > 1e-9])]


def _texture(points: Array, normals: Array, s: PrintSettings, rng: np.random.Generator) -> Array:
    """Normal displacement (m) of layer lines plus roughness at CAD points."""
    d = np.zeros(len(points))
    if s.layer > 0:
        d += layer_offset(points[:, 2], normals[:, 2], s.layer)
    if s.ra > 0:
        d += roughness_height(points, s.ra, s.roughness_length, rng)
    return d


# ------------------------------------------------------------------------ spheres


def sphere_subdivisions(radius: float, s: PrintSettings) -> int:
    """Icosphere subdivisions whose mean edge is at most the texture's mesh step
    (capped at 7: SLA layers below ≈ 0.1 mm are smoothed to the ≈ 47 µm edges)."""
    for n in range(_MIN_SPHERE_SUBDIVISIONS, _MAX_SPHERE_SUBDIVISIONS + 1):
        if 1.21 * radius / 2**n <= s.step():  # icosphere mean edge ≈ 1.21 r / 2^n
            return n
    return _MAX_SPHERE_SUBDIVISIONS


def _real_harmonics(normals: Array, degrees: tuple[int, ...]) -> Array:
    """Orthonormal real spherical harmonics (n, k) at unit vectors ``normals``."""
    polar = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    azimuth = np.arctan2(normals[:, 1], normals[:, 0])
    cols = []
    for deg in degrees:
        for m in range(-deg, deg + 1):
            y = sph_harm_y(deg, abs(m), polar, azimuth)
            cols.append(y.real if m == 0 else np.sqrt(2) * (y.real if m > 0 else y.imag))
    return np.column_stack(cols)


@_cached
def printed_sphere(
    centre: Array, radius: float, s: PrintSettings, index: int, rng: np.random.Generator
) -> tuple[trimesh.Trimesh, Array, float]:
    """A printed sphere (mesh in the phantom frame), the centre and radius of the
    least-squares sphere of its surface (its true landmark and radius)."""
    mesh = trimesh.creation.icosphere(subdivisions=sphere_subdivisions(radius, s), radius=radius)
    normals = mesh.vertices / radius
    points = centre + mesh.vertices
    d = np.zeros(len(points))
    if s.roundness > 0:
        sh = _real_harmonics(normals, (2, 3))
        # E[rms²] = Σ E[c²] / 4π over the 12 orthonormal harmonics = roundness².
        scale = s.roundness * np.sqrt(4 * np.pi / sh.shape[1])
        coeffs = part_stream(rng, ROUNDNESS_SPAWN_KEY, index).normal(0.0, scale, sh.shape[1])
        d += sh @ coeffs
    smooth = points + d[:, None] * normals
    d += _texture(points, normals, s, part_stream(rng, ROUGHNESS_SPAWN_KEY, index))
    mesh = trimesh.Trimesh(points + d[:, None] * normals, mesh.faces, process=False)
    _acoustic(mesh, smooth, normals[:, 2], s)
    c, r = fit_sphere(mesh, centre, radius)
    return mesh, c, r


def fit_sphere(mesh: trimesh.Trimesh, centre: Array, radius: float) -> tuple[Array, float]:
    """Least-squares sphere of a printed sphere's surface: geometric distances of its
    vertices (an icosphere's, spread evenly over the directions), Gauss-Newton from
    ``centre``, ``radius``. Returns the centre (3,) and radius, metres."""
    p = np.asarray(mesh.vertices)
    w = np.ones(len(p))
    c, r = np.asarray(centre, dtype=float).copy(), float(radius)
    for _ in range(10):
        v = p - c
        dist = np.linalg.norm(v, axis=1)
        J = np.column_stack([-v / dist[:, None], -np.ones(len(p))])
        res = dist - r
        step = np.linalg.solve(J.T @ (w[:, None] * J), -J.T @ (w * res))
        c, r = c + step[:3], r + step[3]
        if np.abs(step).max() < 1e-12:
            break
    return c, r


# -------------------------------------------------------------------- cone, prism


def _body_deformation(s: PrintSettings, half_extent: float, rng: np.random.Generator):
    """Shrinkage and warp as a map of points (n, 3) → (n, 3), metres."""
    warp = s.warp * rng.uniform(0.5, 1.5) if s.warp > 0 else 0.0
    aniso = rng.uniform(-0.3, 0.3) if s.warp > 0 else 0.0
    # Lift w of the base's edge at the largest half-extent a: κ a² / 2 = w; the other
    # axis curls with a curvature up to ±30 % different.
    kappa = 2.0 * warp / half_extent**2
    kx, ky = kappa * (1 + aniso), kappa * (1 - aniso)

    def deform(P: Array) -> Array:
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        # The first layers curl up as the layers above cool and contract; the layers
        # printed later are laid flat at the nozzle's height: the lift fades upward.
        lift = 0.5 * (kx * x**2 + ky * y**2) * np.exp(-np.maximum(z, 0.0) / _WARP_HEIGHT)
        out = np.column_stack([x, y, z + lift])
        out[:, :2] *= 1.0 - s.shrink_xy
        out[:, 2] *= 1.0 - s.shrink_z
        return out

    return deform


def _oriented(faces: NDArray[np.int64], cad: Array, outward) -> NDArray[np.int64]:
    """``faces`` wound so that, on the CAD vertices ``cad``, their normals agree with
    ``outward(centroids) -> (n, 3)`` (one decision for the whole consistently wound patch)."""
    tri = cad[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return faces[:, ::-1] if np.einsum("ij,ij->", n, outward(tri.mean(axis=1))) < 0 else faces


def _grid(idx: NDArray[np.int64]) -> NDArray[np.int64]:
    """Two triangles per cell of a grid of vertex indices (rows, cols)."""
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def _fan(centre: int, ring: NDArray[np.int64]) -> NDArray[np.int64]:
    return np.column_stack([np.full(len(ring), centre), ring, np.roll(ring, -1)])


def _constant(v) -> object:
    return lambda c: np.broadcast_to(np.asarray(v, dtype=float), c.shape)


def _printed(
    cad: Array,
    normals: Array,
    faces: NDArray[np.int64],
    s: PrintSettings,
    rng: np.random.Generator,
    index: int,
    sag: Array | None,
    deform,
) -> trimesh.Trimesh:
    """Displace the CAD vertices along their normals (layer lines, roughness, sag; zero
    normals stay put) and apply the body deformation."""
    d = _texture(cad, normals, s, part_stream(rng, ROUGHNESS_SPAWN_KEY, index))
    shape = np.zeros(len(cad)) if sag is None else sag
    mesh = trimesh.Trimesh(deform(cad + (d + shape)[:, None] * normals), faces, process=False)
    _acoustic(mesh, deform(cad + shape[:, None] * normals), normals[:, 2], s)
    return mesh


@_cached
def printed_cone(
    diameter: float, height: float, s: PrintSettings, index: int, rng: np.random.Generator
) -> tuple[trimesh.Trimesh, dict[str, Array]]:
    """A printed cone (base on the plate, apex up) and its landmarks (apex, base centre)
    moved by the shape error (shrinkage, warp); the texture is not a landmark's."""
    R, H = diameter / 2, height
    slant = np.hypot(R, H)
    rows = _kink_rows(0.0, H, R / slant, s)
    sections = _COARSE_SECTIONS
    if s.ra > 0:  # the roughness resolved around the base's circumference
        sections = max(sections, int(np.ceil(2 * np.pi * R / s.step(layers=False))))
        sections = max(_COARSE_SECTIONS, min(sections, _MAX_GRID_FACES // (2 * len(rows))))
    theta = np.arange(sections) * 2 * np.pi / sections
    rho = R * (1.0 - rows / H)
    lateral = np.column_stack(
        [
            np.outer(rho, np.cos(theta)).ravel(),
            np.outer(rho, np.sin(theta)).ravel(),
            np.repeat(rows, sections),
        ]
    )
    side = np.column_stack(
        [
            np.tile(H * np.cos(theta), len(rows)),
            np.tile(H * np.sin(theta), len(rows)),
            np.full(len(lateral), R),
        ]
    )
    # The top row (a ring of copies of the apex) opens into the top tread, closed by a
    # fan to one vertex on the axis; the bottom face is a fan to the base centre.
    cad = np.vstack([lateral, [[0.0, 0.0, 0.0]], [[0.0, 0.0, H]]])
    normals = np.vstack([side / slant, [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]]])
    bottom, top = len(lateral), len(lateral) + 1
    idx = np.arange(len(lateral)).reshape(len(rows), sections)
    wrap = np.column_stack([idx, idx[:, :1]])

    def radial(c: Array) -> Array:
        return np.column_stack([c[:, 0], c[:, 1], np.full(len(c), R / H)])

    base = _fan(bottom, idx[0])
    base_oriented = _oriented(base, cad, _constant([0, 0, -1]))
    # The apex fan is degenerate on the CAD: wound against the base's (same ring order).
    apex = _fan(top, idx[-1])
    apex = apex if not np.array_equal(base, base_oriented) else apex[:, ::-1]
    faces = np.vstack([_oriented(_grid(wrap), cad, radial), base_oriented, apex])
    deform = _body_deformation(s, R, part_stream(rng, SHAPE_SPAWN_KEY, index))
    mesh = _printed(cad, normals, faces, s, rng, index, None, deform)
    marks = deform(np.array([[0.0, 0.0, H], [0.0, 0.0, 0.0]]))
    return mesh, {"apex": marks[0], "base_centre": marks[1]}


@_cached
def printed_prism(
    width: float,
    length: float,
    height: float,
    s: PrintSettings,
    index: int,
    rng: np.random.Generator,
) -> tuple[trimesh.Trimesh, dict[str, Array]]:
    """A printed triangular prism (ridge along x at the top, base on the plate) and its
    ridge landmarks moved by the shape error (shrinkage, warp); the texture and the
    faces' sag are not a landmark's (the sag vanishes at the ridge)."""
    W, L, H = width / 2, length, height
    slant = np.hypot(W, H)
    rows = _kink_rows(0.0, H, W / slant, s)
    cols = int(np.ceil(L / s.step(layers=False)))
    cols = max(2, min(cols, _MAX_GRID_FACES // (4 * len(rows))))
    x = np.linspace(-L / 2, L / 2, cols + 1)
    X, Z = np.meshgrid(x, rows)  # (rows, cols)
    Y = W * (1.0 - Z / H)
    n_face = X.size
    cad = np.vstack(
        [
            np.column_stack([X.ravel(), -Y.ravel(), Z.ravel()]),  # face A, y < 0
            np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]),  # face B, y > 0
        ]
    )
    normal_a, normal_b = np.array([0.0, -H, W]) / slant, np.array([0.0, H, W]) / slant
    normals = np.vstack([np.tile(normal_a, (n_face, 1)), np.tile(normal_b, (n_face, 1))])
    A = np.arange(n_face).reshape(X.shape)
    B = A + n_face
    base = _grid(np.vstack([A[0], B[0]]))
    bottom = _oriented(base, cad, _constant([0, 0, -1]))
    flipped = not np.array_equal(base, bottom)
    top = _grid(np.vstack([A[-1], B[-1]]))
    faces = np.vstack(
        [
            _oriented(_grid(A), cad, _constant(normal_a)),
            _oriented(_grid(B), cad, _constant(normal_b)),
            _oriented(_grid(np.column_stack([A[:, 0], B[:, 0]])), cad, _constant([-1, 0, 0])),
            _oriented(_grid(np.column_stack([A[:, -1], B[:, -1]])), cad, _constant([1, 0, 0])),
            bottom,
            # The ridge opens into the top tread: a strip wound against the bottom's
            # (same vertex order; it is degenerate on the CAD).
            top if flipped else top[:, ::-1],
        ]
    )
    sag = None
    if s.sag > 0:
        # A half-sine pillow on each sloped face, zero at its edges, sign and size drawn.
        amp = part_stream(rng, SAG_SPAWN_KEY, index).normal(0.0, s.sag, 2)
        shape = np.sin(np.pi * (cad[:, 0] + L / 2) / L) * np.sin(np.pi * cad[:, 2] / H)
        sag = shape * np.repeat(amp, n_face)
    deform = _body_deformation(s, max(L, width) / 2, part_stream(rng, SHAPE_SPAWN_KEY, index))
    mesh = _printed(cad, normals, faces, s, rng, index, sag, deform)
    marks = deform(np.array([[-L / 2, 0.0, H], [L / 2, 0.0, H]]))
    return mesh, {"ridge_start": marks[0], "ridge_end": marks[1]}
