"""Compile the project's numba kernels once, before the test workers start.

The kernels are compiled on first use and cached beside their modules (``cache=True``).
On a fresh clone every process that starts before a cache entry exists compiles the
same kernel (≈ 40 s of CPU for all of them): at the start of a parallel test run, the two
workers and the pools their first end-to-end runs spawn did that four or five times over,
side by side on two cores. :func:`warm` runs the smallest real workloads that reach every
kernel, the simulator's (frames rendered in gel and in water) and calib's (both
localizers on a drawn sweep, a mesh's closest points) in two processes side by side, so
the workers and their subprocesses load the kernels from the cache (≈ 28 s on a fresh
clone on 2 cores, ≈ 42 s one after the other; a few seconds with the cache warm)."""

from __future__ import annotations

import numpy as np


def _sweep(medium: str, n: int):
    """``n`` frames over ±10 mm across sphere 1 of the default scene in ``medium``."""
    from bench.acquire_sim import make_imager, make_twin
    from bench.config.scenario import load_scenario
    from calib import se3
    from calib.acquisition.protocol import facing_pose

    from .rendered import render_sweep

    s = load_scenario(None, ["robot.dh_error_scale=0", f"medium.kind={medium}"], check_reach=False)
    twin = make_twin(s)
    T_face = facing_pose(twin.truth.landmarks_base["sphere_1"], 0.02)
    frames = [T_face @ se3.make(np.eye(3), [0, 0, z]) for z in np.linspace(-0.01, 0.01, n)]
    sweep, _ = render_sweep(twin, make_imager(s, twin), frames)
    return sweep, twin.truth.T_ee_us


def _synthetic_sweep():
    """A sweep drawn by hand (a bright cap 5 mm in radius, 21 frames 0.5 mm apart), as
    :func:`calib.localize.localize_sphere`'s example draws it: the localizer's kernels
    compile on it without the simulator's."""
    from calib import se3
    from calib.image import pixel_axes
    from calib.records import Sweep

    z = np.linspace(-5e-3, 5e-3, 21)
    rows, cols = np.mgrid[0:151, 0:151]
    x, y = pixel_axes(rows, cols, 151, (0.2e-3, 0.2e-3))
    centre = np.array([1e-3, 15e-3, 0.3e-3])

    def frame(zk):
        d = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (zk - centre[2]) ** 2)
        return np.where((abs(d - 5e-3) < 0.3e-3) & (y < centre[1]), 200, 0)

    images = np.array([frame(zk) for zk in z], np.uint8)
    poses = np.array([se3.make(np.eye(3), [0.0, 0.0, zk]) for zk in z])
    return Sweep("sphere_1", 0, images, (0.2e-3, 0.2e-3), np.zeros((21, 6)), poses)


def warm_simulator() -> None:
    """The simulator's kernels: a few frames in gel (the medium's speckle) and a sweep in
    water (the surfaces' echoes)."""
    _sweep("gel", 3)
    _sweep("water", 5)


def warm_calib() -> None:
    """The localizer's kernels (both methods) and the reconstruction's closest points."""
    import trimesh

    from calib.evaluation.reconstruct import surface_distances
    from calib.localize import LocalizerConfig, localize_sphere
    from calib.localize.refine import _parabola_vertex

    sweep = _synthetic_sweep()
    for method in ("refined", "paper"):
        localize_sphere([sweep], np.eye(4), 5e-3, LocalizerConfig(method=method))
    # The drawn cap is saturated: its elevation comes without the parabola's fit.
    u = np.arange(-2.0, 3.0)
    _parabola_vertex(u, 10.0 - u**2, np.exp(-0.5 * u**2))
    surface_distances(trimesh.creation.box((0.01, 0.01, 0.01)), np.zeros((3, 3)))


def warm() -> None:
    """Both halves side by side: the calib half in a process of its own while this one
    compiles the simulator's (≈ 25 s and ≈ 10 s of CPU on a fresh clone: one after the
    other they left the second core idle for ≈ 40 s at the start of every CI run)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    other = subprocess.Popen(
        [sys.executable, "-c", "from tests.numba_warmup import warm_calib; warm_calib()"],
        cwd=root,
    )
    try:
        warm_simulator()
    finally:
        code = other.wait()
    if code != 0:
        raise RuntimeError(f"compiling the calib kernels failed (exit {code})")
