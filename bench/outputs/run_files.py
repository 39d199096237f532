"""A run's output directory, written as one piece (``uscal run`` and ``uscal
calibrate`` alike): ``metrics.json``, Tables I–III as ``tables.md`` / ``tables.csv`` (the
paper's experiment), the report with its figures and ``calibration.yaml``
(:func:`~bench.outputs.report.write_report`) and the rerun recording — in a new
directory that appears whole or not at all; a recording asked for elsewhere
(``--rrd FILE``) is moved there once complete."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from calib.errors import UscalError

from ..config.scenario import Scenario
from ..files import atomic_output_dir, make_directory
from ..recording.options import RecordingOptions
from ..results import RunResult
from .report import write_report

__all__ = ["RunDirectory", "run_directory"]


@dataclass
class RunDirectory:
    """Where a run writes while it runs (``tmp``, renamed to ``path`` at the end) and
    what it wrote (relative to ``path``, or absolute for a recording moved elsewhere)."""

    path: Path
    tmp: Path
    recording: RecordingOptions | None
    rrd: Path | None  # --rrd FILE: the recording's final place
    written: list[str] = field(default_factory=list)

    @property
    def recording_path(self) -> Path | None:
        """Where the recording will be once the directory is complete."""
        if self.recording is None:
            return None
        return self.rrd if self.rrd is not None else self.path / "recording.rrd"

    def write(self, scenario: Scenario, result: RunResult) -> None:
        """``metrics.json``, the tables of an evaluation and the report."""
        (self.tmp / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        self.written.append("metrics.json")
        if self.recording is not None and self.rrd is None:
            self.written.append("recording.rrd")
        if result.evaluation is not None:
            ev = result.evaluation
            (self.tmp / "tables.md").write_text(ev.tables_markdown, encoding="utf-8")
            (self.tmp / "tables.csv").write_text(ev.tables_csv, encoding="utf-8")
            self.written += ["tables.md", "tables.csv"]
        self.written += write_report(self.tmp, scenario, result)


@contextlib.contextmanager
def run_directory(
    out: str | os.PathLike[str],
    force: bool,
    rrd: str | None,
    no_rrd: bool,
    rrd_frames: int,
) -> Iterator[RunDirectory]:
    """A new output directory ``out`` for the block (refused before anything runs when
    it, or the ``rrd`` file's directory, cannot be made); with a recording unless
    ``no_rrd``, written inside it and moved to ``rrd`` when one is given."""
    if rrd and Path(rrd).is_dir():
        raise UscalError(f"--rrd {rrd}: is a directory; give a file name (e.g. run.rrd)")
    if rrd and not no_rrd:
        make_directory(Path(rrd).parent)  # fail now, not after the run
    with atomic_output_dir(out, force=force) as tmp:
        recording = None if no_rrd else RecordingOptions.new(tmp / "recording.rrd", rrd_frames)
        directory = RunDirectory(Path(out), tmp, recording, Path(rrd) if rrd else None)
        yield directory
    if directory.rrd is not None and recording is not None:
        make_directory(directory.rrd.parent)
        # The finished file leaves the (now final) output directory in one rename.
        os.replace(directory.path / "recording.rrd", directory.rrd)
        directory.written.append(str(directory.rrd.resolve()))
