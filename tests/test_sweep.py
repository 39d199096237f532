"""`uscal sweep`: the sweep file's validation, the same results on a local pool and on
a real Dask LocalCluster, resuming an interrupted sweep without recomputing, and the
paper's robustness claim measured against the fixed-threshold baseline."""

from __future__ import annotations

import contextlib
import csv
import io
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.acquire_sim import (
    make_imager,
    make_twin,
    simulate_acquisition,
    simulate_acquisition_at_gains,
)
from bench.config.scenario import load_scenario
from bench.jobs.sweep import load_sweep
from bench.jobs.sweep import run_sweep as _run_sweep
from bench.outputs.sweep_report import write_sweep
from calib.errors import UscalError

from .test_cli import uscal, uscal_here

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "scenarios" / "quick.yaml"
# One sphere, short sweeps (13 frames 1 mm apart): a point takes a few seconds.
SMALL = (
    "  protocol.spheres: [[1]]\n  protocol.frames_per_sweep: [13]\n"
    "  protocol.sweep_half_length_mm: [6]\n"
)


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _sweep_file(tmp_path: Path, grid: str, seeds="[0]", methods="[refined, fixed_threshold]"):
    return _write(
        tmp_path / "sweep.yaml",
        f"base: {QUICK}\ngrid:\n{SMALL}{grid}seeds: {seeds}\nstages: [localize]\n"
        f"methods: {methods}\n",
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (f"base: {QUICK}\ncolour: red\n", "colour: unknown key"),
        ("grid: {}\n", "base: the base scenario's path"),
        (f"base: {QUICK}\nstages: [calibrate]\n", "stages: [localize] or [localize, calibrate]"),
        (f"base: {QUICK}\nmethods: [magic]\n", "methods: a non-empty list from"),
        (f"base: {QUICK}\nseeds: [1.5]\n", "seeds: a non-empty list of whole numbers"),
        (f"base: {QUICK}\ngrid:\n  imaging.gain_db: 3\n", "grid: a mapping of key path"),
        (f"base: {QUICK}\ngrid:\n  imaging.gain_db: [loud]\n", "imaging.gain_db"),
        (f"base: {QUICK}\ngrid:\n  imaging.gane_db: [0]\n", "gane_db"),
        (
            f"base: {QUICK}\ngrid:\n  protocol.target_depth_mm, imaging.depth_mm: [[10]]\n",
            "linked keys: each value a list of 2 values",
        ),
        (
            f"base: {QUICK}\ngrid:\n  protocol.target_depth_mm, imaging.depth_mm: [[10, -5]]\n",
            "imaging.depth_mm",
        ),
        ("base: nowhere.yaml\n", "nowhere.yaml"),
        (
            f"base: {QUICK}\ngrid:\n  imaging.gain_db: [0]\ndraws: {{points: 2, seed: 1, "
            "keys: {imaging.gain_db: {uniform: [-1, 1]}}}\n",
            "draws: drawn points vary their keys and seeds themselves",
        ),
        (
            f"base: {QUICK}\ndraws: {{points: 0, seed: 1, keys: {{}}}}\n",
            "draws: points: how many points to draw",
        ),
        (
            f"base: {QUICK}\ndraws: {{points: 3, seed: 1, keys: "
            "{imaging.gain_db: {uniform: [5, -5]}}}\n",
            "draws: keys: imaging.gain_db: uniform: [lo, hi], two numbers with lo < hi",
        ),
        (
            f"base: {QUICK}\ndraws: {{points: 3, seed: 1, keys: "
            "{imaging.gain_db: {gauss: [0, 1]}}}\n",
            "draws: keys: imaging.gain_db: {uniform: [lo, hi], step: s} or {choice:",
        ),
        (
            f"base: {QUICK}\ndraws: {{points: 3, seed: 1, keys: "
            "{'protocol.target_depth_mm, imaging.depth_mm': {choice: [[10]]}}}\n",
            "linked keys: each choice a list of 2 values",
        ),
        (
            f"base: {QUICK}\ngrid:\n  protocol.second_pass: [false, true]\n",
            "protocol.second_pass: a sweep scans each point once",
        ),
        # A drawn value the scenario refuses: named as a grid's is.
        (
            f"base: {QUICK}\ndraws: {{points: 20, seed: 1, keys: "
            "{imaging.gain_db: {uniform: [0, 90]}}}\n",
            "imaging.gain_db",
        ),
    ],
)
def test_bad_sweep_files_fail_with_one_clear_line(tmp_path, capsys, text, message):
    path = _write(tmp_path / "bad.yaml", text)
    with pytest.raises(UscalError, match=re.escape(message)):
        load_sweep(path)
    r = uscal_here(capsys, "sweep", str(path), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stderr.startswith("uscal: error:") and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("text", "line", "key"),
    [
        (f"base: {QUICK}\nseeds: [0]\nseeds: [1, 2]\n", 3, "seeds"),
        (
            f"base: {QUICK}\ngrid:\n  imaging.gain_db: [0]\n  imaging.gain_db: [10]\n",
            4,
            "imaging.gain_db",
        ),
    ],
)
def test_a_duplicate_key_is_refused_naming_the_file_and_key(tmp_path, capsys, text, line, key):
    """A sweep file is read as every settings file is (``bench.config.schema.read_yaml``):
    a key given twice, which a bare ``yaml.safe_load`` silently keeps the last of, is one
    error naming the file, the line and the key."""
    path = _write(tmp_path / "twice.yaml", text)
    expected = f"{path}:{line}: invalid YAML: duplicate key '{key}'"
    with pytest.raises(UscalError, match=re.escape(expected)):
        load_sweep(path)
    r = uscal_here(capsys, "sweep", str(path), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"uscal: error: {expected}"]
    assert not (tmp_path / "out").exists()


