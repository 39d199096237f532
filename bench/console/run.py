"""What ``uscal run`` prints of one acquisition: the localization, the calibrations
against the ground truth with their 95 % bounds, the timing; and the files a run or
calibration wrote."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from rich.console import Console

from ..summaries import RunSummary
from ..summaries.calibration import CalibrationSummary
from .tables import print_table

__all__ = ["print_run", "print_verdicts", "print_written"]

_STYLE = {"accepted": "green", "suspect": "yellow", "rejected": "bold red"}


def print_verdicts(calibrations: Iterable[CalibrationSummary], console: Console) -> None:
    """Each calibration's verdict, one line with its reasons (:mod:`calib.calibration.verdict`)."""
    for c in calibrations:
        if c.verdict is not None:
            v = c.verdict
            console.print(
                f"{c.method}-marker verdict: [{_STYLE.get(v.status, 'bold')}]{v.status}"
                f"[/]{v.line()[len(v.status) :]}",
                highlight=False,
            )


def print_run(run: RunSummary, console: Console) -> None:
    for line in run.replaced:
        console.print(f"plan: {line}", highlight=False)
    loc, e = run.localization, run.localization.error_mm
    against = (
        ""
        if e is None  # never on the twin
        else f"; error vs truth median {e.median:.3f} mm, p95 {e.p95:.3f} mm, max {e.max:.3f} mm"
    )
    console.print(
        f"localization ({loc.method}): {loc.n_sweeps} sweeps, {loc.n_rejected} rejected{against}"
    )
    print_table(run.calibration_table(), console)
    print_verdicts(run.calibrations, console)
    for c in run.calibrations:
        b, e_true = c.bound95, c.truth_for_bound
        if b is None or e_true is None:
            continue
        console.print(
            f"{c.method}: 95 % error bounds (data and declared errors, no truth) "
            f"rotation {b.rotation_deg:.3f}°, "
            f"translation {b.translation_mm:.3f} mm, image {b.image_mm:.3f} mm; "
            f"the truth is {'inside' if e_true.within(b) else 'OUTSIDE'}"
        )
    t = run.timing
    summed = f" (summed over {t.workers} workers)" if t.workers is not None else ""
    console.print(
        f"time: simulate {t.simulate:.1f} s, localize {t.localize:.1f} s, "
        f"calibrate {t.calibrate:.1f} s{summed}, total {t.total:.1f} s"
    )


def print_written(out: Path, written: Sequence[str], console: Console) -> None:
    """The files a run or calibration wrote (figures counted, not listed)."""
    figures = [f for f in written if f.startswith("figures/")]
    files = [f for f in written if not f.startswith("figures/")]
    console.print(
        f"wrote {', '.join(str(out / f) for f in files)} and {len(figures)} figures in "
        f"{out / 'figures'} (open {out / 'report.html'})"
    )
