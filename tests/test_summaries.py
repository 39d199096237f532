"""The typed read of ``metrics.json`` (:mod:`bench.summaries`) and the table model
(:mod:`bench.tables`): built from a real quick run's metrics (and from metrics with their
optional parts left out), every table's rows are the figures of the metrics; a table
renders alike to Markdown, CSV, HTML and the console."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from rich.console import Console

from bench.console import print_run, rich_table
from bench.jobs.budget import BudgetOutcome
from bench.jobs.sweep import SweepPoint
from bench.summaries import (
    PaperEvaluation,
    Reconstruction,
    RecordedSummary,
    RunSummary,
    read_metrics,
)
from bench.tables import Column, Table, left, right
from calib.evaluation.cross_validation import TABLE_ROWS, PaperTable


def _printed(print_fn, summary) -> str:
    console = Console(record=True, width=200)
    print_fn(summary, console)
    return console.export_text()


# ----------------------------------------------------------------------------- the table


def test_a_table_renders_to_markdown_csv_html_and_the_console():
    t = Table(
        (Column("fold", code=True), *left("sphere"), *right("mm", "")),
        (("A/single", "sphere_2", "0.324", ""), ("A/three", "a|b <c>", "1.000", "x")),
        "folds",
        ("mm, against the touches.",),
    )
    assert t.markdown() == (
        "| fold | sphere | mm | |\n"
        "|---|---|---:|---:|\n"
        "| `A/single` | sphere_2 | 0.324 | |\n"
        "| `A/three` | a|b <c> | 1.000 | x |\n"
        "\n"
        "mm, against the touches."
    )
    assert t.csv() == "fold,sphere,mm,\nA/single,sphere_2,0.324,\nA/three,a|b <c>,1.000,x\n"
    page = t.html()
    assert page.startswith("<table>\n<caption>folds</caption>\n<thead>\n<tr>\n<th>fold</th>\n")
    assert '<th style="text-align: right">mm</th>' in page
    assert "<td><code>A/single</code></td>" in page
    assert "<td>a|b &lt;c&gt;</td>" in page  # escaped
    assert page.endswith("</table>\n<p>mm, against the touches.</p>\n")
    console = Console(record=True, width=100)
    console.print(rich_table(t))
    text = console.export_text()
    assert text.splitlines()[0].strip() == "folds"
    assert "│ A/single │ sphere_2 │ 0.324 │   │" in text
    with pytest.raises(ValueError, match="a row of 2 cells in a table of 4"):
        Table(t.columns, (("a", "b"),))


def test_an_unnamed_header_is_one_space_per_cell():
    """The report's 4 × 4 matrix: columns without names."""
    t = Table((Column("", "right"),) * 2, (("1.0000", "0.0000"),))
    assert t.markdown() == "| | |\n|---:|---:|\n| 1.0000 | 0.0000 |"


def test_a_paper_table_keeps_its_labels_left_and_unwrapped():
    p = PaperTable("Table I.", ("Metric", "Statistic", "A"), (("Tool prec.", "RMSE", "0.43"),))
    t = Table.from_paper(p, ("", "stat", "A"))
    assert [(c.name, c.align, c.no_wrap) for c in t.columns] == [
        ("", "left", True),
        ("stat", "left", True),
        ("A", "right", False),
    ]
    assert t.rows == p.rows and t.title == p.title


# ----------------------------------------------------------------------------- uscal run