def test_the_points_cache_is_keyed_by_the_code(monkeypatch):
    """A cached point is reused only by the code that computed it: the key hashes the
    packages' source (which once was looked for one directory too deep, so that the
    hash was the empty string's and every version shared one cache)."""
    import hashlib

    from bench import grid

    assert grid.code_version() != hashlib.sha256(b"").hexdigest()[:16]
    key = grid.cache_key(base="b", seed=0)
    assert grid.cache_key(seed=0, base="b") == key
    monkeypatch.setattr(grid, "code_version", lambda: "other code")
    assert grid.cache_key(base="b", seed=0) != key


def run_sweep(spec, out: Path, **kwargs):
    """Run a sweep and write its files, as ``uscal sweep`` does."""
    result = _run_sweep(spec, out, **kwargs)
    write_sweep(out, result)
    return result


def _rows(out: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO((out / "results.csv").read_text())))


@pytest.mark.slow
def test_a_dask_cluster_gives_the_local_pools_results(tmp_path):
    distributed = pytest.importorskip("distributed")
    spec = load_sweep(_sweep_file(tmp_path, "  imaging.gain_db: [0, 10]\n"))
    local = run_sweep(spec, tmp_path / "local", workers=2)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        remote = run_sweep(spec, tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert local.computed == remote.computed == 2 and not local.failed
    assert _rows(tmp_path / "local") == _rows(tmp_path / "dask")
    rows = _rows(tmp_path / "local")
    assert [r["method"] for r in rows] == ["refined", "fixed_threshold"] * 2
    assert list(rows[0])[:4] == [
        "protocol.spheres",
        "protocol.frames_per_sweep",
        "protocol.sweep_half_length_mm",
        "imaging.gain_db",
    ]
    assert all(
        float(r["localization_median_error_mm"]) < 1.0 for r in rows if r["method"] == "refined"
    )
    assert (tmp_path / "dask" / "sweep.html").read_text().count("<img") >= 2


@pytest.mark.slow
def test_an_unreachable_scheduler_fails_fast(tmp_path):
    pytest.importorskip("distributed")
    path = _sweep_file(tmp_path, "  imaging.gain_db: [0]\n")
    t0 = time.perf_counter()
    r = uscal("sweep", str(path), "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:9")
    assert r.returncode == 2 and "cannot connect" in r.stderr
    assert time.perf_counter() - t0 < 60


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_without_recomputing(tmp_path):
    # Three seeds: three acquisitions, each point written as it ends (points that differ
    # in the gain alone are written together: test_grid_batches_*).
    path = _write(
        tmp_path / "sweep.yaml",
        f"base: {QUICK}\ngrid:\n{SMALL}  imaging.gain_db: [0]\nseeds: [0, 1, 2]\n"
        "stages: [localize, calibrate]\nmethods: [refined]\n",
    )
    out = tmp_path / "out"
    script = Path(sys.executable).parent / "uscal"
    proc = subprocess.Popen(
        [str(script), "sweep", str(path), "--out", str(out), "--workers", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    points = out / "points"
    deadline = time.time() + 240
    while time.time() < deadline and not (points.is_dir() and list(points.glob("*.json"))):
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)  # the whole process group, workers included
    proc.wait()
    first = {p.name: p.stat().st_mtime_ns for p in points.glob("*.json")}
    assert 1 <= len(first) < 3 and not (out / "results.csv").exists()
    r = uscal("sweep", str(path), "--out", str(out), "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert f"{len(first)} from the cache" in r.stdout
    assert "1 grid points × 3 seed(s) = 3 points, 3 acquisitions; ≈ " in " ".join(r.stdout.split())
    assert {p.name: p.stat().st_mtime_ns for p in points.glob("*.json") if p.name in first} == first
    rows = _rows(out)
    assert len(rows) == 3
    assert all(0 < float(r["calibration_image_mm"]) < 1.0 for r in rows)  # calibrate stage
    # A sound rig: no calibration rejected, most accepted, each judged on its 95 % bound
    # as `uscal run` judges it, and each bound covers the true image error.
    verdicts = [r["calibration_verdict"] for r in rows]
    assert set(verdicts) <= {"accepted", "suspect"} and verdicts.count("accepted") >= 2
    for r in rows:
        assert float(r["calibration_image_mm"]) <= float(r["calibration_bound_image_mm"]) < 2.0
        assert r["calibration_bound_covers"] == "True"
    # Each verdict says why in its own cell (commas and all): none when accepted.
    for r in rows:
        reasons = r["calibration_verdict_reasons"]
        assert (r["calibration_verdict"] == "accepted") == (reasons == ""), reasons
        assert r["error"] == ""
    assert (
        "The calibrations' verdicts (on their 95 % bounds): refined:"
        in (out / "sweep.html").read_text()
    )
    assert (
        "cover the true error: refined <strong>3 of 3</strong>" in (out / "sweep.html").read_text()
    )


def _pool_workers(pid: int) -> list[int]:
    """The spawned pool workers among a process's children (Linux /proc)."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    out = []
    for c in children:
        try:
            if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes():
                out.append(int(c))
        except FileNotFoundError:
            continue
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc (Linux)")
@pytest.mark.parametrize("after_s", [0.0, 3.0], ids=["while-starting", "mid-task"])
def test_a_sweep_stopped_by_sigterm_takes_its_workers_with_it(tmp_path, after_s):
    """``kill`` (SIGTERM) to the sweep alone, as a job scheduler sends it: its workers
    exit within seconds instead of running their task to its end, whether they were
    into their point or still importing (a worker the run left before its initializer
    ran once took init for its parent and ran its whole point)."""
    path = _write(
        tmp_path / "sweep.yaml",
        f"base: {QUICK}\ngrid:\n{SMALL}  imaging.gain_db: [-10, 0]\nseeds: [0]\n"
        "stages: [localize, calibrate]\nmethods: [refined]\n",
    )
    script = Path(sys.executable).parent / "uscal"
    proc = subprocess.Popen(
        [str(script), "sweep", str(path), "--out", str(tmp_path / "out"), "--workers", "1"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.time() + 120
        workers: list[int] = []
        while time.time() < deadline and not workers:
            time.sleep(0.2)
            workers = _pool_workers(proc.pid)
        assert workers, "the sweep started no worker"
        time.sleep(after_s)  # 3 s: the worker is past its start, into its point
        os.kill(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        deadline = time.time() + 10
        while time.time() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.2)
        assert not any(_alive(w) for w in workers)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # whatever is left of the session


@pytest.mark.slow
def test_the_threshold_free_localizer_holds_across_gain_and_the_baseline_does_not(tmp_path):
    """The paper's claim on the twin: quick.yaml (spheres 1-2, 90 sweeps per gain),
    seed 0. Measured (also over seeds 0-2, in the closing note): the threshold-free
    median error stays within 25 % of its 0 dB value from -10 to +10 dB; beyond, it does
    not — +20 dB raises it by half or more (speckle and cap saturate) and -20 dB loses a
    fifth of the detections — though it stays sub-millimetre; the fixed threshold tuned
    at 0 dB loses every detection at -20 dB and is centimetres off from +10 dB."""
    path = _write(
        tmp_path / "gain.yaml",
        f"base: {QUICK}\ngrid:\n  protocol.spheres: [[1, 2]]\n"
        "  imaging.gain_db: [-20, -10, 0, 10, 20]\nseeds: [0]\n"
        "stages: [localize]\nmethods: [refined, fixed_threshold]\n",
    )
    result = run_sweep(load_sweep(path), tmp_path / "out", workers=2)
    assert not result.failed
    table = {}
    for doc in result.points:
        gain = dict((k, v) for k, v in doc["overrides"])["imaging.gain_db"]
        for row in doc["rows"]:
            table[(row["method"], gain)] = (
                row["localization_median_error_mm"],
                row["rejected_fraction"],
            )
    ref0 = table[("refined", 0)][0]
    for gain in (-10, 10):
        assert abs(table[("refined", gain)][0] - ref0) <= 0.25 * ref0, table
        assert table[("refined", gain)][1] <= 0.05, table
    for gain in (-20, 20):
        assert table[("refined", gain)][0] < 1.0 and table[("refined", gain)][1] <= 0.3, table
    base0 = table[("fixed_threshold", 0)][0]
    assert base0 < 0.2  # tuned at 0 dB: as good as the threshold-free method there
    # Several-fold worse, or no detection in most sweeps, at ±10 dB or beyond.
    grew = {
        g for g in (-20, -10, 10, 20)
        if not np.isfinite(table[("fixed_threshold", g)][0])
        or table[("fixed_threshold", g)][0] >= 5 * base0
        or table[("fixed_threshold", g)][1] >= 0.5
    }  # fmt: skip
    assert {-20, 10, 20} <= grew, table


def test_a_failing_point_records_its_error_and_the_sweep_goes_on(tmp_path):
    """A point that raises (here: its base scenario vanished after validation) is
    recorded with its error, in points/ and results.csv; the other points still run."""
    base = _write(tmp_path / "base.yaml", QUICK.read_text(encoding="utf-8"))
    path = _write(
        tmp_path / "sweep.yaml",
        "base: base.yaml\ngrid:\n  imaging.gain_db: [0, 10]\nseeds: [0]\nmethods: [refined]\n",
    )
    spec = load_sweep(path)
    base.unlink()
    result = run_sweep(spec, tmp_path / "out", workers=1)
    assert result.failed == 2 and result.computed == 2
    rows = _rows(tmp_path / "out")
    assert len(rows) == 2 and all("base.yaml" in r["error"] for r in rows)
    assert "2 point(s) failed" in (tmp_path / "out" / "sweep.html").read_text()


@pytest.mark.slow
def test_a_refused_plan_is_not_a_failure(tmp_path):
    """An 8 mm sphere at a 10 mm target: the probe would touch it, and the plan is
    refused before anything moves. The condition cannot be run on this rig; nothing went
    wrong: the point is listed as refused, not failed, and the sweep exits 0."""
    path = _write(
        tmp_path / "sweep.yaml",
        f"base: {QUICK}\ngrid:\n  protocol.target_depth_mm, imaging.depth_mm: [[10, 25]]\n"
        "  phantom.sphere_radius_mm: [8]\nseeds: [0]\nstages: [localize]\n"
        "methods: [refined]\n",
    )
    out = tmp_path / "out"
    r = uscal("sweep", str(path), "--out", str(out), "--workers", "1")
    assert r.returncode == 0, (r.returncode, r.stdout, r.stderr)
    assert "0 failed, 1 refused before anything moved" in " ".join(r.stdout.split())
    (row,) = _rows(out)
    assert row["error"].startswith("refused: CollisionError")
    page = (out / "sweep.html").read_text()
    assert "1 point(s) refused before anything moved" in page and "failed" not in page


def test_linked_keys_are_set_together_and_reported(tmp_path):
    """A grid entry of several keys (the image depth following the target depth) sets
    them together: one point per value, each key in the point's overrides and its own
    column of results.csv; the page shows the entry against its first key."""
    from bench.outputs.sweep_report import results_csv, sweep_html

    path = _write(
        tmp_path / "sweep.yaml",
        f"base: {QUICK}\ngrid:\n  imaging.gain_db: [0, 10]\n"
        "  protocol.target_depth_mm, imaging.depth_mm: [[15, 30], [25, 40]]\n"
        "seeds: [0]\nstages: [localize]\nmethods: [refined]\n",
    )
    spec = load_sweep(path)
    points = spec.points()
    assert len(points) == 4
    assert points[1][0] == (
        ("imaging.gain_db", 0),
        ("protocol.target_depth_mm", 25),
        ("imaging.depth_mm", 40),
    )
    rows = [
        {"overrides": list(o), "seed": s, "rows": [{"method": "refined", "false_acceptances": 0,
         "localization_median_error_mm": 0.1 * (i + 1), "rejected_fraction": 0.0}]}
        for i, (o, s) in enumerate(points)
    ]  # fmt: skip
    header = results_csv(spec, rows).splitlines()[0].split(",")
    assert header[:3] == ["imaging.gain_db", "protocol.target_depth_mm", "imaging.depth_mm"]
    page = sweep_html(spec, rows, tmp_path)
    assert "protocol.target_depth_mm, imaging.depth_mm" in page
    assert "refined <strong>0</strong>" in page or "refined **0**" in page


def test_drawn_points_are_the_file_s_own_and_held_out(tmp_path):
    """``draws:``: the same file draws the same points (each key uniform within its range
    at its step, or one of its choices; linked keys together), every point with a twin
    seed of its own, away from the grids' seeds; another draw seed draws other points.
    results.csv has a column per key; the page gives the spread over the points and
    every point against each key."""
    from bench.jobs.sweep import DRAWN_SEEDS
    from bench.outputs.sweep_report import results_csv, sweep_html

    text = (
        f"base: {QUICK}\ndraws:\n  points: 30\n  seed: 4\n  keys:\n"
        "    imaging.gain_db: {uniform: [-20, 20], step: 0.1}\n"
        "    phantom.sphere_radius_mm: {uniform: [3, 8], step: 1}\n"
        "    protocol.target_depth_mm, imaging.depth_mm: {choice: [[15, 30], [25, 40]]}\n"
        "stages: [localize]\nmethods: [refined]\n"
    )
    spec = load_sweep(_write(tmp_path / "drawn.yaml", text))
    points = spec.points()
    assert spec.count() == len(points) == 30 and points == load_sweep(spec.source).points()
    gains = [dict(o)["imaging.gain_db"] for o, _ in points]
    radii = [dict(o)["phantom.sphere_radius_mm"] for o, _ in points]
    depths = [(dict(o)["protocol.target_depth_mm"], dict(o)["imaging.depth_mm"]) for o, _ in points]
    assert all(-20 <= g <= 20 and abs(10 * g - round(10 * g)) < 1e-9 for g in gains)
    assert len(set(gains)) >= 25 and min(gains) < -10 and max(gains) > 10  # spread, not a grid
    assert set(radii) <= {3, 4, 5, 6, 7, 8} and all(type(r) is int for r in radii)
    assert set(depths) == {(15, 30), (25, 40)}
    seeds = [s for _, s in points]
    assert len(set(seeds)) == 30 and all(DRAWN_SEEDS[0] <= s < DRAWN_SEEDS[1] for s in seeds)
    assert spec.seeds == tuple(seeds)
    assert spec.acquisitions() == 30  # nothing shared: each point its own twin
    assert spec.describe().startswith("30 points drawn at random (draw seed 4")
    other = load_sweep(_write(tmp_path / "other.yaml", text.replace("seed: 4", "seed: 5")))
    assert [dict(o)["imaging.gain_db"] for o, _ in other.points()] != gains
    rows = [
        {"overrides": list(o), "seed": s, "rows": [{"method": "refined", "false_acceptances": 0,
         "localization_median_error_mm": 0.01 * (i + 1), "rejected_fraction": 0.0}]}
        for i, (o, s) in enumerate(points)
    ]  # fmt: skip
    lines = results_csv(spec, rows).splitlines()
    assert lines[0].split(",")[:5] == [
        "imaging.gain_db",
        "phantom.sphere_radius_mm",
        "protocol.target_depth_mm",
        "imaging.depth_mm",
        "seed",
    ]
    assert lines[1].split(",")[:5] == [str(v) for v in (*dict(points[0][0]).values(), seeds[0])]
    page = sweep_html(spec, rows, tmp_path)
    assert "The spread over the drawn points" in page
    # The median error's spread over the 30 points: 0.01 … 0.30 mm, median 0.155.
    assert re.search(r"refined</td>\s*<td[^>]*>30</td>\s*<td[^>]*>0.01</td>", page)
    assert ">0.155<" in page and ">0.3<" in page
    for key in ("imaging_gain_db", "phantom_sphere_radius_mm", "protocol_target_depth_mm"):
        assert (tmp_path / "figures" / f"{key}__localization_median_error_mm.png").stat().st_size


@pytest.mark.slow
def test_a_drawn_sweep_runs_each_point_with_its_own_seed(tmp_path):
    """Two drawn points run end to end (one sphere, short sweeps): each point's row under
    its own drawn seed and values, the localizer's figures filled in."""
    path = _write(
        tmp_path / "drawn.yaml",
        f"base: {QUICK}\ndraws:\n  points: 2\n  seed: 9\n  keys:\n"
        "    imaging.gain_db: {uniform: [-10, 10]}\n"
        "    protocol.spheres: {choice: [[1]]}\n"
        "    protocol.frames_per_sweep: {choice: [13]}\n"
        "    protocol.sweep_half_length_mm: {choice: [6]}\n"
        "stages: [localize]\nmethods: [refined]\n",
    )
    spec = load_sweep(path)
    result = _run_sweep(spec, tmp_path / "out", workers=2)
    write_sweep(tmp_path / "out", result)
    rows = _rows(tmp_path / "out")
    assert [(float(r["imaging.gain_db"]), int(r["seed"])) for r in rows] == [
        (dict(o)["imaging.gain_db"], s) for o, s in spec.points()
    ]
    for r in rows:
        assert not r["error"] and int(r["sweeps"]) == 45 and int(r["false_acceptances"]) == 0
        assert float(r["localization_median_error_mm"]) < 0.3


@pytest.mark.slow
def test_a_large_grid_is_validated_value_by_value_and_announced(tmp_path):
    """A 1 001-value grid is validated from the base read once, ≈ 1 ms a value (its last
    value, out of range, named in one line), and the sweep says how many acquisitions it
    is and roughly how long: robustness.yaml's estimate is within a factor 2 of its
    measured 8.7 min on 2 workers (its gain axis shares acquisitions: 15 for 75 points)."""
    values = [round(-20 + 40 * i / 1_000, 4) for i in range(1_001)]
    path = _write(
        tmp_path / "big.yaml",
        f"base: {QUICK}\ngrid:\n  imaging.gain_db: {[*values[:-1], 400]}\nseeds: [0, 1]\n",
    )
    with pytest.raises(UscalError, match=r"imaging.gain_db = 400"):
        load_sweep(path)
    path.write_text(path.read_text().replace("400]", f"{values[-1]}]"))
    spec = load_sweep(path)
    assert spec.count() == 2_002 == len(spec.points())
    # A fine gain axis shares acquisitions five neighbouring gains at a time (each holds
    # its gains' frames): 201 per seed.
    assert spec.acquisitions() == 402
    robustness = load_sweep(ROOT / "scenarios" / "robustness.yaml")
    assert robustness.acquisitions() == 15
    assert 520 < robustness.estimated_seconds() < 2080  # measured: 1040 worker-seconds


@pytest.mark.slow
def test_points_that_differ_in_the_gain_alone_share_one_acquisition():
    """A gain axis is acquired once and each frame's echoes simulated once, then shown at
    every gain: each gain's acquisition is the one it makes alone (same motions, poses
    and noise; the highest gain's frames bit for bit), but for echoes only the highest
    gain's deeper trace reaches, under a lower gain's display floor: at most one grey
    level, in a few pixels per million."""
    small = [
        "protocol.spheres=[1]",
        "protocol.frames_per_sweep=13",
        "protocol.sweep_half_length_mm=6",
    ]
    gains = [-10, 10, 0]
    scenarios = [load_scenario(QUICK, [*small, f"imaging.gain_db={g}"]) for g in gains]
    twin, series = simulate_acquisition_at_gains(scenarios, "sweep")
    for scenario, shared in zip(scenarios, series, strict=True):
        alone_twin = make_twin(scenario)
        alone = simulate_acquisition(
            scenario, alone_twin, make_imager(scenario, alone_twin), "sweep"
        )
        assert np.array_equal(shared.T_ee_us_coarse, alone.T_ee_us_coarse)
        assert shared.T_base_ee_true.keys() == alone.T_base_ee_true.keys()
        assert all(
            np.array_equal(shared.T_base_ee_true[k], alone.T_base_ee_true[k])
            for k in alone.T_base_ee_true
        )
        pairs = list(zip(shared.dataset.sweeps, alone.dataset.sweeps, strict=True))
        assert len(pairs) == 45
        assert all(np.array_equal(a.T_base_ee, b.T_base_ee) for a, b in pairs)
        differ = sum(int((a.images != b.images).sum()) for a, b in pairs)
        worst = max(
            int(np.abs(a.images.astype(int) - b.images.astype(int)).max()) for a, b in pairs
        )
        pixels = sum(b.images.size for _, b in pairs)
        if scenario.imaging.gain_db == max(gains):
            assert differ == 0
        assert worst <= 1 and differ <= 1e-5 * pixels, (scenario.imaging.gain_db, differ, worst)
    assert np.array_equal(twin.truth.T_ee_us, make_twin(scenarios[0]).truth.T_ee_us)
    # Scenarios that differ in more than the gain are not one acquisition.
    deeper = load_scenario(QUICK, [*small, "imaging.gain_db=0", "imaging.depth_mm=50"])
    with pytest.raises(ValueError, match="more than the gain"):
        simulate_acquisition_at_gains([scenarios[0], deeper])


def test_a_gain_series_is_imaged_at_its_highest_gain_each_gain_once():
    """The series' own imager must trace for its highest gain (a lower one's trace stops
    short of a higher gain's echoes), each gain once; the simulator refuses a gain above
    the one it traces for."""
    from twin.imager import GainSeriesImager

    scenario = load_scenario(QUICK, ["protocol.spheres=[1]", "imaging.gain_db=0"])
    twin = make_twin(scenario)
    args = (twin.robot, twin.truth.T_ee_us, scenario.imaging, scenario.medium)
    with pytest.raises(ValueError, match=r"must be the highest of \[0\.0, 10\.0\]"):
        GainSeriesImager(*args, np.random.default_rng(0), gains_db=[0.0, 10.0])
    with pytest.raises(ValueError, match="each once"):
        GainSeriesImager(*args, np.random.default_rng(0), gains_db=[0.0, 0.0])
    imager = GainSeriesImager(*args, np.random.default_rng(0), gains_db=[-10.0, 0.0])
    T = np.eye(4)[None]
    with pytest.raises(ValueError, match="above the configured 0 dB"):
        imager.simulator.render_at_gains(T, [10.0], [None])
    with pytest.raises(ValueError, match="2 gains but 1 noise"):
        imager.simulator.render_at_gains(T, [-10.0, 0.0], [None])
