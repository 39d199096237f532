"""Phantoms of the paper as trimesh meshes in metres, each with named landmarks.

Every phantom is a set of *convex* parts (MuJoCo collides meshes by their convex hull, so
a non-convex phantom must be split) in its CAD frame ``phantom``: origin at the centre
of the phantom's bottom face, z up. The union of the parts is what the B-mode simulator
ray-casts.

Four-sphere calibration phantom (paper, "System Overview"): four spheres of radius 5 mm
at the corners of a 50 mm square, on thin posts above a base plate; four cone vertices
used as touch targets lie in the plane of the sphere centres, on the square's axes
outside it (layout below). Cone: 60 mm base diameter, 44.64 mm high. Triangular prism:
60 mm wide, 120 mm ridge, 44.64 mm high.

Layout of the four-sphere phantom (top view, phantom frame, mm; ``h`` = centre height)::

              V4 (0, +o)
        S4 (-s/2,+s/2)   S3 (+s/2,+s/2)
    V1 (-o, 0)        +        V3 (+o, 0)
        S1 (-s/2,-s/2)   S2 (+s/2,-s/2)
              V2 (0, -o)

with ``s`` the sphere spacing (50) and ``o`` the vertex offset (60): vertices sit 60 mm
from the centre, 39 mm from the nearest sphere centres, so a tilted stylus reaches them
without touching a sphere and the probe sweeping a sphere keeps clear of the targets.

A manufacturing tolerance perturbs the *true* radii and positions, and the printing
effects of twin/printing.py (layer lines, roughness, shrinkage, warp, sag, out-of-roundness)
the true surfaces; the CAD stays nominal.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import trimesh
from numpy.typing import NDArray

from calib import se3

from .printing import PrintSettings, printed_cone, printed_prism, printed_sphere

__all__ = [
    "FCAL2_NWIRES",
    "Phantom",
    "PhantomConfig",
    "PhantomPart",
    "PhantomWire",
    "build_phantom",
    "build_tank",
    "nwire_patterns",
    "phantom_pair",
    "single_wire",
]

Array = NDArray[np.float64]

_SPHERE_SUBDIVISIONS = 4  # icosphere of 5120 faces: facets deviate ≤ 4 µm at r = 5 mm
_ROUND_SECTIONS = 96  # facets around cylinders and cones
_HULL_VERTICES = 20_000  # vertices of a printed part's collision hull at most


@dataclass(frozen=True)
class PhantomConfig:
    """The phantom in the tank: which one, where (truth), its CAD and its tolerance."""

    kind: Literal["spheres", "cone", "prism", "nwire", "wire"] = field(
        default="spheres",
        metadata={
            "doc": "Phantom in the tank: four-sphere calibration phantom, cone (`uscal "
            "run` calibrates from its tip), prism, the N-wire phantom (PLUS's fCal 2.0 "
            "geometry: three N patterns of wires between two printed end plates), or a "
            "single wire (one straight wire between the same plates, through the N "
            "patterns' centre)."
        },
    )
    position_mm: tuple[float, float, float] = field(
        default=(300.0, 0.0, 0.0),
        metadata={"doc": "True position of the phantom frame (bottom-face centre) in base."},
    )
    rotation_deg: tuple[float, float, float] = field(
        default=(0.0, 0.0, 0.0),
        metadata={"doc": "True orientation, extrinsic x-y-z Euler angles about base axes."},
    )
    sphere_radius_mm: float = field(
        default=5.0, metadata={"doc": "CAD sphere radius.", "gt": 0.5, "le": 50}
    )
    stated_radius_error_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Simulation of a user's mistake: the pipeline is told a sphere radius this "
            "far from the CAD radius the phantom is printed to (0 = told right).",
            "ge": -5,
            "le": 5,
        },
    )
    sphere_spacing_mm: float = field(
        default=50.0, metadata={"doc": "Side of the square of sphere centres.", "gt": 5, "le": 200}
    )
    center_height_mm: float = field(
        default=20.0,
        metadata={
            "doc": "Height of sphere centres and touch vertices above the bottom face.",
            "gt": 5,
            "le": 150,
        },
    )
    vertex_offset_mm: float = field(
        default=60.0,
        metadata={
            "doc": "Distance of the four touch vertices from the phantom centre.",
            "gt": 5,
            "le": 300,
        },
    )
    plate_thickness_mm: float = field(
        default=5.0, metadata={"doc": "Base plate thickness.", "gt": 0.5, "le": 50}
    )
    wire_diameter_mm: float = field(
        default=0.3,
        metadata={
            "doc": "N-wire and single-wire phantoms: the wires' diameter (nylon fishing "
            "line 0.2-0.5 mm).",
            "gt": 0.02,
            "le": 2,
        },
    )
    wire_material: Literal["nylon", "steel"] = field(
        default="nylon",
        metadata={
            "doc": "N-wire and single-wire phantoms: the wires' material (steel rings: a "
            "comet tail under each wire)."
        },
    )
    cone_base_diameter_mm: float = field(
        default=60.0, metadata={"doc": "Cone phantom base diameter.", "gt": 1, "le": 300}
    )
    cone_height_mm: float = field(
        default=44.64, metadata={"doc": "Cone phantom height.", "gt": 1, "le": 300}
    )
    prism_width_mm: float = field(
        default=60.0, metadata={"doc": "Triangular prism base width.", "gt": 1, "le": 300}
    )
    prism_length_mm: float = field(
        default=120.0, metadata={"doc": "Triangular prism ridge length.", "gt": 1, "le": 300}
    )
    prism_height_mm: float = field(
        default=44.64, metadata={"doc": "Triangular prism height.", "gt": 1, "le": 300}
    )
    tolerance_radius_mm: float = field(
        default=0.05,
        metadata={
            "doc": "Printing tolerance (1 σ) of true radii and dimensions (truth only). "
            "Plausible FDM 0.05–0.15 mm, SLA 0.02–0.05 mm (printing-service tolerance guides: "
            "FDM ±0.3 mm, SLA ±0.1 mm under 100 mm).",
            "ge": 0,
            "le": 5,
        },
    )
    tolerance_position_mm: float = field(
        default=0.1,
        metadata={
            "doc": "Printing tolerance (1 σ) of true sphere and vertex positions, per "
            "axis (truth only). Plausible FDM 0.1–0.3 mm, SLA 0.03–0.1 mm (printing-service "
            "tolerance guides: FDM ±0.3 mm, SLA ±0.1 mm under 100 mm).",
            "ge": 0,
            "le": 5,
        },
    )
    print_layer_mm: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Layer height h of the printed phantom (truth only; 0 = a smooth surface). "
                "The slicer prints each layer as the CAD's section at its mid-height: a "
                "staircase of ±(h/2)·cos α along the normal (α the surface's angle to the "
                "build axis z), largest on near-horizontal surfaces, none on vertical "
                "walls; on the spheres, cone and prism. Plausible: FDM 0.1-0.3 mm, SLA "
                "0.025-0.1 mm (printer and slicer settings)."
            ),
            "ge": 0,
            "le": 0.5,
        },
    )
    print_roughness_ra_um: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Surface roughness Ra of the printed spheres, cone and prism (truth only; "
                "0 = off): a Gaussian height field along the normal, correlated over "
                "print_roughness_length_mm. Plausible: FDM 10-30 µm, SLA 1-3 µm (printing "
                "service surface-finish guides)."
            ),
            "ge": 0,
            "le": 200,
        },
    )
    print_roughness_length_mm: float = field(
        default=0.4,
        metadata={
            "doc": (
                "Correlation length of the roughness (Gaussian covariance); about the "
                "extrusion width for FDM (0.4 mm nozzle), 0.05-0.1 mm for SLA."
            ),
            "ge": 0.02,
            "le": 5,
        },
    )
    print_shrinkage_pct: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Linear shrinkage of the printed cone and prism in the build plane (x, y), "
                "about the bottom-face centre (truth only; 0 = off). Plausible for PLA FDM "
                "0.2-0.5 % (material datasheets, printing service tolerance guides)."
            ),
            "ge": -2,
            "le": 3,
        },
    )
    print_shrinkage_z_pct: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Linear shrinkage of the printed cone and prism along the build axis z "
                "(truth only; 0 = off). FDM shrinks less across layers than along them: "
                "plausible 0-0.3 % (anisotropy reported for PLA/ABS FDM parts)."
            ),
            "ge": -2,
            "le": 3,
        },
    )
    print_warp_mm: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Warp of the printed cone's and prism's base (truth only; 0 = off): the "
                "first layers curl up as the layers above cool and contract, a lift "
                "growing with the square of the distance from the centre, reaching this "
                "amount at the base's far edges (drawn per part ×U(0.5, 1.5), curvatures "
                "in x and y ±30 %) and fading over the first 5 mm of height. Plausible "
                "FDM 0.1-0.3 mm on a 60-120 mm base (warping reports for PLA on a heated "
                "bed)."
            ),
            "ge": 0,
            "le": 3,
        },
    )
    print_sag_mm: float = field(
        default=0.0,
        metadata={
            "doc": (
                "1 σ sag (−) or bulge (+) of the printed prism's two large sloped faces "
                "(truth only; 0 = off): a half-sine pillow along the face normal, zero at "
                "the face's edges, drawn per face (sparse infill pulling or pushing the "
                "skin). Plausible FDM 0.02-0.1 mm (est.)."
            ),
            "ge": 0,
            "le": 1,
        },
    )
    sphere_roundness_mm: float = field(
        default=0.0,
        metadata={
            "doc": (
                "Out-of-roundness of the printed spheres, rms radial deviation (1 σ; "
                "truth only; 0 = round): degree-2 and -3 spherical harmonics with random "
                "coefficients (ellipsoid, trefoil). The true centre is the least-squares "
                "sphere's of the printed surface. Plausible FDM 0.05-0.2 mm, SLA "
                "0.02-0.05 mm (sphericity of printed spheres, printing tolerance guides)."
            ),
            "ge": 0,
            "le": 1,
        },
    )
    tank_inner_mm: tuple[float, float, float] = field(
        default=(320.0, 240.0, 150.0),
        metadata={"doc": "Water tank inner length (x), width (y), height (z).", "gt": 10},
    )
    tank_wall_mm: float = field(
        default=6.0, metadata={"doc": "Tank wall and floor thickness.", "gt": 0.5, "le": 50}
    )
    tank_position_mm: tuple[float, float, float] = field(
        default=(300.0, 0.0, 0.0),
        metadata={"doc": "Centre of the tank's inner floor in base (tank axes = base axes)."},
    )
    water_level_mm: float = field(
        default=100.0, metadata={"doc": "Water depth above the tank floor.", "gt": 0}
    )

    @property
    def T_base_phantom(self) -> Array:
        """True phantom pose (4, 4)."""
        R = se3.matrix_from_euler(np.radians(self.rotation_deg))
        return se3.make(R, np.array(self.position_mm) * 1e-3)

    @property
    def T_base_tank(self) -> Array:
        """Pose of the tank frame (centre of its inner floor), (4, 4)."""
        return se3.make(np.eye(3), np.array(self.tank_position_mm) * 1e-3)

    @property
    def printing(self) -> PrintSettings:
        """The printing effects in SI units (twin/printing.py)."""
        return PrintSettings(
            layer=self.print_layer_mm * 1e-3,
            ra=self.print_roughness_ra_um * 1e-6,
            roughness_length=self.print_roughness_length_mm * 1e-3,
            shrink_xy=self.print_shrinkage_pct * 1e-2,
            shrink_z=self.print_shrinkage_z_pct * 1e-2,
            warp=self.print_warp_mm * 1e-3,
            sag=self.print_sag_mm * 1e-3,
            roundness=self.sphere_roundness_mm * 1e-3,
        )


@dataclass(frozen=True)
class PhantomPart:
    """One convex solid of a phantom, in the phantom's CAD frame (metres).

    ``collision_mesh``, when set, is what MuJoCo collides (it takes a mesh's convex hull
    anyway): a printed part's fine mesh (10⁵-10⁶ faces) would cost MuJoCo seconds per
    compile, its hull of a few thousand faces is the same solid to within its texture.

    A textured (printed) part also carries, for the ultrasound simulator, its vertices
    before the texture ``acoustic_vertices`` (V, 3) and the texture's rms height per
    vertex ``texture_rms_m`` (V,), metres, with the layer staircase's share of it
    ``texture_layer_share`` (V,) and the layer height ``layer_m`` (see twin/printing.py);
    None when untextured. The CAD frame's z is the build direction."""

    name: str
    mesh: trimesh.Trimesh
    material: str
    collision_mesh: trimesh.Trimesh | None = None
    acoustic_vertices: Array | None = None
    texture_rms_m: Array | None = None
    texture_layer_share: Array | None = None
    layer_m: float = 0.0


