"""Compile the project's numba kernels once, before the test workers start.

The kernels are compiled on first use and cached beside their modules (``cache=True``).
On a fresh clone every process that starts before a cache entry exists compiles the
same kernel (≈ 25 s of CPU for all of them): at the start of a parallel test run, the two
workers and the pools their first end-to-end runs spawn did that four or five times over,
side by side on two cores. :func:`warm` runs the smallest real workload that reaches
every kernel (a sweep rendered in water, a few frames in gel, both localizers on it, a
mesh's closest points), so the workers and their subprocesses load the kernels from the
cache; with the cache already warm it costs a few seconds."""

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


def warm() -> None:
    import trimesh

    from calib.evaluation.reconstruct import surface_distances
    from calib.localize import LocalizerConfig, localize_sphere

    _sweep("gel", 3)  # the medium's speckle
    sweep, T_ee_us = _sweep("water", 21)
    for method in ("refined", "paper"):
        localize_sphere([sweep], T_ee_us, 5e-3, LocalizerConfig(method=method))
    surface_distances(trimesh.creation.box((0.01, 0.01, 0.01)), np.zeros((3, 3)))
