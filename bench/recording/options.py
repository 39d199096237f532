"""Where a run's rerun recording goes and how much of it: plain settings, picklable for
the pool workers, in a module of their own so that a run that records nothing never
loads rerun (≈ 50 MB and ≈ 1 s per process, measured)."""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RecordingOptions", "frames_per_target", "sweeps_to_log"]


@dataclass(frozen=True)
class RecordingOptions:
    """Where the run's recording goes and how much of it (picklable, for the workers).

    ``recording_id`` ties the part files of one run together; ``max_frames`` bounds the
    B-mode frames logged per session (whole sweeps, spread evenly); ``jpeg_quality`` of
    the logged frames (the frames are grey levels: 85 keeps speckle visible at a tenth
    of the raw size).
    """

    path: Path
    recording_id: str
    max_frames: int = 420
    jpeg_quality: int = 85

    @classmethod
    def new(cls, path: str | Path, max_frames: int = 420) -> RecordingOptions:
        return cls(Path(path), f"uscal-{uuid.uuid4().hex[:12]}", max_frames)

    def part(self, name: str) -> RecordingOptions:
        """Options of a worker's part file beside the final one."""
        parts = self.path.parent / f".{self.path.stem}.parts"
        parts.mkdir(parents=True, exist_ok=True)
        return RecordingOptions(
            parts / f"{name}.rrd", self.recording_id, self.max_frames, self.jpeg_quality
        )


def sweeps_to_log(n_sweeps: int, frames_per_sweep: int, max_frames: int) -> list[int]:
    """Indices of whole sweeps, spread evenly, with at most ``max_frames`` frames."""
    if n_sweeps == 0 or frames_per_sweep == 0:
        return []
    k = min(n_sweeps, max(max_frames // frames_per_sweep, 0))
    if k == 0:
        return []
    return sorted({int(i) for i in np.linspace(0, n_sweeps - 1, k).round()})


def frames_per_target(targets: list[str], frames_per_sweep: int, max_frames: int) -> dict[str, int]:
    """A session's ``max_frames`` as whole sweeps dealt out over its targets in turn (the
    first targets take the remainder), in frames per target. An even split in frames
    gave each of four spheres 15 of 60 frames, less than a sweep, and the recording had
    none."""
    if not targets or frames_per_sweep <= 0:
        return dict.fromkeys(targets, 0)
    n = max_frames // frames_per_sweep
    k = len(targets)
    return {t: frames_per_sweep * (n // k + (i < n % k)) for i, t in enumerate(targets)}