@dataclass(frozen=True, eq=False)
class PhantomWire:
    """A wire of a phantom, between two points of its CAD frame (metres)."""

    name: str
    front: Array
    back: Array
    diameter_m: float
    material: str


@dataclass(frozen=True, eq=False)
class Phantom:
    """A phantom: convex parts and named landmarks (``name -> (3,)`` metres, own frame),
    and its wires (an N-wire phantom; thinner than the beam, they are imaged as line
    targets, not ray-cast, and are no collision bodies: the plates holding them are)."""

    name: str
    parts: tuple[PhantomPart, ...]
    landmarks: dict[str, Array]
    sphere_radii: dict[str, float] = field(default_factory=dict)
    wires: tuple[PhantomWire, ...] = ()

    def mesh(self) -> trimesh.Trimesh:
        """All parts concatenated into one mesh (for ray casting and display)."""
        return trimesh.util.concatenate([p.mesh for p in self.parts])

    def landmarks_in(self, T_frame_phantom: Array) -> dict[str, Array]:
        """Landmarks mapped into another frame (e.g. base) with ``T_frame_phantom``."""
        return {k: se3.apply(T_frame_phantom, v) for k, v in self.landmarks.items()}


def _placed(mesh: trimesh.Trimesh, translation: Array) -> trimesh.Trimesh:
    mesh.apply_translation(translation)
    return mesh


