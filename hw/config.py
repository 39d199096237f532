"""Settings of the real rig: the UR controller connection and motion limits, the frame
grabber. Validated from a hw config file by :mod:`bench.config.hw`, like scenarios."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

__all__ = ["GrabberConfig", "URRobotConfig"]


@dataclass(frozen=True)
class URRobotConfig:
    """A UR controller reached through RTDE (``ur_rtde``), and the safety limits the
    adapter enforces before any motion."""

    host: str = field(default="192.168.1.10", metadata={"doc": "Controller IP address."})
    model: Literal["ur3", "ur3e"] = field(
        default="ur3", metadata={"doc": "Arm model (its published DH table plans dry runs)."}
    )
    speed_m_s: float = field(
        default=0.03, metadata={"doc": "Linear (moveL) tool speed.", "gt": 0, "le": 0.25}
    )
    acceleration_m_s2: float = field(
        default=0.3, metadata={"doc": "Linear (moveL) acceleration.", "gt": 0, "le": 1.5}
    )
    joint_speed_rad_s: float = field(
        default=0.3, metadata={"doc": "Joint (moveJ) speed.", "gt": 0, "le": 1.05}
    )
    joint_acceleration_rad_s2: float = field(
        default=0.8, metadata={"doc": "Joint (moveJ) acceleration.", "gt": 0, "le": 3.0}
    )
    workspace_min_mm: tuple[float, float, float] = field(
        default=(-450.0, -450.0, -50.0),
        metadata={"doc": "Flange positions must lie inside this box (base frame), lower corner."},
    )
    workspace_max_mm: tuple[float, float, float] = field(
        default=(450.0, 450.0, 600.0),
        metadata={"doc": "Upper corner of the allowed flange box (base frame)."},
    )
    max_step_mm: float = field(
        default=150.0,
        metadata={
            "doc": "Largest flange translation of one move (between consecutive poses); a "
            "longer step is refused before the robot moves. The paper's protocol steps up to "
            "≈ 100 mm and 35° from the last frame of a sweep to the first of the next.",
            "gt": 0,
            "le": 500,
        },
    )
    max_step_deg: float = field(
        default=45.0,
        metadata={"doc": "Largest flange rotation of one move.", "gt": 0, "le": 180},
    )
    settle_s: float = field(
        default=0.2,
        metadata={
            "doc": "Wait after a move before reading the pose and grabbing.",
            "ge": 0,
            "le": 5,
        },
    )
    connect_timeout_s: float = field(
        default=3.0,
        metadata={"doc": "Give up connecting after this long.", "gt": 0, "le": 60},
    )


@dataclass(frozen=True)
class GrabberConfig:
    """A video capture of the scanner's screen (OpenCV ``VideoCapture``)."""

    source: str = field(
        default="0",
        metadata={
            "doc": "Capture device index (e.g. '0'), a stream URL, a video file, or an image "
            "file (.pgm, .png, ...) that the scanner keeps overwriting with its current "
            "frame: re-read at every grab."
        },
    )
    roi_px: tuple[int, int, int, int] | None = field(
        default=None,
        metadata={
            "doc": "Image region of the B-mode picture in the captured frame: x, y, width, "
            "height (pixels; null: the whole frame). Row 0 of the region must be the "
            "transducer face.",
            "ge": 0,
        },
    )
    pixel_spacing_mm: tuple[float, float] = field(
        default=(0.1, 0.1),
        metadata={
            "doc": "Pixel spacing of the region (lateral, axial) as the scanner displays "
            "it (read it off the depth scale).",
            "gt": 0.001,
            "le": 5,
        },
    )
    flush_frames: int = field(
        default=4,
        metadata={
            "doc": "Frames discarded before each grab (a device buffers a few; they may show "
            "the probe before the robot settled).",
            "ge": 0,
            "le": 100,
        },
    )
    timeout_s: float = field(
        default=2.0,
        metadata={"doc": "Give up when no frame arrives for this long.", "gt": 0, "le": 60},
    )
