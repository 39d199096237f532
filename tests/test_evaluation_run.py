"""The paper's experiment end to end on a small twin (two datasets, two spheres, coarser
images): touches, leave-one-dataset-out DH, folds, Tables I/II files and the ground-truth
figures, through `uscal run`."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from bench.config.scenario import load_scenario
from bench.sessions import dataset_scenario, scan_scenario
from calib.files.dataset import read_dataset

from .rrd import Recording
from .test_cli import uscal

ROOT = Path(__file__).resolve().parents[1]

SMALL = [
    "evaluation.datasets=[A, B]",
    "evaluation.initialisations=2",
    "evaluation.workers=2",
    "protocol.spheres=[1, 2]",
    # The paper's 21 frames per sweep (1 mm apart): at 2 mm (11 frames) a slice 0.8 mm
    # thick is under-sampled, the cap shows in one or two frames and its elevation is a
    # coin toss between them, which decides a single-marker fold by ± 0.3 mm.
    "imaging.pixel_spacing_mm=[0.2, 0.2]",
    "imaging.width_mm=30",
    "imaging.depth_mm=35",
    "localization.refinement_passes=1",
    # The tool's recommended practice on the paper's (hard) rig: sub-voxel centres and
    # the speed of sound corrected; every other error source as paper.yaml sets it.
    "localization.method=refined",
    "imaging.sound_speed_correction=true",
]


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "run"
    args = ["run", str(ROOT / "scenarios" / "paper.yaml"), "--out", str(out)]
    args += ["--save-dataset", str(out.parent / "datasets")]
    for o in SMALL:
        args += ["--set", o]
    scratch = out.parent / "tmp"
    scratch.mkdir()
    r = uscal(*args, env={"TMPDIR": str(scratch)})
    assert r.returncode == 0, r.stderr
    # The re-calibration scan's frames went through a scratch directory: removed.
    assert not any(scratch.iterdir()), list(scratch.iterdir())
    return out, json.loads((out / "metrics.json").read_text()), r.stdout


@pytest.mark.slow
def test_tables_are_written_and_printed(small_run):
    out, _, stdout = small_run
    md = (out / "tables.md").read_text()
    assert "Table I. Single-marker" in md and "Table II. Three-marker" in md
    assert "| Tool prec. | MAE ± SD |" in md
    assert (out / "tables.csv").read_text().startswith("table,metric,set,mae_mm")
    assert "Table I" in stdout and "against ground truth" in stdout


@pytest.mark.slow
def test_evaluation_metrics_have_the_papers_structure(small_run):
    _, m, _ = small_run
    ev = m["evaluation"]
    assert set(ev["single"]) == {"tool_precision_mm", "sphere_precision_mm", "sphere_accuracy_mm"}
    assert set(ev["three"]) == {"sphere_precision_mm", "sphere_accuracy_mm"}
    for kind in ("single", "three"):
        for by_set in ev[kind].values():
            assert set(by_set) == {"A", "B", "overall"}
            for v in by_set.values():
                assert {"mae", "sd", "rmse"} <= set(v)
    # Two spheres: two folds of each kind per set; the tool: one sample per vertex.
    assert ev["single"]["sphere_accuracy_mm"]["A"]["n"] == 2
    assert ev["single"]["sphere_accuracy_mm"]["overall"]["n"] == 4
    assert ev["single"]["tool_precision_mm"]["A"]["n"] == 4
    assert len(ev["folds"]) == 8


@pytest.mark.slow
def test_evaluation_against_ground_truth(small_run):
    _, m, _ = small_run
    ev = m["evaluation"]
    # Contact noise 0.3 mm per axis and ≈ 0.1 mm of stylus bending: six touches scatter
    # ≈ 0.45 mm about their centroid.
    assert 0.2 < ev["single"]["tool_precision_mm"]["overall"]["mae"] < 0.8
    assert ev["single"]["sphere_precision_mm"]["overall"]["mae"] < 0.8
    for name, k in m["kinematics"]["datasets"].items():
        # The refined model is far closer to the true arm than the factory one.
        assert k["true_error"]["refined_rms"] < k["true_error"]["nominal_rms"] / 3, name
    for f in ev["folds"]:
        assert f["true"]["image_mm"] < 1.0, f["fold"]
        assert f["true"]["accuracy_true_mm"] < 1.0, f["fold"]
    single = m["calibration"]["single"]
    assert single["true_error"]["image_mm"] < 1.0
    assert m["timing_s"]["workers"] == 2
    # The rig's own mount error paper.yaml declares is in the folds' bounds: each at
    # least its own 95 % quantile over the image (a whole translation of T_ee_us).
    declared = load_scenario(ROOT / "scenarios" / "paper.yaml", check_reach=False)
    sigma = declared.calibration.mount_error_mm
    assert sigma > 0
    assert single["uncertainty"]["declared"]["mount_sigma_mm"] == pytest.approx(sigma)
    assert all(f["bound95"]["image_mm"] >= 2.8 * sigma for f in ev["folds"])


def test_each_dataset_puts_the_phantom_somewhere_new():
    s = load_scenario(ROOT / "scenarios" / "paper.yaml", check_reach=False)
    first, second = dataset_scenario(s, 0), dataset_scenario(s, 1)
    assert first.phantom == s.phantom
    shift = np.subtract(second.phantom.position_mm, first.phantom.position_mm)
    assert 0 < np.abs(shift[:2]).max() <= s.evaluation.placement_shift_mm
    turn = second.phantom.rotation_deg[2] - first.phantom.rotation_deg[2]
    assert 0 < abs(turn) <= s.evaluation.placement_rotation_deg


@pytest.mark.slow
def test_reconstruction_table_iii_and_heatmaps(small_run):
    """Table III: cone and prism, single- and three-marker, per set and pooled, in
    metrics.json, tables.md/.csv and the heatmap figure; sane against the truth."""
    out, m, stdout = small_run
    rec = m["reconstruction"]
    for kind in ("cone", "prism"):
        for method in ("single", "three"):
            by_set = rec[kind][method]
            assert set(by_set) == {"A", "B", "overall"}
            for s, v in by_set.items():
                assert {"mae", "sd", "rmse", "max", "n", "without_icp"} <= set(v), (kind, s)
                assert 0 < v["mae"] <= v["rmse"] <= v["max"]
                # Sub-millimetre shape consistency, as in the paper.
                assert v["mae"] < 1.0, (kind, method, s, v)
                # ICP can only bring the points closer than the true placement does (it
                # minimises the squared distances of a subset: allow a hair).
                assert v["rmse"] <= v["without_icp"]["rmse"] + 0.02, (kind, method, s)
            assert by_set["overall"]["n"] == by_set["A"]["n"] + by_set["B"]["n"]
        assert rec[kind]["n_sweeps"] == 45
    for key, err in rec["recalibration"]["true_error"].items():
        assert err["image_mm"] < 1.0, key
    md = (out / "tables.md").read_text()
    assert "Table III. Single- and three-marker point-to-surface errors after ICP" in md
    assert "| Cone | Overall |" in md and "| Triangular prism | A |" in md
    rows = [r for r in (out / "tables.csv").read_text().splitlines() if r.startswith("recon")]
    # 2 phantoms × 2 methods × (after ICP, without ICP) × (A, B, overall)
    assert len(rows) == 24
    assert "Table III" in stdout
    png = out / "figures" / "reconstruction_heatmaps.png"
    from matplotlib.image import imread

    img = imread(png)
    assert img.shape[0] > 400 and img.shape[1] > 1000  # 2 rows × 4 panels
    assert img[..., :3].std() > 0.05  # not blank


@pytest.mark.slow
def test_recording_holds_every_session_and_the_reconstruction(small_run):
    out, m, _ = small_run
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no parts
    rec = Recording(out / "recording.rrd")
    for session in ("A", "B", "cone", "prism"):
        assert rec.rows(f"/{session}/bmode/image") > 0, session
        assert f"/{session}/world/scene" in {e.rsplit("/", 1)[0] for e in rec.static}
    # Sphere sessions: sections and every fold's convergence; scans: boundary samples.
    assert rec.rows("/A/bmode/section/detected") == rec.rows("/A/bmode/image")
    folds = {e.split("/folds/")[1].rsplit("/", 1)[0] for e in rec.timed if "/folds/" in e}
    assert len(folds) == len([f for f in m["evaluation"]["folds"] if f["dataset"] == "A"])
    assert rec.rows("/cone/bmode/boundary") == rec.rows("/cone/bmode/image")
    # The touches, and the registered points with their errors as colours.
    assert len(rec.values("/A/world/touches", "Points3D:positions", static=True)[0]) > 0
    for kind in ("cone", "prism"):
        for method in ("single", "three"):
            for s in ("A", "B"):
                entity = f"/reconstruction/{kind}/{method}/{s}"
                pts = rec.values(entity, "Points3D:positions", static=True)[0]
                colours = rec.values(entity, "Points3D:colors", static=True)[0]
                n = m["reconstruction"][kind][method][s]["n"]
                assert len(pts) == len(colours) == min(n, 50_000)


@pytest.mark.slow
def test_report_carries_the_papers_tables_and_the_refined_dh_model(small_run):
    out, m, _ = small_run
    md = (out / "report.md").read_text(encoding="utf-8")
    for title in ("Table I.", "Table II.", "Table III.", "Against the twin's ground truth"):
        assert title in md, title
    nominal = m["kinematics"]["datasets"]["A"]["true_error"]["nominal_rms"]
    assert f"| A | {nominal:.2f} |" in md
    assert "](figures/reconstruction_heatmaps.png)" in md
    assert (out / "figures" / "reconstruction_heatmaps.png").is_file()
    doc = yaml.safe_load((out / "calibration.yaml").read_text(encoding="utf-8"))
    assert doc["dh_table"]["source"].startswith("refined from the touches of datasets B")
    assert np.allclose(doc["T_ee_us"]["matrix_m"], m["calibration"]["three"]["T_ee_us"])


@pytest.mark.slow
def test_saved_datasets_evaluate_offline_as_in_the_run(small_run, tmp_path):
    """Each dataset is saved with its touches; `uscal calibrate A --dh-from B` repeats the
    run's leave-one-dataset-out evaluation of A from the files alone: the same folds give
    the same precision and accuracy against the touch reference."""
    out, m, _ = small_run
    datasets = out.parent / "datasets"
    assert sorted(p.name for p in datasets.iterdir()) == ["A", "B"]
    dest = tmp_path / "A-cal"
    args = ["calibrate", str(datasets / "A"), "--dh-from", str(datasets / "B"), "--out", str(dest)]
    args += ["--no-rrd", "--settings", str(ROOT / "scenarios" / "paper.yaml")]
    for o in SMALL:
        args += ["--set", o]
    r = uscal(*args)
    assert r.returncode == 0, r.stderr
    got = json.loads((dest / "metrics.json").read_text())
    ev = got["evaluation"]
    assert ev["dh_from"] == "B" and ev["touches"] == len(read_dataset(datasets / "A")[0].touches)
    kin = m["kinematics"]["datasets"]["A"]
    assert ev["touch_residual_rms_mm"] == pytest.approx(kin["reference_residual_rms_mm"], abs=1e-6)
    run_folds = {f["fold"]: f for f in m["evaluation"]["folds"] if f["dataset"] == "A"}
    assert [f["fold"] for f in ev["folds"]] == list(run_folds)
    for f in ev["folds"]:
        want = run_folds[f["fold"]]["per_sphere"]
        for sphere, v in f["accuracy_mm"].items():
            assert v == pytest.approx(want[sphere]["accuracy_mm"], abs=1e-6)
            assert f["precision_mm"][sphere] == pytest.approx(
                want[sphere]["precision_mm"], abs=1e-6
            )
    doc = yaml.safe_load((dest / "calibration.yaml").read_text())
    assert "refined from the touches of B" in doc["dh_table"]["source"]
    assert "accuracy" in r.stdout and "touch reference" in r.stdout


def test_the_phantom_moves_between_touches_and_sweeps_only_when_asked():
    s = load_scenario(ROOT / "scenarios" / "paper.yaml", check_reach=False)
    still = replace(s, evaluation=replace(s.evaluation, session_shift_mm=0.0))
    for i in range(3):
        assert scan_scenario(still, i) == dataset_scenario(still, i)
    moved = replace(s, evaluation=replace(s.evaluation, session_shift_mm=0.5))
    shifts = np.array(
        [
            np.subtract(
                scan_scenario(moved, i).phantom.position_mm,
                dataset_scenario(moved, i).phantom.position_mm,
            )
            for i in range(200)
        ]
    )
    # Horizontal only (the phantom stands on the tank floor), 1 σ = 0.5 mm per axis,
    # its own stream per dataset, the same for a seed.
    assert np.all(shifts[:, 2] == 0)
    assert np.std(shifts[:, :2], axis=0) == pytest.approx([0.5, 0.5], rel=0.15)
    assert scan_scenario(moved, 1) == scan_scenario(moved, 1)
    assert scan_scenario(moved, 1) != scan_scenario(moved, 2)


@pytest.mark.slow
def test_simulations_run_beside_the_touches_with_the_same_results(small_run, tmp_path):
    """Without a recording or saved datasets the pool simulates the datasets while the
    touches are refined (the frames wait in the run's scratch directory, removed at the
    end); every figure is the same as when each dataset is one task. The reconstruction
    runs after the datasets in both arrangements (the fixture's run checks it): left out
    here, it changes none of the datasets' figures."""
    _, metrics, _ = small_run
    out = tmp_path / "run"
    args = ["run", str(ROOT / "scenarios" / "paper.yaml"), "--out", str(out), "--no-rrd"]
    for o in [*SMALL, "reconstruction.phantoms=[]"]:
        args += ["--set", o]
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    r = uscal(*args, env={"TMPDIR": str(scratch)})
    assert r.returncode == 0, r.stderr
    assert not any(scratch.iterdir()), list(scratch.iterdir())
    split = json.loads((out / "metrics.json").read_text())

    def figures(m):
        if isinstance(m, dict):
            return {
                k: figures(v)
                for k, v in m.items()
                if "timing" not in k and not k.endswith("_s") and k != "seconds"
            }
        if isinstance(m, list):
            return [figures(v) for v in m]
        return m

    assert "reconstruction" not in split
    for section in ("evaluation", "calibration", "localization"):
        assert figures(split[section]) == figures(metrics[section]), section