def _cylinder(radius: float, z0: float, z1: float, xy: Array) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=_ROUND_SECTIONS)
    return _placed(mesh, np.array([xy[0], xy[1], 0.5 * (z0 + z1)]))


def _cone(radius: float, z0: float, z1: float, xy: Array) -> trimesh.Trimesh:
    mesh = trimesh.creation.cone(radius=radius, height=z1 - z0, sections=_ROUND_SECTIONS)
    return _placed(mesh, np.array([xy[0], xy[1], z0]))


@dataclass(frozen=True)
class _SphereGeometry:
    """Dimensions of a four-sphere phantom (metres), nominal or perturbed."""

    centres: Array  # (4, 3)
    radii: Array  # (4,)
    vertices: Array  # (4, 3)
    plate_half: float
    plate_thickness: float


def _sphere_geometry(cfg: PhantomConfig) -> _SphereGeometry:
    h = cfg.center_height_mm * 1e-3
    s = 0.5 * cfg.sphere_spacing_mm * 1e-3
    o = cfg.vertex_offset_mm * 1e-3
    centres = np.array([[-s, -s, h], [s, -s, h], [s, s, h], [-s, s, h]])
    vertices = np.array([[-o, 0, h], [0, -o, h], [o, 0, h], [0, o, h]])
    half = max(s + cfg.sphere_radius_mm * 1e-3, o) + 0.015
    return _SphereGeometry(
        centres,
        np.full(4, cfg.sphere_radius_mm * 1e-3),
        vertices,
        half,
        cfg.plate_thickness_mm * 1e-3,
    )


