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

__all__ = [
    "OutputExistsError",
    "OutputPlaceError",
    "atomic_output_dir",
    "make_directory",
    "write_text_atomic",
]


class OutputExistsError(UscalError):
    """The output directory exists and would be overwritten."""


class OutputPlaceError(UscalError):
    """An output cannot be written where it was asked for (no such place, read-only,
    not a directory, no permission, no space)."""


def make_directory(path: str | os.PathLike[str]) -> Path:
    """``path`` as a directory, created with its parents if need be; one clear error
    (:class:`OutputPlaceError`) where it cannot be."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputPlaceError(
            f"{path}: cannot create a directory there ({e.strerror or e}); "
            "choose an output directory you can write to"
        ) from None
    return path


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
    make_directory(target.parent)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    except OSError as e:
        raise OutputPlaceError(
            f"{target}: cannot write in {target.parent} ({e.strerror or e}); "
            "choose an output directory you can write to"
        ) from None
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


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through a temporary sibling renamed into place:
    a reader (or a resumed sweep) sees the old file or the new one, never half of one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