def test_a_quick_runs_metrics_give_its_tables(quick_run):
    """The quick run (one sphere: single-marker only): its summary, the console table of
    the calibration against the truth and what ``uscal run`` printed of it."""
    out, _, m, _ = quick_run
    s = read_metrics(json.loads((out / "metrics.json").read_text()))
    assert isinstance(s, RunSummary)
    assert s.evaluation is None and s.reconstruction is None
    loc = m["localization"]
    assert (s.localization.n_sweeps, s.localization.n_rejected) == (
        loc["n_sweeps"],
        loc["n_rejected"],
    )
    assert s.localization.error_mm.median == loc["error_mm"]["median"]
    assert s.calibrations.three is None
    assert [c.method for c in s.calibrations] == ["single"]
    assert s.calibrations.chosen is s.calibrations.single
    c, single = s.calibrations.single, m["calibration"]["single"]
    np.testing.assert_array_equal(c.T_ee_us, np.array(single["T_ee_us"]))
    assert c.bound95.image_mm == single["bound95"]["image_mm"]
    assert c.uncertainty.views == single["uncertainty"]["views"]
    truth = single.get("true_error_equivalent", single["true_error"])  # as the run checks
    assert c.truth_for_bound.image_mm == truth["image_mm"]
    e = single["true_error"]
    expected = (
        "single",
        *(f"{e[k]:.3f}" for k in ("rotation_deg", "translation_mm", "image_mm")),
        f"{single['precision_mm']:.3f}",
        f"{single['accuracy_mm']:.3f}",
        str(single["n_retained"]),
        str(single["iterations"]),
    )
    table = s.calibration_table()
    assert table.rows == (expected,)
    assert [col.name for col in table.columns][:2] == ["method", "rot °"]
    stdout = (out.parent / "stdout.txt").read_text(encoding="utf-8")
    printed = next(line for line in stdout.splitlines() if line.startswith("│ single "))
    assert tuple(cell.strip() for cell in printed.strip("│").split("│")) == expected
    assert f"rotation {single['bound95']['rotation_deg']:.3f}°" in stdout
    assert f"total {m['timing_s']['total']:.1f} s" in stdout


def test_optional_parts_of_a_run_leave_their_rows_and_lines_out(quick_run):
    """Without bounds, the equivalent mount or the localization error the summary is
    built all the same, and what shows them says nothing of them; a second method adds
    its row; the paper's ``workers`` shows in the timing line."""
    _, _, m, _ = quick_run
    m = copy.deepcopy(m)
    for key in ("bound95", "uncertainty", "true_error_equivalent"):
        m["calibration"]["single"].pop(key, None)
    m["calibration"]["three"] = copy.deepcopy(m["calibration"]["single"])
    m["timing_s"]["workers"] = 2
    s = RunSummary.from_metrics(m)
    single = s.calibrations.single
    assert single.bound95 is None and single.uncertainty.views is None
    assert single.truth_for_bound is single.true_error
    assert [r[0] for r in s.calibration_table().rows] == ["single", "three"]
    assert s.calibrations.chosen is s.calibrations.three
    text = _printed(print_run, s)
    assert "95 % error bounds" not in text
    assert "(summed over 2 workers)" in text
    del m["localization"]["error_mm"]
    del m["calibration"]["single"]
    s = RunSummary.from_metrics(m)
    assert s.localization.error_mm is None
    assert [r[0] for r in s.calibration_table().rows] == ["three"]
    assert "error vs truth" not in _printed(print_run, s)


# ----------------------------------------------------------------------------- uscal calibrate


def _recorded_metrics(m: dict) -> dict:
    """A recorded dataset's metrics made from a quick run's (no truth), with touches
    and folds."""
    single = {
        k: v
        for k, v in m["calibration"]["single"].items()
        if k not in ("true_error", "true_error_equivalent", "accuracy_mm")
    }
    fold = {
        "fold": "sim/single/sphere_1",
        "kind": "single",
        "precision_mm": {"sphere_2": 0.31, "sphere_3": 0.29},
        "accuracy_mm": {"sphere_2": 1.2, "sphere_3": 0.9},
    }
    spread = {"mean": 1.05, "sd": 0.15}
    return {
        "dataset": {
            "path": "/data/sim",
            "name": "sim",
            "source": "twin",
            "n_sweeps": 45,
            "n_frames": 945,
            "targets": ["sphere_1", "sphere_2", "sphere_3"],
            "n_touches": 24,
            "temperature_c": 20.0,
            "axial_scale": 0.96,
        },
        "image": {"width_px": 151, "height_px": 176, "spacing_m": [2e-4, 2e-4]},
        "localization": {k: m["localization"][k] for k in ("method", "n_sweeps", "n_rejected")},
        "calibration": {"single": single},
        "evaluation": {
            "dh_from": "sim",
            "touches": 24,
            "touch_residual_rms_mm": 0.48,
            "folds": [fold],
            "summary": {"single": {"accuracy_mm": spread, "precision_mm": spread}},
        },
        "dh_table_refined": np.zeros((6, 4)).tolist(),
    }


