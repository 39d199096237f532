"""Shared fixtures: seeded generators and small builders."""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

import numpy as np
import pytest

from calib.dh import NOMINAL_TABLES, DHDeltas, DHTable

from .rrd import Recording
from .test_cli import uscal

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "scenarios" / "quick.yaml"

# Paper-like DH error magnitudes (RMS): 2.51°, 0.24 mm, 1.51 mm, 0.27°.
PAPER_RMS = (np.radians(2.51), 0.24e-3, 1.51e-3, np.radians(0.27))


def perturbed_table(rng: np.random.Generator, name: str = "ur3") -> DHTable:
    """The nominal table plus DH errors of paper-like size."""
    deltas = np.column_stack([rng.normal(0.0, s, 6) for s in PAPER_RMS])
    return NOMINAL_TABLES[name].with_deltas(DHDeltas.from_array(deltas))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def quick_run(tmp_path_factory, worker_id):
    """`uscal run quick.yaml` on one sphere, the recording sent elsewhere, the
    acquisition saved as dataset files (``base / "dataset"``): (output directory,
    recording path, metrics, the recording read back). Made once per test session: the
    xdist workers share it (the first to ask runs it, under a lock; the tests only read
    it)."""
    if worker_id == "master":  # one process: its own temporary directory
        base = tmp_path_factory.mktemp("rec")
    else:  # the directory the workers' temporary directories sit in: this session's
        base = tmp_path_factory.getbasetemp().parent / "quick_run"
    out, rrd = base / "run", base / "elsewhere" / "quick.rrd"
    base.mkdir(parents=True, exist_ok=True)
    with open(base.parent / f"{base.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (base / "stdout.txt").exists():
            r = uscal(
                "run", str(QUICK), "--out", str(out), "--set", "protocol.spheres=[1]",
                "--rrd", str(rrd), "--rrd-frames", "63", "--save-dataset", str(base / "dataset"),
            )  # fmt: skip
            assert r.returncode == 0, r.stderr
            (base / "stdout.txt").write_text(r.stdout, encoding="utf-8")
    return out, rrd, json.loads((out / "metrics.json").read_text()), Recording(rrd)


@pytest.fixture
def controller(tmp_path, request):
    """A loopback controller (tests/loopback.py) on ``request.param``: (address, *flags)."""
    from .loopback import Controller  # the rig's module takes QUICK from here

    host, *extra = request.param
    c = Controller(tmp_path, host, *extra)
    yield c
    c.stop()


def pytest_configure(config):
    """Before xdist starts its workers: compile the numba kernels into their cache unless
    a previous run did so for these sources (tests/numba_warmup.py says why)."""
    if hasattr(config, "workerinput") or config.option.collectonly:
        return  # a worker: its master warmed the cache
    if not getattr(config.option, "numprocesses", None):
        return  # one process: it compiles each kernel once, as it first needs it
    import hashlib

    from .numba_warmup import warm

    sources = sorted(
        p for d in ("calib", "sim_us") for p in (ROOT / d).rglob("*.py")
        if "numba.njit" in p.read_text(encoding="utf-8")
    )  # fmt: skip
    # What numba's cache checks a kernel's source by: its file's time stamp and size.
    digest = hashlib.sha256(
        repr([(str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in sources]).encode()
    ).hexdigest()
    stamp = ROOT / "tests" / "__pycache__" / "numba-warm.stamp"
    if stamp.exists() and stamp.read_text() == digest:
        return
    warm()
    stamp.parent.mkdir(exist_ok=True)
    stamp.write_text(digest)


def pytest_collection_modifyitems(config, items):
    """The modules with the most slow tests (end-to-end runs) first, each module's tests
    in their own order: with ``--dist loadscope`` a worker takes a module whole, and
    the longest taken first leave the workers finishing together (the last module taken
    a short one); xdist's own order (most tests first) left the end-to-end modules,
    which have few tests, to the end."""

    def module(item) -> str:
        return item.nodeid.split("::")[0]

    slow: dict[str, int] = {}
    for item in items:
        slow[module(item)] = slow.get(module(item), 0) + bool(item.get_closest_marker("slow"))
    first_seen = {m: i for i, m in enumerate(dict.fromkeys(map(module, items)))}
    items.sort(key=lambda i: (-slow[module(i)], first_seen[module(i)]))
