"""Atomic output directories: a run writes into a temporary sibling and renames it into
place at the end, so a failed run leaves no half-written result (DESIGN.md §3)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from calib.errors import UscalError

__all__ = ["OutputExistsError", "atomic_output_dir"]


class OutputExistsError(UscalError):
    """The output directory exists and would be overwritten."""


@contextlib.contextmanager
def atomic_output_dir(target: str | os.PathLike[str], force: bool = False) -> Iterator[Path]:
    """Yield a temporary directory that becomes ``target`` when the block succeeds.

    An existing non-empty ``target`` is an error unless ``force`` (then it is replaced only
    after the new content is complete). On any exception the temporary directory is
    removed and ``target`` is left as it was.
    """
    target = Path(target)
    if target.exists() and not target.is_dir():
        raise OutputExistsError(f"{target}: exists and is not a directory")
    if target.is_dir() and any(target.iterdir()) and not force:
        raise OutputExistsError(
            f"{target}: directory exists and is not empty (use --force to replace it)"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}")
        target.rename(old)
    tmp.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
