"""The paper's evaluation protocol: fold bookkeeping, statistics, tables, retention."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from calib.calibrate import robust_inliers
from calib.errors import CalibrationError
from calib.evaluate import (
    folds,
    format_tables_csv,
    format_tables_markdown,
    sphere_metrics,
    summarize,
)

SPHERES = ["sphere_1", "sphere_2", "sphere_3", "sphere_4"]


def test_folds_are_the_papers_complementary_splits():
    fs = folds("A", SPHERES)
    single = [f for f in fs if f.kind == "single"]
    three = [f for f in fs if f.kind == "three"]
    assert len(single) == 4 and len(three) == 4
    for f in fs:
        assert f.dataset == "A"
        assert set(f.train).isdisjoint(f.test)
        assert sorted(f.train + f.test) == SPHERES
    assert all(len(f.train) == 1 and len(f.test) == 3 for f in single)
    assert all(len(f.train) == 3 and len(f.test) == 1 for f in three)
    # Every sphere trains one single-marker fold and is held out of one three-marker fold.
    assert sorted(f.train[0] for f in single) == SPHERES
    assert sorted(f.test[0] for f in three) == SPHERES
    # Split i of each kind is complementary: single trains on what three holds out.
    for s, t in zip(single, three, strict=True):
        assert s.train == t.test and s.test == t.train
    assert len({f.name for f in fs}) == 8


def test_folds_need_two_spheres():
    with pytest.raises(CalibrationError, match="at least 2 spheres"):
        folds("A", ["sphere_1"])


def test_summary_statistics_match_the_papers_definitions():
    samples = {"A": [1.0, 2.0, 3.0, 4.0], "B": [0.5, 0.5, 0.5, 0.5], "C": [2.0, 2.0, 4.0, 4.0]}
    s = summarize(samples)
    assert s["A"].mae == pytest.approx(2.5)
    assert s["A"].sd == pytest.approx(np.std([1, 2, 3, 4], ddof=1))  # sample SD
    assert s["A"].rmse == pytest.approx(np.sqrt(np.mean(np.square([1, 2, 3, 4]))))
    assert s["B"].sd == pytest.approx(0.0)
    pooled = [v for vs in samples.values() for v in vs]
    assert s["overall"].n == 12
    assert s["overall"].mae == pytest.approx(np.mean(pooled))
    assert s["overall"].rmse == pytest.approx(np.sqrt(np.mean(np.square(pooled))))
    assert list(s) == ["A", "B", "C", "overall"]


def test_tables_in_the_papers_layout():
    tool = summarize({"A": [0.6, 0.6], "B": [0.5, 0.55]})
    sphere = summarize({"A": [0.7, 0.72], "B": [0.9, 0.88]})
    tables = {
        "single": {
            "tool_precision_mm": tool,
            "sphere_precision_mm": sphere,
            "sphere_accuracy_mm": sphere,
        },
        "three": {"sphere_precision_mm": sphere, "sphere_accuracy_mm": sphere},
    }
    md = format_tables_markdown(tables)
    assert "Table I. Single-marker calibration errors (mm)." in md
    assert "Table II. Three-marker calibration errors (mm)." in md
    assert "| Metric | Statistic | A | B | Overall |" in md
    assert f"| Tool prec. | MAE ± SD | 0.60 ± {0.0:.2f} |" in md
    assert md.count("| RMSE |") == 5
    rows = list(csv.DictReader(io.StringIO(format_tables_csv(tables))))
    assert len(rows) == (3 + 2) * 3
    r = next(
        r
        for r in rows
        if r["table"] == "single" and r["metric"] == "tool_precision_mm" and r["set"] == "B"
    )
    assert float(r["mae_mm"]) == pytest.approx(0.525)
    assert int(r["n"]) == 2


def test_sphere_metrics_precision_and_accuracy():
    P = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]]) * 1e-3
    ref = np.array([0.0, 0.0, 2e-3])
    precision, accuracy = sphere_metrics(P, ref)
    assert precision == pytest.approx(1.0)
    assert accuracy == pytest.approx(2.0)


def test_robust_inliers_drop_false_detections(rng):
    P = rng.normal(0, 0.1e-3, (45, 3))
    P[[3, 17]] += np.array([0.0, 20e-3, 5e-3])  # two false detections 20 mm away
    keep = robust_inliers(P)
    assert not keep[3] and not keep[17]
    assert keep.sum() == 43