def test_a_recorded_datasets_metrics_give_its_tables(quick_run):
    from bench.console import print_recorded

    _, _, m, _ = quick_run
    r = _recorded_metrics(m)
    s = read_metrics(r)
    assert isinstance(s, RecordedSummary)
    c = s.calibrations.single
    assert c.true_error is None and c.accuracy_mm is None
    T = np.array(r["calibration"]["single"]["T_ee_us"])
    b = r["calibration"]["single"]["bound95"]
    assert s.calibration_table().rows == (
        (
            "single",
            *(f"{v:.2f}" for v in T[:3, 3] * 1e3),
            f"{b['rotation_deg']:.3f}",
            f"{b['translation_mm']:.3f}",
            f"{c.precision_mm:.3f}",
            str(c.n_retained),
        ),
    )
    assert s.image.spacing_m == (2e-4, 2e-4) and s.dh_table_refined.shape == (6, 4)
    ev = s.touches
    assert ev.folds_table().rows == (
        ("sim/single/sphere_1", "sphere_2", "0.310", "1.200"),
        ("sim/single/sphere_1", "sphere_3", "0.290", "0.900"),
    )
    assert "| `sim/single/sphere_1` | sphere_2 | 0.310 | 1.200 |" in ev.folds_table().markdown()
    text = _printed(print_recorded, s)
    assert "touches: 24, DH refined from sim" in text
    assert "single-marker folds: accuracy 1.050 ± 0.150 mm" in text
    assert "single vs three" not in text

    # Without bounds, touches or the second method: a "-" for the bounds, no touch lines.
    del r["calibration"]["single"]["bound95"], r["evaluation"], r["dh_table_refined"]
    s = RecordedSummary.from_metrics(r)
    assert s.calibration_table().rows[0][4:6] == ("-", "-")
    assert s.touches is None and s.dh_table_refined is None and s.single_vs_three is None
    assert "touches:" not in _printed(print_recorded, s)


# ----------------------------------------------------------------------------- the paper


def _paper_metrics(sets=("A", "B")) -> dict:
    """The paper experiment's metrics.json sections the summaries read, figures
    made up (as calib.evaluation.cross_validation and bench.jobs.paper_metrics shape them)."""
    rng = np.random.default_rng(7)
    cols = [*sets, "overall"]

    def summary():
        return {"mae": rng.uniform(0.1, 2), "sd": 0.1, "rmse": rng.uniform(0.1, 2), "n": 4}

    def stats():
        return {"mae": rng.uniform(0.1, 1), "sd": 0.2, "rmse": 0.5, "max": 3.0}

    folds = [
        {
            "fold": f"{s}/{kind}/{i}",
            "dataset": s,
            "kind": kind,
            "true": {"image_mm": 1.0 + i, "accuracy_true_mm": 0.5 + i},
            "verdict": {"status": "accepted" if i == 0 else "suspect", "reasons": []},
        }
        for s in sets
        for kind in ("single", "three")
        for i in range(2)
        if not (s == "B" and kind == "three")  # B: no three-marker folds
    ]
    evaluation = {"datasets": list(sets), "folds": folds}
    evaluation |= {
        kind: {key: {c: summary() for c in cols} for key, _ in rows}
        for kind, rows in TABLE_ROWS.items()
    }
    kin = {
        s: {
            "true_error": {"nominal_rms": 2.1, "refined_rms": 0.2},
            "reference_error_mm": {"v1": 0.5, "v2": 0.7},
        }
        for s in sets
    }
    recon = {
        kind: {
            m: {c: stats() | {"without_icp": stats()} for c in cols} for m in ("single", "three")
        }
        | {"n_sweeps": 45}
        for kind in ("cone", "prism")
    }
    recon["recalibration"] = {
        "true_error": {
            "A/single": {"rotation_deg": 1.0, "translation_mm": 1.0, "image_mm": 0.8},
            "B/three": {"rotation_deg": 1.0, "translation_mm": 1.0, "image_mm": 1.3},
        }
    }
    return {
        "evaluation": evaluation,
        "kinematics": {
            "datasets": kin,
            "unobservable_share": {"Δθ1": 0.9, "Δd2": 0.1},
            "rms_change_mean": {"theta_deg": 1.4, "d_mm": 0.15, "a_mm": 1.3, "alpha_deg": 0.3},
        },
        "reconstruction": recon,
    }


