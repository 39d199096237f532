"""What ``uscal run`` prints of the paper's experiment: Tables I and II, the same folds
against the ground truth (beyond the paper), the DH refinement, and Table III of the
reconstruction."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from rich.console import Console
from rich.table import Table as RichTable

from calib.evaluation.cross_validation import PaperTable

from ..summaries import PaperEvaluation, Reconstruction
from ..tables import Table
from .tables import print_table, rich_table

__all__ = ["paper_table", "print_evaluation", "print_reconstruction"]


def paper_table(t: PaperTable, columns: Sequence[str] | None = None) -> RichTable:
    """One of the paper's tables (:class:`calib.evaluation.cross_validation.PaperTable`)
    for the console; ``columns`` replaces its column names (shorter ones for a narrow
    terminal)."""
    return rich_table(Table.from_paper(t, columns))


def print_evaluation(ev: PaperEvaluation, console: Console) -> None:
    for t in ev.tables:
        console.print(paper_table(t))
    note = (
        "mm; kin. err: RMS error of the kinematic model at the image over the scanned "
        "configurations (after the base/flange frames touches cannot see); ref. err: touch "
        "reference centres vs true centres; image/acc: per-fold mean true image error of "
        "T_ee_us and accuracy against the true centres (1: single-, 3: three-marker); "
        "accepted: folds the verdict accepted."
    )
    print_table(replace(ev.truth_table(), notes=(note,)), console)
    hidden = [k for k, v in ev.unobservable_share.items() if v >= 0.5]
    console.print(
        "touches cannot identify (≥ half in directions they cannot see; the regulariser "
        f"keeps these at nominal): {', '.join(hidden)}"
    )
    rms = ev.rms_change
    console.print(
        "DH change from nominal, RMS over the leave-one-out models: "
        f"θ {rms.theta_deg:.2f}°, d {rms.d_mm:.2f} mm, a {rms.a_mm:.2f} mm, "
        f"α {rms.alpha_deg:.2f}°"
    )


def print_reconstruction(rec: Reconstruction, console: Console) -> None:
    after_icp = rec.tables[0]
    short = ("", "set", "1: MAE±SD", "RMSE", "max", "3: MAE±SD", "RMSE", "max")
    console.print(paper_table(after_icp, short))

    console.print(
        "1: single-marker (sphere 1), 3: three-marker (spheres 1–3), re-calibrated after the "
        "remount with each set's DH model. Without ICP, through the true phantom placement "
        "(beyond the paper), overall MAE: "
        + "; ".join(
            f"{p.kind} {p.without_icp_mae('single'):.2f} (1), {p.without_icp_mae('three'):.2f} (3)"
            for p in rec.phantoms
        )
        + " mm."
    )
