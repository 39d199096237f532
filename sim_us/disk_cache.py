"""A transducer's tables kept on disk between processes.

Deriving the beam and the mirror echo from a transducer takes ≈ 5 s (the broadband field
at every depth node, :mod:`sim_us.transducer`), and every process that renders pays it
once: each ``uscal`` command, each worker of a run's process pool or of a Dask cluster.
The tables depend only on the transducer's figures, the depth range and the code that
computes them, so they are computed once per machine and read back (≈ 10 ms) after.

The key is a hash of the function's name, its arguments, the source of the module that
computes it and the numpy and scipy versions: a change to any of them computes anew (a
general-purpose memoizer such as joblib's hashes the decorated function's own code only,
not the helpers it calls). Files are written whole (a temporary file renamed), so
processes computing the same tables at once never read a half-written one.

Where: ``$USCAL_CACHE_DIR``, else ``$XDG_CACHE_HOME/uscal``, else ``~/.cache/uscal``;
``USCAL_CACHE_DIR=off`` computes every time. A directory that cannot be written is
skipped without a word (the tables are computed, as without a cache).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import inspect
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

import numpy as np
import scipy

__all__ = ["cache_dir", "disk_cached", "write_whole"]

T = TypeVar("T")


def cache_dir() -> Path | None:
    """The cache's directory, or None when switched off."""
    where = os.environ.get("USCAL_CACHE_DIR")
    if where is not None:
        return None if where.strip().lower() in ("", "off") else Path(where)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "uscal"


@functools.cache
def _source_digest(module: str) -> str:
    return hashlib.sha256(inspect.getsource(sys.modules[module]).encode()).hexdigest()


def _key(fn: Callable[..., Any], args: tuple[Any, ...]) -> str:
    parts = [
        fn.__module__,
        fn.__qualname__,
        _source_digest(fn.__module__),
        np.__version__,
        scipy.__version__,
        *(repr(dataclasses.astuple(a) if dataclasses.is_dataclass(a) else a) for a in args),
    ]
    return hashlib.sha256("\x1f".join(parts).encode()).hexdigest()[:32]


def _read(path: Path, cls: type[T]) -> T | None:
    try:
        with np.load(path, allow_pickle=False) as f:
            values = {k: f[k] for k in f.files}
    except (OSError, ValueError, EOFError):
        return None
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    if {f.name for f in fields} != set(values):
        return None
    return cls(**{k: (v.item() if v.ndim == 0 else v) for k, v in values.items()})


def write_whole(path: Path, dump: Callable[[BinaryIO], None]) -> None:
    """Write a file whole: ``dump`` writes a temporary file beside ``path``, renamed to it
    when done, so that a process reading at the same time sees the whole file or none.
    Creates the directory; on an error nothing is left behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            dump(f)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def _write(path: Path, value: Any) -> None:
    arrays = {k: np.asarray(v) for k, v in dataclasses.asdict(value).items()}
    # An unwritable cache: computed every time, as without one.
    with contextlib.suppress(OSError):
        write_whole(path, lambda f: np.savez(f, **arrays))


def disk_cached(cls: type[T]) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """Keep the results of a function (hashable arguments; a dataclass ``cls`` of
    arrays and numbers) on disk, as the module docstring says."""

    def wrap(fn: Callable[..., T]) -> Callable[..., T]:
        @functools.wraps(fn)
        def cached(*args: Any) -> T:
            where = cache_dir()
            if where is None:
                return fn(*args)
            path = where / f"{fn.__name__}-{_key(fn, args)}.npz"
            value = _read(path, cls) if path.exists() else None
            if value is None:
                value = fn(*args)
                _write(path, value)
            return value

        return cached

    return wrap
