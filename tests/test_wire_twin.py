"""The twin's single-wire phantom (scenarios/wire.yaml: one 0.3 mm nylon wire between the
N-wire phantom's plates, drawn by sim_us as a line target) calibrated end to end with
uscal's own threshold-free dot detection, the wire's pose unknown, against the twin's
ground truth: `uscal run`, the dataset it saves through `uscal calibrate` and `uscal validate`; with
every error source off as the sanity case."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from .rrd import Recording
from .test_cli import uscal, uscal_here

# Two twin runs of 945 frames (≈ 30 s each): the slow tier.
pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
WIRE = ROOT / "scenarios" / "wire.yaml"


@pytest.fixture(scope="module")
def wire_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("wire")
    r = uscal("run", str(WIRE), "--out", str(base / "run"), "--save-dataset", str(base / "data"))
    assert r.returncode == 0, r.stderr
    return base, json.loads((base / "run" / "metrics.json").read_text()), r.stdout


def test_the_twin_s_single_wire_calibrates_to_its_ground_truth(wire_run):
    _, m, stdout = wire_run
    w = m["calibration"]["wire"]
    assert m["dataset"]["target"] == "wire"
    assert m["detection"]["frames_found"] >= 0.9 * m["dataset"]["n_frames"]
    assert w["converged"] and m["dataset"]["phantom_pose"].startswith("estimated (4 of")
    e = w["true_error"]
    assert e["rotation_deg"] < 0.5 and e["translation_mm"] < 0.5 and e["image_mm"] < 0.3
    assert all(w["bound_covers"].values()), (e, w["bound95"])
    assert "against the twin's truth" in stdout


def test_its_dataset_calibrates_as_the_run_did_and_validates_to_the_same_error(wire_run, capsys):
    base, m, _ = wire_run
    r = uscal_here(capsys, "calibrate", str(base / "data"), "--out", str(base / "cal"))
    assert r.returncode == 0, r.stderr
    again = json.loads((base / "cal" / "metrics.json").read_text())["calibration"]["wire"]
    np.testing.assert_allclose(again["T_ee_us"], m["calibration"]["wire"]["T_ee_us"], atol=1e-6)
    doc = (base / "cal" / "calibration.yaml").read_text()
    assert "single wire" in doc and '<Transform From="Image" To="Probe"' in doc
    r = uscal_here(
        capsys, "validate", str(base / "data"),
        "--calibration", str(base / "cal" / "calibration.yaml"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    last = re.fullmatch(r"reprojection_mm=(\S+) sd_mm=(\S+)", r.stdout.strip().splitlines()[-1])
    assert last is not None
    assert float(last.group(1)) == pytest.approx(
        again["reprojection_3d_mm"]["plus_mean"], abs=0.005
    )


def test_with_every_error_source_off_the_wire_gives_the_mount(tmp_path):
    r = uscal(
        "run", str(WIRE), "--out", str(tmp_path / "run"),
        "--set", "phantom.tolerance_position_mm=0", "--set", "protocol.teaching_error_mm=0",
        # Sweeps of 7 frames (2 mm apart): the wire's dots are in every frame.
        "--set", "protocol.frames_per_sweep=7",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    w = json.loads((tmp_path / "run" / "metrics.json").read_text())["calibration"]["wire"]
    e = w["true_error"]
    assert e["rotation_deg"] < 0.2 and e["translation_mm"] < 0.1 and e["image_mm"] < 0.1
    assert all(w["bound_covers"].values())
    assert w["verdict"]["status"] == "accepted"


def test_its_recording_shows_the_frames_the_dots_and_the_wire_where_fit_and_truth_put_it(
    wire_run,
):
    """The run's rerun recording, read back: B-mode frames, every observation through
    the answer, and the wire where the fit and the truth put it — the same line (the
    fit's wire is the truth's within a few tenths of a millimetre across it)."""
    base, m, _ = wire_run
    rec = Recording(base / "run" / "recording.rrd")
    assert rec.rows("/run/bmode/image") > 100
    observed = rec.values("/run/world/targets/observed", "Points3D:positions", static=True)
    assert len(observed[0]) == m["detection"]["points"]
    fitted = np.array(
        rec.values("/run/world/targets/fitted", "LineStrips3D:strips", static=True)[0][0]
    )
    true = np.array(rec.values("/run/world/targets/true", "LineStrips3D:strips", static=True)[0][0])
    d = (true[1] - true[0]) / np.linalg.norm(true[1] - true[0])
    for p in fitted:  # each fitted end lies on the true line
        off = (p - true[0]) - ((p - true[0]) @ d) * d
        assert np.linalg.norm(off) < 0.5e-3


def test_a_plan_chosen_for_the_wire_calibrates_it_in_a_third_of_the_time(tmp_path):
    """`uscal plan --optimize` on the single wire: sweeps about the wire (its dots in every
    frame, turned about the lateral axis no more than the protocol's tilt, which the
    wire's echo needs), chosen for the wire's two constraints per frame with the wire's
    pose and the pixel scale unknown; then `uscal run` with that plan calibrates to the
    twin's truth inside its bounds and the plan's own prediction."""
    plan = tmp_path / "plan.yaml"
    fast = ["--set", "planning.session_draws=4", "--set", "planning.spares=3"]
    r = uscal("plan", str(WIRE), "--optimize", "--sweeps", "12", "--out", str(plan), *fast)
    assert r.returncode == 0, r.stderr
    said = " ".join(r.stdout.split())
    assert "for a single-wire calibration (phantom pose and pixel scale unknown)" in said
    doc = yaml.safe_load(plan.read_text())
    sweeps = doc["targets"]["wire"]
    assert (
        list(doc["targets"]) == ["wire"] and len(sweeps) == 12 and len(doc["spares"]["wire"]) == 3
    )
    tilt = yaml.safe_load(WIRE.read_text())["protocol"]["tilt_deg"]
    assert all(abs(s["rotation_xyz_deg"][0]) <= tilt for s in sweeps + doc["spares"]["wire"])
    assert len({tuple(s["rotation_xyz_deg"]) for s in sweeps}) > 3  # turned, not one view
    predicted, paper = doc["predicted"], doc["paper_plan"]
    assert predicted["robot_time_s"] < 0.5 * paper["robot_time_s"]

    out = tmp_path / "run"
    r = uscal("run", str(WIRE), "--set", f"protocol.plan={plan}", "--out", str(out))
    assert r.returncode == 0, r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["acquisition"]["sweeps"] == 12 and m["acquisition"]["plan"] == str(plan)
    w = m["calibration"]["wire"]
    assert w["verdict"]["status"] == "accepted" and all(w["bound_covers"].values())
    # The truth within three of the plan's predicted 1 σ over the image.
    assert w["true_error"]["image_mm"] < 3 * predicted["image_mm_rms"]
    assert w["true_error"]["rotation_deg"] < 0.3
