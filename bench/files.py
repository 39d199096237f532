"""Files on disk, for every layer that writes: atomic output directories (a run writes
into a temporary sibling and renames it into place at the end, so a failed run leaves no
half-written result, DESIGN.md §3), atomic text files (a sweep's cached points), and the
frame files through which sweeps cross between processes (memory-mapped ``.npy``)."""

from __future__ import annotations

import contextlib
import mmap
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from calib.errors import UscalError
from calib.records import Sweep

__all__ = [
    "OutputExistsError",
    "OutputPlaceError",
    "atomic_output_dir",
    "check_new_directory",
    "drop_frame_pages",
    "frames_to_file",
    "make_directory",
    "replaced_atomically",
    "with_frames",
    "without_frames",
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


@contextlib.contextmanager
def replaced_atomically(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary sibling of ``path`` to write, renamed onto ``path`` when the block
    ends without an error (removed when it raises): a reader sees the old file or the
    new one, never half of one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replaced_atomically` (a resumed
    sweep's cached points, the stored references)."""
    with replaced_atomically(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def frames_to_file(sweeps: Sequence[Sweep], path: Path) -> list[Sweep]:
    """Write the sweeps' frames (all of one shape) to ``path`` (``.npy``) and return the
    sweeps with their frames mapped from it (:func:`with_frames`)."""
    shape = (len(sweeps), *sweeps[0].images.shape)
    for s in sweeps:  # checked before anything is written
        if s.images.shape != shape[1:]:
            raise ValueError(f"sweep {s.pose_id}: frames {s.images.shape}, not {shape[1:]}")
    # Written, not through a writable map: a map takes a page fault per 4 KiB written
    # (≈ 1 s of CPU per dataset's 577 MB).
    with open(path, "wb") as f:
        header = {"descr": "|u1", "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(f, header)
        for s in sweeps:
            f.write(np.ascontiguousarray(s.images, dtype=np.uint8).data)
    return with_frames(sweeps, path)


def with_frames(sweeps: Sequence[Sweep], path: Path) -> list[Sweep]:
    """The sweeps with their frames mapped from the ``.npy`` file ``path`` (one frame
    stack per sweep, in order), copy-on-write: the pages are the page cache's, shared by
    every process that maps them, read as the pipeline touches them, and writable, so the
    localizer's compiled kernels take them as any frame array. Nothing else changes."""
    frames = np.load(path, mmap_mode="c")
    return [replace(s, images=frames[i]) for i, s in enumerate(sweeps)]


def drop_frame_pages(sweeps: Iterable[Sweep]) -> None:
    """Let go of the resident pages of the sweeps' frames mapped from scratch files
    (:func:`with_frames`), e.g. between folds that use different spheres: the frames
    stay valid, and the pages a later step touches are read back from the page cache
    (a minor fault each). Frames held in memory are left alone."""
    maps = {}
    for s in sweeps:
        m = getattr(s.images, "_mmap", None)
        if m is not None:
            maps[id(m)] = m
    for m in maps.values():
        m.madvise(mmap.MADV_DONTNEED)


def without_frames(sweeps: Sequence[Sweep]) -> tuple[Sweep, ...]:
    """The sweeps with their frames left out (while a file holds them), to cross a pipe."""
    empty = np.zeros((0, 0, 0), dtype=np.uint8)
    return tuple(replace(s, images=empty) for s in sweeps)


def check_new_directory(path: str | os.PathLike[str], option: str) -> None:
    """Refuse (one line naming the option) a directory that exists and is not empty: a
    new dataset is never written over another."""
    p = Path(path)
    if p.exists() and (not p.is_dir() or any(p.iterdir())):
        raise OutputPlaceError(f"{option} {path}: exists and is not an empty directory")