def _build_spheres(
    g: _SphereGeometry, printed: list[tuple[trimesh.Trimesh, Array, float]] | None = None
) -> Phantom:
    plate = trimesh.creation.box(extents=[2 * g.plate_half, 2 * g.plate_half, g.plate_thickness])
    parts = [PhantomPart("plate", _placed(plate, np.array([0, 0, g.plate_thickness / 2])), "pla")]
    landmarks: dict[str, Array] = {}
    radii: dict[str, float] = {}
    for i, (c, r) in enumerate(zip(g.centres, g.radii, strict=True), start=1):
        if printed is None:
            sphere = trimesh.creation.icosphere(subdivisions=_SPHERE_SUBDIVISIONS, radius=r)
            parts.append(PhantomPart(f"sphere_{i}", _placed(sphere, c), "pla"))
            centre, radius = c.copy(), float(r)
        else:  # printed: the landmark is the least-squares sphere of the printed surface
            mesh, centre, radius = printed[i - 1]
            parts.append(_printed_part(f"sphere_{i}", mesh))
        # The post ends just inside the sphere so the two solids overlap (printed as one).
        post_top = c[2] - 0.8 * r
        parts.append(
            PhantomPart(f"post_{i}", _cylinder(0.4 * r, g.plate_thickness, post_top, c), "pla")
        )
        landmarks[f"sphere_{i}"] = centre
        radii[f"sphere_{i}"] = float(radius)
    for j, v in enumerate(g.vertices, start=1):
        parts.append(
            PhantomPart(f"vertex_cone_{j}", _cone(0.008, g.plate_thickness, v[2], v), "pla")
        )
        landmarks[f"vertex_{j}"] = v.copy()
    return Phantom("spheres", tuple(parts), landmarks, radii)


