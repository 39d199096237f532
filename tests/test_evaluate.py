"""The paper's evaluation protocol: fold bookkeeping, statistics, tables, retention."""

from __future__ import annotations

import csv
import io
import re

import numpy as np
import pytest

from calib.calibration.markers import robust_inliers
from calib.errors import CalibrationError
from calib.evaluation.cross_validation import (
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


def test_tables_i_to_iii_carry_the_same_figures_in_every_rendering():
    """One model of the paper's tables (``calib.evaluation.cross_validation.PaperTable``)
    rendered to Markdown (``tables.md``), HTML (the report), the console and CSV (``tables.csv``):
    every rendering carries the figures as ``metrics.json`` holds them, in the paper's
    order (rounded to 0.01 mm where shown, exact in the CSV)."""
    from rich.console import Console

    from bench.console import paper_table
    from bench.outputs.report import report_html
    from calib.evaluation.cross_validation import (
        TABLE_ROWS,
        format_table_iii_csv,
        format_table_iii_markdown,
        table_iii,
        tables_i_ii,
    )

    rng = np.random.default_rng(4)
    sets = ["A", "B", "C"]
    cols = [*sets, "overall"]

    def figures(*keys):
        return {k: float(rng.uniform(0.05, 3.0)) for k in keys} | {"n": 8}

    evaluation = {
        kind: {key: {s: figures("mae", "sd", "rmse") for s in cols} for key, _ in rows}
        for kind, rows in TABLE_ROWS.items()
    }
    recon = {
        phantom: {
            m: {
                s: figures("mae", "sd", "rmse", "max")
                | {"without_icp": figures("mae", "sd", "rmse", "max")}
                for s in cols
            }
            for m in ("single", "three")
        }
        for phantom in ("cone", "prism")
    }
    expected = []  # the figures in reading order
    for kind, rows in TABLE_ROWS.items():
        for key, _ in rows:
            by_set = evaluation[kind][key]
            expected += [by_set[s][k] for s in cols for k in ("mae", "sd")]
            expected += [by_set[s]["rmse"] for s in cols]
    for pick in (None, "without_icp"):
        for phantom in recon:
            for s in cols:
                for m in ("single", "three"):
                    v = recon[phantom][m][s]
                    v = v[pick] if pick else v
                    expected += [v[k] for k in ("mae", "sd", "rmse", "max")]

    def shown(text: str) -> list[float]:
        return [float(x) for x in re.findall(r"\d+\.\d\d\b", text)]

    markdown = format_tables_markdown(evaluation) + "\n" + format_table_iii_markdown(recon, sets)
    console = Console(record=True, width=250)
    for t in [*tables_i_ii(evaluation), *table_iii(recon, sets)]:
        console.print(paper_table(t))
    html = report_html(markdown)
    html_tables = "".join(re.findall(r"<table>.*?</table>", html, flags=re.S))  # not the CSS
    for rendering in (markdown, html_tables, console.export_text()):
        assert shown(rendering) == pytest.approx(expected, abs=0.005 + 1e-9)
    rows = list(
        csv.DictReader(
            io.StringIO(format_tables_csv(evaluation) + format_table_iii_csv(recon, sets))
        )
    )
    for r in rows:
        if r["table"] == "reconstruction":
            phantom, method = r["metric"].split("_")[:2]
            v = recon[phantom][method][r["set"]]
            v = v["without_icp"] if r["metric"].endswith("_without_icp") else v
            assert float(r["max_mm"]) == pytest.approx(v["max"], abs=1e-6)
        else:
            v = evaluation[r["table"]][r["metric"]][r["set"]]
        for k in ("mae", "sd", "rmse"):
            assert float(r[f"{k}_mm"]) == pytest.approx(v[k], abs=1e-6)
    assert len(rows) == 5 * 4 + 2 * 2 * 2 * 4