def test_the_paper_evaluation_gives_its_tables():
    from bench.console import print_evaluation, print_reconstruction

    m = _paper_metrics()
    ev = PaperEvaluation.from_metrics(m)
    assert ev.datasets == ("A", "B")
    assert [t.title[:9] for t in ev.tables] == ["Table I. ", "Table II."]
    # A: both kinds of folds (means of 1, 2 and of 0.5, 1.5); B: no three-marker folds.
    assert ev.truth_table().rows == (
        ("A", "2.10", "0.200", "0.60", "1.50", "1.00", "1.50", "1.00", "1 / 2", "1 / 2"),
        ("B", "2.10", "0.200", "0.60", "1.50", "1.00", "–", "–", "1 / 2", "–"),
    )
    text = _printed(print_evaluation, ev)
    assert "against ground truth (beyond the paper)" in text
    assert "nominal): Δθ1\n" in text
    assert "θ 1.40°, d 0.15 mm, a 1.30 mm, α 0.30°" in text

    rec = Reconstruction.from_metrics(m)
    assert [p.kind for p in rec.phantoms] == ["cone", "prism"]
    assert rec.worst_recalibration_image_mm == 1.3
    cone = m["reconstruction"]["cone"]
    assert (
        rec.phantoms[0].without_icp_mae("three") == cone["three"]["overall"]["without_icp"]["mae"]
    )
    after_icp = rec.tables[0]
    assert len(after_icp.rows) == 2 * 3  # two phantoms × (A, B, overall)
    assert after_icp.rows[0][3] == f"{cone['single']['A']['rmse']:.2f}"
    text = _printed(print_reconstruction, rec)
    assert f"cone {cone['single']['overall']['without_icp']['mae']:.2f} (1)" in text

    # A run that scanned one phantom and scored no re-calibration.
    del m["reconstruction"]["prism"], m["reconstruction"]["recalibration"]
    rec = Reconstruction.from_metrics(m)
    assert [p.kind for p in rec.phantoms] == ["cone"]
    assert rec.worst_recalibration_image_mm is None
    assert len(rec.tables[0].rows) == 3


# ----------------------------------------------------------------------------- sweep, budget


def test_grid_documents_read_as_points_and_outcomes():
    row = {
        "seed": 0,
        "method": "refined",
        "localization_median_error_mm": 0.1,
        "rejected_fraction": 0.0,
        "localization_max_error_mm": 0.3,
        "false_acceptances": 1,
        "sweeps": 45,
    }
    ok = SweepPoint.from_document({"overrides": [["imaging.gain_db", 0]], "seed": 0, "rows": [row]})
    assert ok.override("imaging.gain_db") == 0 and ok.override("seed") is None
    assert ok.rows[0].figure("false_acceptances") == 1
    assert ok.rows[0].figure("calibration_image_mm") is None  # no calibrate stage
    failed = SweepPoint.from_document(
        {"overrides": [["imaging.gain_db", 5]], "seed": 1, "error": "E: no", "traceback": ""}
    )
    assert failed.rows == () and failed.error == "E: no"
    run = BudgetOutcome.from_document({"figures": {"image_mm": 0.2}, "seconds": 3.0})
    assert run.figure("image_mm") == 0.2 and np.isnan(run.figure("cone_mae_mm"))
    assert np.isnan(BudgetOutcome.from_document({"error": "E: no"}).figure("image_mm"))
