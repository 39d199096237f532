"""Small acoustic scenes for the simulator's physics checks (probe at the origin looking
along +y of the scene frame, so image coordinates equal scene coordinates)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from calib import se3
from sim_us import MediumConfig, ProbeConfig
from sim_us.raycast import AcousticScene, ScenePart
from sim_us.simulator import BmodeSimulator

MM = 1e-3
#: The probe frame is the scene frame.
T_IDENTITY = np.eye(4)[None]

# The mechanism tests (partial volume, speckle statistics, shadows, gain, golden frames)
# use a probe of stated widths: a Gaussian beam of the paper's stated resolution (0.7 mm
# lateral and slice at the focus, 0.35 mm axial, a geometric slice), no side lobes, the
# receiver noise at -55 dB, smooth surface echoes and a line every 0.2 mm, so their
# figures follow from numbers they can state. The beam derived from the transducer (the
# default) is tested against the stored physics reference in tests/test_transducer.py.
STATED_BEAM = {
    "lateral_fwhm_mm": 0.7,
    "axial_fwhm_mm": 0.35,
    "slice_thickness_mm": 0.7,
    "side_lobe_db": None,
    "noise_db": -55.0,
    "surface_speckle": False,
    "scanline_spacing_mm": 0.2,
}
SMALL_PROBE = ProbeConfig(width_mm=12.0, depth_mm=30.0, pixel_spacing_mm=(0.1, 0.1), **STATED_BEAM)


def sphere(centre_mm, radius_mm=5.0, material="pla") -> ScenePart:
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius_mm * MM)
    mesh.apply_translation(np.asarray(centre_mm) * MM)
    return ScenePart("sphere", mesh, material)


def slab(depth_mm, thickness_mm=5.0, tilt_deg=0.0, material="pla", size_mm=200.0) -> ScenePart:
    """A flat plate whose top face crosses the image centre line at ``depth_mm``, tilted
    about the elevation (z) axis by ``tilt_deg``."""
    mesh = trimesh.creation.box(extents=[size_mm * MM, thickness_mm * MM, size_mm * MM])
    mesh.apply_translation([0.0, thickness_mm * MM / 2, 0.0])
    R = se3.matrix_from_euler([0.0, 0.0, np.radians(tilt_deg)])
    mesh.apply_transform(se3.make(R, [0.0, depth_mm * MM, 0.0]))
    return ScenePart("slab", mesh, material)


def wire(x_mm, depth_mm, radius_mm=0.03, material="pla") -> ScenePart:
    """A thin wire along the elevational axis (a resolution target)."""
    mesh = trimesh.creation.cylinder(radius=radius_mm * MM, height=20 * MM, sections=32)
    mesh.apply_translation([x_mm * MM, depth_mm * MM, 0.0])
    return ScenePart("wire", mesh, material)


def simulator(parts, probe=SMALL_PROBE, medium=None, **probe_changes) -> BmodeSimulator:
    probe = replace(probe, **probe_changes)
    return BmodeSimulator(AcousticScene(tuple(parts)), probe, medium or MediumConfig())


def elevation_shift(e_mm: float) -> np.ndarray:
    """Probe pose moved by e along its elevational axis, (1, 4, 4)."""
    return se3.make(np.eye(3), [0.0, 0.0, e_mm * MM])[None]


def trace_along_y(caster, materials, medium, origins, directions, **kwargs):
    """``sim_us.propagation.trace`` for rays of SMALL_PROBE's transducer whose lateral axis
    is the scene's x and elevational axis its z (the probe at the origin looking along +y):
    50 mm deep, 13 MHz, displayed at 1540 m/s, a 200 dB floor."""
    from sim_us.beam import mirror_of
    from sim_us.propagation import trace

    n = len(origins)
    axes = (np.tile([1.0, 0.0, 0.0], (n, 1)), np.tile([0.0, 0.0, 1.0], (n, 1)))
    return trace(
        caster,
        materials,
        medium,
        origins,
        directions,
        0.05,
        SMALL_PROBE.f_mhz,
        1540.0,
        200.0,
        mirror_of(SMALL_PROBE),
        axes,
        **kwargs,
    )
