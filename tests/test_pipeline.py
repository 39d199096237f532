"""The one dataset → calibration path (calib.pipeline) on a small twin dataset with
touches, read back from its files as `uscal calibrate` reads a rig's: single- and
three-marker calibration, the touch-based kinematics and the paper's folds, checked
against the twin's ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from bench.acquire_sim import (
    make_imager,
    make_twin,
    save_dataset,
    simulate_acquisition,
    simulate_touches,
)
from bench.config.method import method_inputs
from bench.config.scenario import load_scenario
from bench.jobs.recorded import calibrate_recorded
from bench.sessions import dataset_rngs
from bench.truth import image_error_mm
from calib.pipeline import calibrate_markers, run_folds

from .conftest import QUICK


@pytest.fixture(scope="module")
def two_spheres_with_touches(tmp_path_factory):
    """quick.yaml on spheres 1 and 2 (11 frames a sweep, 1 mm apart), with the 24 stylus touches,
    saved as dataset files: (scenario, twin truth, acquisition, dataset directory)."""
    sc = load_scenario(
        QUICK,
        [
            "protocol.spheres=[1, 2]",
            "protocol.frames_per_sweep=11",
            "protocol.sweep_half_length_mm=5",
            "evaluation.initialisations=2",
        ],
    )
    twin = make_twin(sc)
    touches = simulate_touches(sc, twin, dataset_rngs(sc, 0)["touch_contact"])
    acq = simulate_acquisition(sc, twin, make_imager(sc, twin), "A", touches=touches)
    directory = tmp_path_factory.mktemp("pipeline") / "A"
    save_dataset(directory, sc, twin, acq)
    return sc, twin.truth, acq, directory


@pytest.mark.slow
def test_a_recorded_dataset_with_touches_runs_the_papers_folds(two_spheres_with_touches):
    sc, truth, acq, directory = two_spheres_with_touches
    result = calibrate_recorded(directory, sc, (1,))
    # The sweeps ran along the coarse mount's elevational axis: the recorded calibration
    # says how far that is from its own normal (the true one, to its error).
    coarse_off = np.degrees(np.arccos(acq.T_ee_us_coarse[:3, 2] @ truth.T_ee_us[:3, 2]))
    assert coarse_off > 2.0
    axis = result.metrics["calibration"]["sweep_axis"]
    assert axis["angle_deg"] == pytest.approx(coarse_off, abs=1.0)
    ev = result.metrics["evaluation"]
    assert ev["dh_from"] == "A" and ev["touches"] == 24
    # Two spheres: each trained alone and tested on the other, then leave-one-out.
    assert [(f["kind"], f["train"]) for f in ev["folds"]] == [
        ("single", ["sphere_1"]),
        ("single", ["sphere_2"]),
        ("three", ["sphere_2"]),
        ("three", ["sphere_1"]),
    ]
    # quick.yaml's arm is exact and its touches are the stylus's: the test sphere's
    # centre lands within a millimetre of where the touches put it, and every fold's
    # mount maps the image within a millimetre of the truth.
    for fold in ev["folds"]:
        assert all(0 < v < 1.0 for v in fold["accuracy_mm"].values()), fold
        T = np.array(fold["T_ee_us"])
        assert image_error_mm(sc, T, truth.T_ee_us) < 1.0
    s = ev["summary"]["single"]
    assert s["accuracy_mm"]["mean"] == pytest.approx(
        np.mean([v for f in ev["folds"][:2] for v in f["accuracy_mm"].values()])
    )
    assert result.metrics["dh_table_refined"] and result.dh_table is not None


@pytest.mark.slow  # ten seconds or more on this machine
def test_folds_against_the_true_centres_measure_the_method_alone(two_spheres_with_touches):
    """With the twin's true sphere centres as the references (the touches' role), a
    fold's accuracy is the localization and calibration error alone: under a millimetre
    with quick.yaml's error sources, on every fold; the calibrations run once per fold
    from one shared first localization."""
    sc, truth, acq, _ = two_spheres_with_touches
    cad = {k: v for k, v in make_twin(sc).phantom_cad.landmarks.items() if "sphere" in k}
    method = method_inputs(sc, cad_centres=cad, T_coarse=acq.T_ee_us_coarse)
    targets = ("sphere_1", "sphere_2")
    sweeps = {t: acq.dataset.of(t) for t in targets}
    folds = run_folds("A", sweeps, {t: truth.landmarks_base[t] for t in targets}, method)
    assert [r.fold.name for r in folds.results] == [
        "A/single/sphere_1",
        "A/single/sphere_2",
        "A/three/sphere_2",
        "A/three/sphere_1",
    ]
    assert folds.seconds_initial > 0 and folds.seconds_folds > 0
    for r in folds.results:
        assert 0 < r.accuracy < 1.0, r.fold.name
        assert image_error_mm(sc, r.T_ee_us, truth.T_ee_us) < 1.0
    # The single-marker calibration of calibrate_markers is the first fold's.
    single = calibrate_markers(acq.dataset, method, markers=(1,)).single
    assert np.allclose(single.result.T_ee_us, folds.results[0].T_ee_us, atol=1e-12)


@pytest.mark.slow
def test_the_method_runs_from_calib_alone(two_spheres_with_touches, tmp_path):
    """A script with its own data needs calib alone: the whole method (touch
    kinematics, single-marker calibration, bounds, folds) from a dataset directory and
    frozen settings, in a process that never imports the test bench, the twin or the
    simulator — and it gives what `uscal calibrate` gives with the same settings."""
    import pickle
    import subprocess
    import sys

    from bench.config.method import method_settings

    sc, _, _, directory = two_spheres_with_touches
    settings_file = tmp_path / "settings.pkl"
    settings_file.write_bytes(pickle.dumps(method_settings(sc)))
    script = f"""
import pickle, sys
import numpy as np
from calib.files.dataset import read_dataset
from calib.pipeline import calibrate_dataset
settings = pickle.loads(open({str(settings_file)!r}, "rb").read())
dataset, info = read_dataset({str(directory)!r})
found = calibrate_dataset(dataset, info, settings, markers=(1,))
np.save({str(tmp_path / "T.npy")!r}, found.calibrations.single.result.T_ee_us)
print(len(found.folds.results), sorted(found.bounds))
print(sorted({{m.split(".")[0] for m in sys.modules}} & {{"bench", "twin", "sim_us", "hw"}}))
"""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, check=False
    )
    assert out.returncode == 0, out.stderr
    folds_line, foreign_line = out.stdout.splitlines()
    assert folds_line == "4 ['single']"
    assert foreign_line == "[]"
    recorded = calibrate_recorded(directory, sc, (1,))
    T_bench = np.array(recorded.metrics["calibration"]["single"]["T_ee_us"])
    np.testing.assert_allclose(np.load(tmp_path / "T.npy"), T_bench, atol=1e-9)
