"""End to end on simulated scans with known ground truth (the CI regression of the
calibration pipeline): quick.yaml, the all-errors-off sanity case, convergence from a bad
coarse estimate, the speed-of-sound bias, and `uscal run` writing metrics.json."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bench.config.error_sources import ERROR_SOURCES
from bench.config.scenario import load_scenario
from bench.jobs.single import run

from .test_cli import uscal

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "scenarios" / "quick.yaml"
ONE_SPHERE = ["protocol.spheres=[1]"]
# Every declared error source off (bench.config.error_sources), and the operator's teaching exact.
ALL_ERRORS_OFF = [
    *(f"{key}={json.dumps(value)}" for s in ERROR_SOURCES for key, value in s.off),
    "protocol.teaching_error_mm=0",
]


@pytest.fixture(scope="module")
def quick_metrics():
    return run(load_scenario(QUICK)).metrics


def test_quick_end_to_end_meets_the_regression_limits(quick_metrics):
    m = quick_metrics
    loc = m["localization"]
    assert loc["n_sweeps"] == 135  # 3 spheres × 45 poses
    assert loc["n_rejected"] <= 5
    assert loc["error_mm"]["median"] <= 0.2
    single = m["calibration"]["single"]
    assert single["true_error"]["image_mm"] <= 0.5
    assert single["true_error"]["rotation_deg"] <= 0.6
    assert single["n_retained"] >= 40
    three = m["calibration"]["three"]
    assert three["true_error"]["image_mm"] <= 0.5
    # Both calibrations are sound and say so (calib/calibration/verdict.py).
    assert single["verdict"]["status"] == three["verdict"]["status"] == "accepted"
    # The coarse estimate really was coarse: calibration did the work.
    assert m["calibration"]["coarse_error"]["rotation_deg"] > 2.0


def test_metrics_have_the_documented_keys(quick_metrics):
    m = quick_metrics
    assert {"name", "seed"} <= set(m["scenario"])
    assert {"n_sweeps", "n_rejected"} <= set(m["localization"])
    assert {"median", "p95", "max"} <= set(m["localization"]["error_mm"])
    for method in ("single", "three"):
        c = m["calibration"][method]
        assert {"rotation_deg", "translation_mm", "image_mm"} <= set(c["true_error"])
        assert {"precision_mm", "accuracy_mm", "n_retained", "iterations", "verdict"} <= set(c)
        # The verdict's evidence of how the sweeps met the spheres.
        assert set(c["sweep_geometry"]) == {"in_depth_deg", "cap_depth_mm"}
        assert 0.0 < c["sweep_geometry"]["cap_depth_mm"] < 40.0
    assert {"simulate", "localize", "calibrate", "total"} <= set(m["timing_s"])


def test_all_error_sources_off_is_near_perfect():
    m = run(load_scenario(QUICK, ONE_SPHERE + ALL_ERRORS_OFF)).metrics
    assert m["calibration"]["single"]["true_error"]["image_mm"] <= 0.1


@pytest.mark.slow  # ten seconds or more on this machine
def test_converges_from_a_bad_coarse_estimate(tmp_path):
    out = tmp_path / "run"
    r = uscal(
        "run",
        str(QUICK),
        "--out",
        str(out),
        "--set",
        "protocol.spheres=[1]",
        "--set",
        "calibration.initial_error_mm=10",
        "--set",
        "calibration.initial_error_deg=20",
        "--no-rrd",
    )
    assert r.returncode == 0, r.stderr
    assert not (out / "recording.rrd").exists()
    assert "single" in r.stdout and "image mm" in r.stdout
    m = json.loads((out / "metrics.json").read_text())
    assert m["calibration"]["coarse_error"]["rotation_deg"] > 10
    single = m["calibration"]["single"]
    assert single["true_error"]["image_mm"] <= 0.5
    assert single["true_error"]["rotation_deg"] <= 0.6


@pytest.mark.slow
def test_speed_of_sound_correction_removes_a_real_bias():
    off = run(load_scenario(QUICK, [*ONE_SPHERE, "imaging.sound_speed_correction=false"]))
    err_off = off.metrics["calibration"]["single"]["true_error"]["image_mm"]
    assert err_off > 0.3  # water at 20 °C: depths 3.9 % too large


@pytest.mark.slow  # ten seconds or more on this machine
def test_localizing_spheres_on_threads_changes_nothing():
    """`alternate(threads=2)` (the re-calibration's last task) localizes the spheres side
    by side: the same estimate, bit for bit, as one after the other."""
    from bench.acquire_sim import make_imager, make_twin, simulate_acquisition
    from bench.config.method import axial_scale
    from calib.calibration.alternation import AlternationSettings, alternate

    sc = load_scenario(
        QUICK,
        ["protocol.spheres=[1, 2]", "protocol.frames_per_sweep=11",
         "imaging.pixel_spacing_mm=[0.2, 0.2]", "imaging.width_mm=30", "imaging.depth_mm=35"],
    )  # fmt: skip
    twin = make_twin(sc)
    acq = simulate_acquisition(sc, twin, make_imager(sc, twin))
    sweeps = {t: acq.dataset.of(t) for t in acq.dataset.targets()}
    cad = {t: twin.phantom_cad.landmarks[t] for t in sweeps}
    settings = AlternationSettings(sc.localization, axial_scale=axial_scale(sc))
    radius = sc.phantom.sphere_radius_mm * 1e-3
    serial, threaded = (
        alternate(
            sweeps,
            radius,
            replace(settings, threads=threads),
            cad_centres=cad,
            T_coarse=acq.T_ee_us_coarse,
        )
        for threads in (1, 2)
    )
    assert len(serial.history) == len(threaded.history) >= 2
    assert (serial.result.T_ee_us == threaded.result.T_ee_us).all()
    centres = [
        np.array([loc.centre for t in sweeps for loc in alt.localizations[t]])
        for alt in (serial, threaded)
    ]
    assert np.isfinite(centres[0]).all(axis=1).mean() > 0.8
    np.testing.assert_array_equal(*centres)


def _random_sweeps(rng: np.random.Generator, n: int, shape: tuple[int, int, int]) -> list:
    """``n`` sweeps of sphere 1 with random frames of ``shape`` and random joint angles."""
    from calib.records import Sweep

    return [
        Sweep(
            "sphere_1",
            k,
            rng.integers(0, 256, shape, dtype=np.uint8),
            (1e-4, 1e-4),
            rng.normal(size=(shape[0], 6)),
            np.repeat(np.eye(4)[None], shape[0], axis=0),
        )
        for k in range(n)
    ]


def test_frames_to_file_maps_the_same_frames(tmp_path):
    """A sphere's frames written to the run's scratch file come back identical, mapped
    copy-on-write (a write changes the mapping, never the file), the sweeps otherwise
    unchanged."""
    from bench.files import frames_to_file

    sweeps = _random_sweeps(np.random.default_rng(0), 4, (3, 8, 6))
    mapped = frames_to_file(sweeps, tmp_path / "A_sphere_1.npy")
    for a, b in zip(sweeps, mapped, strict=True):
        np.testing.assert_array_equal(a.images, b.images)
        assert isinstance(b.images.base, np.memmap) or isinstance(b.images, np.memmap)
        assert (a.target, a.pose_id, a.spacing) == (b.target, b.pose_id, b.spacing)
        np.testing.assert_array_equal(a.q, b.q)
    mapped[0].images[0, 0, 0] ^= 255
    on_disk = np.load(tmp_path / "A_sphere_1.npy")
    np.testing.assert_array_equal(on_disk[0], sweeps[0].images)
    # Frames of another shape: one clear error, and no file half written.
    odd = [*sweeps, *_random_sweeps(np.random.default_rng(2), 1, (3, 8, 7))]
    with pytest.raises(ValueError, match=r"frames \(3, 8, 7\), not \(3, 8, 6\)"):
        frames_to_file(odd, tmp_path / "B_sphere_1.npy")
    assert not (tmp_path / "B_sphere_1.npy").exists()


def _mapped_file_kib() -> int:
    """This process's resident pages mapped from files (kB, /proc/self/smaps_rollup)."""
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
        if line.startswith("Pss_File:"):
            return int(line.split()[1])
    raise AssertionError("no Pss_File in smaps_rollup")


def test_drop_frame_pages_lets_go_of_mapped_frames_and_keeps_them_valid(tmp_path):
    """Frames mapped from a scratch file hold their pages once read; dropping them gives
    the pages back (64 MB here) and the frames still read the same; a sweep whose frames
    are in memory is left alone."""
    from bench.files import drop_frame_pages, frames_to_file

    sweeps = _random_sweeps(np.random.default_rng(1), 16, (4, 1024, 1024))
    sums = [int(s.images.sum(dtype=np.int64)) for s in sweeps]
    mapped = frames_to_file(sweeps, tmp_path / "A_sphere_1.npy")
    before = _mapped_file_kib()
    assert [int(s.images.sum(dtype=np.int64)) for s in mapped] == sums  # pages read in
    touched = _mapped_file_kib()
    assert touched - before > 48 * 1024  # most of the 64 MB is resident
    drop_frame_pages([*mapped, *sweeps])  # the in-memory ones are ignored
    assert touched - _mapped_file_kib() > 48 * 1024
    assert [int(s.images.sum(dtype=np.int64)) for s in mapped] == sums
    assert [int(s.images.sum(dtype=np.int64)) for s in sweeps] == sums


def test_one_blas_thread_limits_blas_inside_and_restores_after():
    """The limiter a pool's processes use: one BLAS thread while it holds, the previous
    count after."""
    from threadpoolctl import threadpool_info

    from bench.parallel import one_blas_thread

    def blas_threads() -> list[int]:
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    np.ones((4, 4)) @ np.ones((4, 4))  # BLAS loaded
    outside = blas_threads()
    assert outside
    with one_blas_thread():
        assert blas_threads() == [1] * len(outside)
    assert blas_threads() == outside
