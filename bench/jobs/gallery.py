"""A gallery of simulated B-mode frames at the paper's representative poses.

The paper shows cross-sections of a sphere at three robot poses relative to the
nominal one: (a) XYZ Euler offset (−10°, +10°, +10°) with in-plane offset (+3, +3) mm,
(b) the same orientation centred, (c) (+10°, +10°, +10°) centred. The gallery renders
those, the nominal pose, and an elevational sweep through the target, by moving the
twin's robot (controller model, true arm) and grabbing frames from the simulated scanner.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from matplotlib.figure import Figure
from skimage import io as skio

from calib import se3
from calib.acquisition.protocol import rotated_about_target
from calib.image import pixel_to_us

from ..acquire_sim import make_imager, make_twin, teach_at
from ..config.geometry import lateral_axis
from ..config.scenario import Scenario

__all__ = ["GalleryPose", "gallery_poses", "write_gallery"]


@dataclass(frozen=True)
class GalleryPose:
    """A probe pose relative to the nominal one facing the target."""

    name: str
    euler_deg: tuple[float, float, float]
    in_plane_mm: tuple[float, float]
    elevation_mm: float = 0.0


def gallery_poses() -> list[GalleryPose]:
    """The paper's representative poses, the nominal one and a short elevational sweep."""
    poses = [
        GalleryPose("nominal", (0, 0, 0), (0, 0)),
        GalleryPose("a_m10_p10_p10_offset", (-10, 10, 10), (3, 3)),
        GalleryPose("b_m10_p10_p10", (-10, 10, 10), (0, 0)),
        GalleryPose("c_p10_p10_p10", (10, 10, 10), (0, 0)),
    ]
    poses += [GalleryPose(f"sweep_{e:+.0f}mm", (0, 0, 0), (0, 0), e) for e in (-6, -4, -2, 2, 4, 6)]
    return poses


def _target(scenario: Scenario, landmarks: dict[str, np.ndarray]) -> tuple[str, np.ndarray]:
    name = {
        "spheres": "sphere_1",
        "cone": "apex",
        "prism": "ridge_start",
        "nwire": "nwire",
        "wire": "wire",
    }[scenario.phantom.kind]
    point = landmarks[name]
    if scenario.phantom.kind == "prism":  # the middle of the ridge
        point = (landmarks["ridge_start"] + landmarks["ridge_end"]) / 2
        name = "ridge"
    return name, point


def write_gallery(scenario: Scenario, outdir: Path) -> list[str]:
    """Render the gallery into ``outdir`` (which exists); returns the written file names."""
    twin = make_twin(scenario)
    imager = make_imager(scenario, twin)
    depth = scenario.protocol.target_depth_mm * 1e-3
    # The operator teaches the nominal pose by jogging until the target sits on the image
    # centre line; the poses are then commanded relative to the taught one, so the arm's
    # kinematic error shows as it would on a real robot.
    T_ee_us = twin.truth.T_ee_us
    target_name, target = _target(scenario, twin.truth.landmarks_base)
    taught = teach_at(
        twin, target, depth, "taught pose", lateral_axis=lateral_axis(scenario.phantom)
    )
    T_face = taught.T_base_ee @ T_ee_us
    written, frames, records = [], [], {}
    for pose in gallery_poses():
        R = se3.matrix_from_euler(np.radians(pose.euler_deg))
        T_us = rotated_about_target(T_face, R, depth)
        shift = [pose.in_plane_mm[0] * 1e-3, pose.in_plane_mm[1] * 1e-3, pose.elevation_mm * 1e-3]
        T_us = T_us @ se3.make(np.eye(3), shift)
        reading = twin.robot.move_to(T_us @ se3.invert(T_ee_us), pose_label=pose.name)
        frame = imager.grab().image
        frames.append((pose, frame))
        name = f"frame_{pose.name}.png"
        skio.imsave(outdir / name, frame, check_contrast=False)
        written.append(name)
        records[pose.name] = {
            "euler_deg": list(pose.euler_deg),
            "in_plane_mm": list(pose.in_plane_mm),
            "elevation_mm": pose.elevation_mm,
            "reported_T_base_ee": np.round(reading.T_base_ee, 9).tolist(),
        }
    (outdir / "gallery.yaml").write_text(
        yaml.safe_dump(
            {"scenario": scenario.source, "target": target_name, "poses": records}, sort_keys=False
        )
    )
    written.append("gallery.yaml")
    written.append(_contact_sheet(frames, imager.spacing, outdir / "gallery.png", target_name))
    return written


def _contact_sheet(frames, spacing, path: Path, target: str) -> str:
    H, W = frames[0][1].shape
    # The first and last pixels' centres in the us frame, mm: the axes' extent (left,
    # right, bottom, top; row 0, the transducer face, at the top).
    (x0, y0, _), (x1, y1, _) = 1e3 * pixel_to_us([0, H - 1], [0, W - 1], W, spacing)
    extent = [x0, x1, y1, y0]
    cols = 5
    rows = -(-len(frames) // cols)
    # A bare Figure renders with the Agg canvas whatever backend pyplot would pick.
    fig = Figure(figsize=(3.2 * cols, 3.4 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (pose, frame) in zip(axes.ravel(), frames, strict=False):
        ax.axis("on")
        ax.imshow(frame, cmap="gray", vmin=0, vmax=255, extent=extent)
        ax.set_title(pose.name, fontsize=8)
        ax.set_xlabel("lateral (mm)", fontsize=7)
        ax.set_ylabel("depth (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(f"simulated B-mode frames about {target}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path.name