def _build_cone(diameter: float, height: float) -> Phantom:
    cone = _cone(diameter / 2, 0.0, height, np.zeros(2))
    landmarks = {"apex": np.array([0.0, 0.0, height]), "base_centre": np.zeros(3)}
    return Phantom("cone", (PhantomPart("cone", cone, "pla"),), landmarks)


def _build_prism(width: float, length: float, height: float) -> Phantom:
    # Ridge along x at the top; the triangular cross-section in the y-z plane.
    section = np.array([[-width / 2, 0.0], [width / 2, 0.0], [0.0, height]])
    corners = np.array(
        [[x, y, z] for x in (-length / 2, length / 2) for (y, z) in section], dtype=float
    )
    prism = trimesh.convex.convex_hull(corners)
    landmarks = {
        "ridge_start": np.array([-length / 2, 0.0, height]),
        "ridge_end": np.array([length / 2, 0.0, height]),
    }
    return Phantom("prism", (PhantomPart("prism", prism, "pla"),), landmarks)


#: PLUS's fCal 2.0 phantom (its device set's PhantomDefinition, mm, its phantom frame):
#: three N patterns, (name, front, back) per wire, outer wires along y.
FCAL2_NWIRES: tuple[tuple[tuple[str, tuple[float, ...], tuple[float, ...]], ...], ...] = (
    (("7:G1_g1", (30, 0, 20), (30, 40, 20)), ("8:L1_h1", (55, 0, 20), (35, 40, 20)),
     ("9:M1_m1", (60, 0, 20), (60, 40, 20))),
    (("4:G3_g3", (30, 0, 10), (30, 40, 10)), ("5:H3_l3", (35, 0, 10), (55, 40, 10)),
     ("6:M3_m3", (60, 0, 10), (60, 40, 10))),
    (("1:H5_h5", (35, 0, 0), (35, 40, 0)), ("2:L5_i5", (55, 0, 0), (40, 40, 0)),
     ("3:M5_m5", (60, 0, 0), (60, 40, 0))),
)  # fmt: skip
#: Where fCal's phantom frame sits in the twin's CAD frame (origin at the bottom face's
#: centre, z up): the patterns centred over the base, the lowest wires 15 mm above it.
_FCAL2_SHIFT_MM = np.array([-45.0, -20.0, 15.0])
_NWIRE_PLATE_MM = 5.0  # end plates' thickness (the wires pass through them)


def nwire_patterns(cfg: PhantomConfig | None = None) -> tuple[tuple[str, Array, Array], ...]:
    """The N-wire phantom's wires as (name, front, back), CAD frame, metres, pattern by
    pattern in fCal's order (three wires each)."""
    del cfg  # one geometry: fCal 2.0's
    return tuple(
        (name, (np.array(f) + _FCAL2_SHIFT_MM) * 1e-3, (np.array(b) + _FCAL2_SHIFT_MM) * 1e-3)
        for pattern in FCAL2_NWIRES
        for name, f, b in pattern
    )


