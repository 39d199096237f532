"""What ``uscal run`` prints of the paper's experiment: Tables I and II, the same folds
against the ground truth (beyond the paper), the DH refinement, and Table III of the
reconstruction."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from rich.console import Console
from rich.table import Table

from calib.evaluate import PaperTable, table_iii, tables_i_ii

__all__ = ["paper_table", "print_evaluation", "print_reconstruction"]


def paper_table(t: PaperTable, columns: Sequence[str] | None = None) -> Table:
    """One of the paper's tables (:class:`calib.evaluate.PaperTable`) for the console;
    ``columns`` replaces its column names (shorter ones for a narrow terminal)."""
    table = Table(title=t.title)
    for i, col in enumerate(columns or t.columns):
        table.add_column(col, justify="left" if i < 2 else "right", no_wrap=i < 2)
    for row in t.rows:
        table.add_row(*row)
    return table


def print_evaluation(m: dict, console: Console) -> None:
    names = m["evaluation"]["datasets"]
    for t in tables_i_ii(m["evaluation"]):
        console.print(paper_table(t))
    kin = m["kinematics"]
    table = Table(title="against ground truth (beyond the paper)")
    for col in (
        "set",
        "kin. err nominal",
        "kin. err refined",
        "ref. err",
        "1: image",
        "1: acc",
        "3: image",
        "3: acc",
    ):
        table.add_column(col, justify="right" if col != "set" else "left")
    for n in names:
        k = kin["datasets"][n]
        folds = [f for f in m["evaluation"]["folds"] if f["dataset"] == n]

        def mean(kind: str, key: str, folds=folds) -> float:
            return float(np.mean([f["true"][key] for f in folds if f["kind"] == kind]))

        table.add_row(
            n,
            f"{k['true_error']['nominal_rms']:.2f}",
            f"{k['true_error']['refined_rms']:.3f}",
            f"{np.mean(list(k['reference_error_mm'].values())):.2f}",
            f"{mean('single', 'image_mm'):.2f}",
            f"{mean('single', 'accuracy_true_mm'):.2f}",
            f"{mean('three', 'image_mm'):.2f}",
            f"{mean('three', 'accuracy_true_mm'):.2f}",
        )
    console.print(table)
    console.print(
        "mm; kin. err: RMS error of the kinematic model at the image over the scanned "
        "configurations (after the base/flange frames touches cannot see); ref. err: touch "
        "reference centres vs true centres; image/acc: per-fold mean true image error of "
        "T_ee_us and accuracy against the true centres (1: single-, 3: three-marker)."
    )
    hidden = [k for k, v in kin["unobservable_share"].items() if v >= 0.5]
    console.print(
        "touches cannot identify (≥ half in directions they cannot see; the regulariser "
        f"keeps these at nominal): {', '.join(hidden)}"
    )
    rms = kin["rms_change_mean"]
    console.print(
        "DH change from nominal, RMS over the leave-one-out models: "
        f"θ {rms['theta_deg']:.2f}°, d {rms['d_mm']:.2f} mm, a {rms['a_mm']:.2f} mm, "
        f"α {rms['alpha_deg']:.2f}°"
    )


def print_reconstruction(m: dict, console: Console) -> None:
    names = m["evaluation"]["datasets"]
    rec = m["reconstruction"]
    kinds = [k for k in ("cone", "prism") if k in rec]
    after_icp = table_iii({k: rec[k] for k in kinds}, names)[0]
    short = ("", "set", "1: MAE±SD", "RMSE", "max", "3: MAE±SD", "RMSE", "max")
    console.print(paper_table(after_icp, short))
    console.print(
        "1: single-marker (sphere 1), 3: three-marker (spheres 1–3), re-calibrated after the "
        "remount with each set's DH model. Without ICP, through the true phantom placement "
        "(beyond the paper), overall MAE: "
        + "; ".join(
            f"{kind} {rec[kind]['single']['overall']['without_icp']['mae']:.2f} (1), "
            f"{rec[kind]['three']['overall']['without_icp']['mae']:.2f} (3)"
            for kind in kinds
        )
        + " mm."
    )
