"""The sweeps a plan can be made of, about spheres the twin's arm faces: a dense set of
sweep poses about each taught pose (``planning`` settings), kept where the sphere stays
inside the image by the margin (as the coarse mount predicts it) and where the arm
reaches the sweep's first, middle and last frames with the clearance from the tank and
the phantom; and their information about ``T_ee_us`` (:class:`calib.acquisition.planning.
Candidates`). Used by ``uscal plan --optimize`` and by the sequential acquisition."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.acquisition.planning import (
    Candidates,
    SweepPose,
    sweep_commands,
)

from .acquire_sim import teach_at
from .config.scenario import Scenario, layout_sigma_mm

__all__ = [
    "NOT_CLEAR",
    "OUT_OF_IMAGE",
    "PlanSphere",
    "candidate_sweeps",
    "clear",
    "in_image",
    "observations",
    "path_clear",
    "sweep_of",
    "taught_sphere",
]

Array = NDArray[np.float64]
#: Why a candidate sweep is left out.
OUT_OF_IMAGE = "out of the image"
NOT_CLEAR = "unreachable or too close to the tank or phantom"


@dataclass(frozen=True, eq=False)
class PlanSphere:
    name: str
    index: int  # into the plan's spheres
    taught: Array  # T_base_ee of the taught pose (as the controller reports it)
    centre: Array  # where the coarse T_ee_us puts the sphere, base frame (m)
    taught_q: Array | None = None  # the taught joint angles (where its sweeps start from)


def taught_sphere(
    scenario: Scenario, twin, coarse: Array, name: str, index: int, rng: np.random.Generator
) -> PlanSphere:
    """Teach the nominal pose at sphere ``name`` as the session's acquisition teaches it
    (its teaching error drawn from ``rng``, the session's protocol stream): a rig plans
    from the pose it was taught, so the twin's plan is the one its acquisition checks
    and moves through."""
    proto = scenario.protocol
    depth = proto.target_depth_mm * 1e-3
    taught = teach_at(
        twin,
        twin.truth.landmarks_base[name],
        depth,
        f"taught pose at {name}",
        rng,
        proto.teaching_error_mm,
    )
    centre = se3.apply(taught.T_base_ee @ coarse, np.array([0.0, depth, 0.0]))
    return PlanSphere(name, index, taught.T_base_ee, centre, taught.q)


def in_image(scenario: Scenario, pose: SweepPose) -> bool:
    """The sphere, as the coarse mount predicts it, inside the image by the margin."""
    p = scenario.planning
    depth = scenario.protocol.target_depth_mm
    r = scenario.phantom.sphere_radius_mm + p.image_margin_mm
    x, y = -pose.lateral_mm, depth - pose.axial_mm
    return abs(x) + r <= scenario.imaging.width_mm / 2 and r <= y <= scenario.imaging.depth_mm - r


def sweep_of(
    scenario: Scenario,
    sphere: PlanSphere,
    coarse: Array,
    pose: SweepPose,
    n_frames: int | None = None,
) -> Array:
    """The flange commands of one sweep about ``sphere`` (``n_frames``: the protocol's,
    or e.g. 3 for its first, middle and last frames)."""
    proto = scenario.protocol
    return sweep_commands(
        sphere.taught,
        coarse,
        proto.target_depth_mm * 1e-3,
        pose,
        half_length=proto.sweep_half_length_mm * 1e-3,
        n_frames=proto.frames_per_sweep if n_frames is None else n_frames,
    )


def clear(scenario: Scenario, twin, commands: Array) -> bool:
    """Every pose reachable, with the clearance (``planning.clearance_mm``) from the tank
    and the phantom."""
    need = scenario.planning.clearance_mm * 1e-3
    return bool(np.all(twin.robot.clearances(commands, need + 1e-3) >= need))


def path_clear(scenario: Scenario, twin, commands: Array, q_start: Array) -> Array:
    """Per pose of ``commands`` (moved through in order from ``q_start``), whether the
    arm reaches it with the clearance, on the way the acquisition takes."""
    need = scenario.planning.clearance_mm * 1e-3
    return twin.robot.path_clearances(commands, need + 1e-3, q_start) >= need


def candidate_sweeps(scenario, twin, spheres, coarse, poses_of, check: bool):
    """(sphere, pose, commands) of every candidate that passes the checks, and the
    count left out by each check (the reach and clearance of every candidate's first,
    middle and last frames in one batch)."""
    out, left = [], {OUT_OF_IMAGE: 0, NOT_CLEAR: 0}
    for s in spheres:
        for pose in poses_of(s):
            if check and not in_image(scenario, pose):
                left[OUT_OF_IMAGE] += 1
                continue
            out.append((s, pose, sweep_of(scenario, s, coarse, pose)))
    if check and out:
        ends = np.array([C[[0, len(C) // 2, -1]] for _, _, C in out])
        need = scenario.planning.clearance_mm * 1e-3
        room = twin.robot.clearances(ends.reshape(-1, 4, 4), need + 1e-3).reshape(len(out), 3)
        keep = np.all(room >= need, axis=1)
        left[NOT_CLEAR] += int((~keep).sum())
        out = [c for c, k in zip(out, keep, strict=True) if k]
    return out, left


def observations(scenario, coarse, spheres, found, multi: bool) -> Candidates:
    depth = scenario.protocol.target_depth_mm * 1e-3
    T_ref = np.array([C[len(C) // 2] for _, _, C in found])
    p_us = np.array([pose.target_in_image(depth) for _, pose, _ in found])
    target = np.array([s.index for s, _, _ in found])
    layout = {s.index: s.centre for s in spheres} if multi else None
    return Candidates.build(
        T_ref,
        coarse,
        p_us,
        target,
        scenario.planning.noise(),
        layout=layout,
        layout_sigma_mm=layout_sigma_mm(scenario),
    )