def single_wire(cfg: PhantomConfig | None = None) -> tuple[tuple[str, Array, Array], ...]:
    """The single-wire phantom's wire as (name, front, back), CAD frame, metres: along y
    through the N patterns' centre, between the same end plates."""
    del cfg
    ends = np.array([p for _, f, b in nwire_patterns() for p in (f, b)])
    centre = (ends.min(axis=0) + ends.max(axis=0)) / 2
    half = np.array([0.0, (ends[:, 1].max() - ends[:, 1].min()) / 2, 0.0])
    return (("wire", centre - half, centre + half),)


def _build_nwire(cfg: PhantomConfig, wires: tuple[tuple[str, Array, Array], ...]) -> Phantom:
    """Two end plates the wires pass between, on a base plate; landmarks ``nwire`` (or
    ``wire``: the wires' centre, where the probe is taught) and each wire's ends. The
    plates span the N-wire phantom's width whatever the wires (one print for both)."""
    ends = np.array([p for _, f, b in wires for p in (f, b)])
    lo, hi = ends.min(axis=0), ends.max(axis=0)
    frame = np.array([p for _, f, b in nwire_patterns() for p in (f, b)])
    lo_x, hi_x = frame[:, 0].min(), frame[:, 0].max()
    t = _NWIRE_PLATE_MM * 1e-3
    base_t = cfg.plate_thickness_mm * 1e-3
    margin = 0.01
    x0, x1 = lo_x - margin, hi_x + margin
    z1 = hi[2] + 0.003  # the plates stop just above the top wires: the probe sweeps over them
    parts = [
        PhantomPart(
            "plate",
            _placed(
                trimesh.creation.box(extents=[x1 - x0, hi[1] - lo[1] + 2 * t, base_t]),
                np.array([(x0 + x1) / 2, (lo[1] + hi[1]) / 2, base_t / 2]),
            ),
            "pla",
        )
    ]
    for name, y0 in (("end_plate_front", lo[1] - t), ("end_plate_back", hi[1])):
        parts.append(
            PhantomPart(
                name,
                _placed(
                    trimesh.creation.box(extents=[x1 - x0, t, z1 - base_t]),
                    np.array([(x0 + x1) / 2, y0 + t / 2, (base_t + z1) / 2]),
                ),
                "pla",
            )
        )
    landmarks = {cfg.kind: (lo + hi) / 2}
    for name, f, b in wires:
        landmarks[f"{name}_front"], landmarks[f"{name}_back"] = f.copy(), b.copy()
    d = cfg.wire_diameter_mm * 1e-3
    return Phantom(
        cfg.kind,
        tuple(parts),
        landmarks,
        wires=tuple(PhantomWire(n, f, b, d, cfg.wire_material) for n, f, b in wires),
    )


