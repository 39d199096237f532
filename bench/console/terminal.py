"""The live terminal: progress bars (one per task :mod:`bench.progress` reports, with
counts, elapsed time and ETA) and the rerun viewer opened on a recording."""

from __future__ import annotations

import contextlib
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as RichProgress

__all__ = ["Bars", "progress_bars", "spawn_viewer"]


class Bars:
    """Rich progress bars, one per reported task, with counts, elapsed time and ETA."""

    def __init__(self, console: Console) -> None:
        self.progress = RichProgress(
            TextColumn("{task.description:<28}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            console=console,
            disable=console.quiet,
        )
        self.console = self.progress.console
        self._tasks: dict[str, TaskID] = {}

    def update(self, task: str, done: int, total: int) -> None:
        if task not in self._tasks:
            self._tasks[task] = self.progress.add_task(task, total=total)
        self.progress.update(self._tasks[task], completed=done, total=total)


@contextlib.contextmanager
def progress_bars(console: Console):
    bars = Bars(console)
    with bars.progress:
        yield bars


def spawn_viewer(path: Path, console: Console) -> None:
    """Open a recording in the rerun viewer, if one is installed (a separate process)."""
    import shutil
    import subprocess

    viewer = shutil.which("rerun")
    if viewer is None:
        console.print(f"no rerun viewer found on PATH: open {path} with `rerun {path}`")
        return
    subprocess.Popen([viewer, str(path)], start_new_session=True)
    console.print(f"opened {path} in the rerun viewer")
