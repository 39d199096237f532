"""The rerun recording of `uscal run`, read back with rerun's reader: entity paths,
counts, and values checked against metrics.json and the ground truth it overlays."""

from __future__ import annotations

import numpy as np
import pytest

from bench.recording.options import frames_per_target, sweeps_to_log


def test_recording_goes_where_asked_and_nothing_else_is_left(quick_run):
    out, rrd, m, _ = quick_run
    assert rrd.is_file() and rrd.stat().st_size > 0
    assert not (out / "recording.rrd").exists()
    assert sorted(p.name for p in rrd.parent.iterdir()) == ["quick.rrd"]  # no part files
    assert m["recording"]["frames"] == 63


def test_scene_robot_and_frames_are_logged(quick_run):
    *_, rec = quick_run
    assert rec.blueprints, "the recording carries a blueprint"
    assert "/run/world/scene/sphere_1" in rec.static
    assert "/run/world/scene/tank_floor" in rec.static
    robot = [e for e in rec.entities if e.startswith("/run/world/robot/")]
    assert len(robot) >= 7  # six links' segments and the probe
    for e in robot:
        assert rec.rows(e) == 63  # one pose per logged frame
    # 63 frames = 3 whole sweeps of 21, spread over the 45.
    assert rec.rows("/run/bmode/image") == 63
    assert rec.rows("/run/bmode/section/detected") == 63
    assert rec.rows("/run/world/image/estimated") == 63
    frames = rec.values("/run/bmode/image", "frame", index="frame")
    assert frames == list(range(63))


def test_convergence_matches_the_metrics(quick_run):
    _, _, m, rec = quick_run
    history = m["calibration"]["single"]["history"]
    loss = rec.values("/run/calibration/single/loss_mm2", "Scalars:scalars", index="iteration")
    assert np.allclose([v[0] for v in loss], [h["cost_mm2"] for h in history])
    residuals = rec.values("/run/calibration/single/residuals_mm", "BarChart:values")
    assert len(residuals) == 1
    # One residual per accepted sweep; localized centres likewise, in the base frame.
    centres = rec.values("/run/world/centres/single", "Points3D:positions", static=True)[0]
    n_accepted = m["localization"]["n_sweeps"] - m["localization"]["n_rejected"]
    assert len(centres) == n_accepted
    spread = np.linalg.norm(np.array(centres) - np.mean(centres, axis=0), axis=1)
    assert np.median(spread) < 1e-3  # metres: every sweep finds the same sphere


def test_radial_profile_crossings_bracket_the_radius(quick_run):
    *_, rec = quick_run
    pts = rec.values("/run/localization/single/sphere_1/crossings", "Points2D:positions")[0]
    inner, rise, fall = (p[0] for p in pts)  # mm
    radius_mm = 5.0  # quick.yaml's spheres (the CAD radius)
    assert 0 < inner < rise < radius_mm < fall < 1.5 * radius_mm


def test_detected_sections_lie_on_the_true_ones(quick_run):
    """Red (found) and green (true) contours come from different paths — the estimated
    T_ee_us and the sweep's stacking vs the twin's true poses — and must agree."""
    *_, rec = quick_run
    det = rec.values("/run/bmode/section/detected", "LineStrips2D:strips", index="frame")
    true = rec.values("/run/bmode/section/true", "LineStrips2D:strips", index="frame")
    both = 0
    for d, t in zip(det, true, strict=True):
        if not d or not t:
            continue
        both += 1
        d, t = np.array(d[0]), np.array(t[0])
        pixel_mm = 0.2
        assert np.linalg.norm(d.mean(axis=0) - t.mean(axis=0)) * pixel_mm < 0.6
        r_d = np.linalg.norm(d - d.mean(axis=0), axis=1).mean()
        r_t = np.linalg.norm(t - t.mean(axis=0), axis=1).mean()
        assert abs(r_d - r_t) * pixel_mm < 0.6
    assert both >= 30


@pytest.mark.parametrize(
    ("n", "per", "limit", "expected"),
    [(45, 21, 63, [0, 22, 44]), (45, 21, 0, []), (3, 21, 10_000, [0, 1, 2]), (0, 21, 50, [])],
)
def test_sweeps_to_log_spreads_whole_sweeps(n, per, limit, expected):
    assert sweeps_to_log(n, per, limit) == expected


@pytest.mark.parametrize(
    ("targets", "limit", "expected"),
    [
        # Four spheres, 60 frames: two whole sweeps (an even split in frames gave none).
        (["s1", "s2", "s3", "s4"], 60, [21, 21, 0, 0]),
        (["s1", "s2", "s3", "s4"], 420, [105, 105, 105, 105]),
        (["s1", "s2", "s3"], 420, [147, 147, 126]),
        (["s1"], 20, [0]),
        ([], 420, []),
    ],
)
def test_a_sessions_frames_are_dealt_as_whole_sweeps_over_its_targets(targets, limit, expected):
    got = frames_per_target(targets, 21, limit)
    assert list(got) == targets and list(got.values()) == expected
    assert sum(got.values()) <= limit
