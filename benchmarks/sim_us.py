"""Frames per second of the B-mode simulator, single process.

The paper probe (38 × 40 mm at 0.1 mm: 401 × 381 px, its elevation sub-planes and
scanlines as its beam sets them, printed first; PSF, noise, log compression) imaging the
four-sphere phantom in water, rendered in whole 21-frame sweeps as the calibration
protocol acquires them; first the same in gel (with speckle) over half as many sweeps.
Prints the split between ray casting, image formation and display, the pixel
throughput (``Mpx_per_s``, one core) and the spread of frames/s over the sweeps. The
last line is ``frames_per_s=<value>`` for the paper probe in water.

Run: python benchmarks/sim_us.py [--sweeps N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

# This script shares its name with the package it measures: keep its own folder off the
# import path so ``import sim_us`` finds the package.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import numpy as np  # noqa: E402

from calib import se3  # noqa: E402
from calib.acquisition.protocol import facing_pose, orientation_offsets, rotated_about_target  # noqa: E402
from calib.dh import NOMINAL_TABLES  # noqa: E402
from sim_us import MediumConfig, ProbeConfig  # noqa: E402
from sim_us.beam import scanline_step  # noqa: E402
from sim_us.simulator import BmodeSimulator, Timings  # noqa: E402
from twin.imager import acoustic_scene  # noqa: E402
from twin.phantoms import PhantomConfig, build_phantom, build_tank  # noqa: E402
from twin.scene import Scene  # noqa: E402
from twin.tools import ToolsConfig  # noqa: E402


def sweeps(n_sweeps: int, depth: float = 0.02) -> list[np.ndarray]:
    """Sweeps of 21 frames at 1 mm about the four spheres, at the plan's orientations."""
    pc = PhantomConfig()
    centres = build_phantom(pc).landmarks_in(pc.T_base_phantom)
    rotations = orientation_offsets(10.0)
    out = []
    for k in range(n_sweeps):
        c = centres[f"sphere_{k % 4 + 1}"]
        T = rotated_about_target(facing_pose(c, depth), rotations[k % 9], depth)
        steps = [se3.make(np.eye(3), [0.0, 0.0, dz]) for dz in np.linspace(-0.01, 0.01, 21)]
        out.append(np.array([T @ s for s in steps]))
    return out


def run(sim: BmodeSimulator, poses: list[np.ndarray], rng: np.random.Generator) -> float:
    sim.render(poses[0][:2], rng)  # warm-up: noise pool, caches
    sim.timings = Timings()
    per_sweep = []
    t0 = time.perf_counter()
    for sweep in poses:
        t1 = time.perf_counter()
        sim.render(sweep, rng)
        per_sweep.append(len(sweep) / (time.perf_counter() - t1))
    wall = time.perf_counter() - t0
    n = sum(len(s) for s in poses)
    t = sim.timings
    H, W = sim.shape
    # Pixel throughput on this one core, comparable with published simulators' figures
    # (PLUS's CPU simulator ≈ 17 Mpx/s; a GPU ray tracer ≈ 34 Mpx/s on a workstation GPU).
    print(
        f"  frames={n} wall_s={wall:.3f} frames_per_s={n / wall:.1f} "
        f"Mpx_per_s={n * H * W / wall / 1e6:.1f}"
    )
    # The sweeps differ (sphere, orientation: what the rays meet), and so does the machine
    # from one second to the next: the spread over the sweeps.
    lo, med, hi = np.percentile(per_sweep, [0, 50, 100])
    print(f"  per sweep: frames_per_s min={lo:.1f} median={med:.1f} max={hi:.1f}")
    print(
        f"  per frame: raycast_ms={1e3 * t.raycast / n:.2f} "
        f"formation_ms={1e3 * t.formation / n:.2f} display_ms={1e3 * t.display / n:.2f} "
        f"other_ms={1e3 * (wall - t.raycast - t.formation - t.display) / n:.2f}"
    )
    return n / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sweeps", type=int, default=12)
    args = parser.parse_args()
    pc = PhantomConfig()
    scene = acoustic_scene(
        Scene(
            NOMINAL_TABLES["ur3"],
            ToolsConfig(),
            build_phantom(pc),
            pc.T_base_phantom,
            build_tank(pc),
            pc.T_base_tank,
        )
    )
    poses = sweeps(args.sweeps)
    probe = ProbeConfig()
    H, W = probe.image_shape
    print(
        f"paper probe: {H}x{W} px, {probe.elevation_planes} sub-planes, "
        f"scanlines every "
        f"{scanline_step(probe, probe.spacing_m[0]) * probe.pixel_spacing_mm[0]:g} mm"
    )
    print("gel (speckle everywhere):")
    gel = BmodeSimulator(scene, probe, MediumConfig(kind="gel"), speckle_key=1)
    run(gel, poses[: max(1, len(poses) // 2)], np.random.default_rng(1))
    print("water, paper probe, sphere phantom:")
    water = BmodeSimulator(scene, probe, MediumConfig(), speckle_key=1)
    fps = run(water, poses, np.random.default_rng(0))
    print(f"frames_per_s={fps:.1f}")


if __name__ == "__main__":
    main()