def _printed_part(name: str, mesh: trimesh.Trimesh) -> PhantomPart:
    """A printed part and its collision hull (of at most ≈ 20 000 of its vertices)."""
    hull = mesh.metadata.get("collision_hull")  # printed meshes are cached: so is this
    if hull is None:
        stride = max(1, len(mesh.vertices) // _HULL_VERTICES)
        hull = mesh.metadata["collision_hull"] = trimesh.convex.convex_hull(mesh.vertices[::stride])
    return PhantomPart(
        name,
        mesh,
        "pla",
        hull,
        mesh.metadata.get("acoustic_vertices"),
        mesh.metadata.get("texture_rms_m"),
        mesh.metadata.get("texture_layer_share"),
        float(mesh.metadata.get("layer_m", 0.0)),
    )


def build_phantom(cfg: PhantomConfig, rng: np.random.Generator | None = None) -> Phantom:
    """The phantom of ``cfg``: its CAD if ``rng`` is None, else a printed (true) copy.

    The true copy draws each sphere radius and cone/prism dimension with
    ``tolerance_radius_mm`` and each sphere centre and touch vertex with
    ``tolerance_position_mm`` (1 σ, per axis). When a printing effect is on
    (``print_*``, ``sphere_roundness_mm``; see twin/printing.py) the imaged surfaces are
    then printed: finely meshed, with layer lines and roughness, the spheres out of round,
    the cone and prism shrunk, warped and sagging, each part from its own random stream
    (children of ``rng``'s seed sequence; ``rng`` itself draws nothing more). The truth's
    landmarks are where a perfect measurement puts them: a printed sphere's centre and
    radius are the least-squares sphere's of its printed surface; the apex and ridge ends
    move with the shrinkage and warp.
    """
    tol_r = 0.0 if rng is None else cfg.tolerance_radius_mm * 1e-3
    tol_p = 0.0 if rng is None else cfg.tolerance_position_mm * 1e-3
    gen = rng if rng is not None else np.random.default_rng(0)
    prints = cfg.printing

    def jitter(values: Array, sigma: float) -> Array:
        return values + (gen.normal(0.0, sigma, np.shape(values)) if sigma > 0 else 0.0)

    if cfg.kind == "spheres":
        g = _sphere_geometry(cfg)
        g = replace(
            g,
            radii=jitter(g.radii, tol_r),
            centres=jitter(g.centres, tol_p),
            vertices=jitter(g.vertices, tol_p),
        )
        if rng is None or not (prints.surface or prints.roundness > 0):
            return _build_spheres(g)
        printed = [
            printed_sphere(c, float(r), prints, i, rng)
            for i, (c, r) in enumerate(zip(g.centres, g.radii, strict=True))
        ]
        return _build_spheres(g, printed)
    if cfg.kind in ("nwire", "wire"):
        # The wires' ends where the plates' holes put them (the print's position
        # tolerance); the plates themselves are not imaged.
        cad = nwire_patterns(cfg) if cfg.kind == "nwire" else single_wire(cfg)
        wires = tuple((n, jitter(f, tol_p), jitter(b, tol_p)) for n, f, b in cad)
        return _build_nwire(cfg, wires)
    on = rng is not None and (prints.surface or prints.shape)
    if cfg.kind == "cone":
        d, h = jitter(np.array([cfg.cone_base_diameter_mm, cfg.cone_height_mm]) * 1e-3, tol_r)
        if not on:
            return _build_cone(d, h)
        assert rng is not None
        mesh, landmarks = printed_cone(d, h, prints, 0, rng)
        return Phantom("cone", (_printed_part("cone", mesh),), landmarks)
    w, length, h = jitter(
        np.array([cfg.prism_width_mm, cfg.prism_length_mm, cfg.prism_height_mm]) * 1e-3, tol_r
    )
    if not on:
        return _build_prism(w, length, h)
    assert rng is not None
    mesh, landmarks = printed_prism(w, length, h, prints, 0, rng)
    return Phantom("prism", (_printed_part("prism", mesh),), landmarks)


def phantom_pair(cfg: PhantomConfig, rng: np.random.Generator) -> tuple[Phantom, Phantom]:
    """(CAD, true) phantoms: what the pipeline knows and what the twin images."""
    return build_phantom(cfg), build_phantom(cfg, rng)


def build_tank(cfg: PhantomConfig) -> Phantom:
    """The water tank (floor and four walls, convex boxes) in its own frame: origin at the
    centre of the inner floor, z up. Landmark ``water_surface`` is the surface centre."""
    length, width, height = (v * 1e-3 for v in cfg.tank_inner_mm)
    t = cfg.tank_wall_mm * 1e-3
    boxes = {
        "tank_floor": ([length + 2 * t, width + 2 * t, t], [0, 0, -t / 2]),
        "tank_wall_xneg": ([t, width + 2 * t, height], [-(length + t) / 2, 0, height / 2]),
        "tank_wall_xpos": ([t, width + 2 * t, height], [(length + t) / 2, 0, height / 2]),
        "tank_wall_yneg": ([length, t, height], [0, -(width + t) / 2, height / 2]),
        "tank_wall_ypos": ([length, t, height], [0, (width + t) / 2, height / 2]),
    }
    parts = tuple(
        PhantomPart(name, _placed(trimesh.creation.box(extents=ext), np.array(pos)), "acrylic")
        for name, (ext, pos) in boxes.items()
    )
    landmarks = {"water_surface": np.array([0.0, 0.0, cfg.water_level_mm * 1e-3])}
    return Phantom("tank", parts, landmarks)
