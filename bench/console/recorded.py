"""What the commands on recorded data print: ``uscal calibrate`` (a recorded dataset's
calibration, no ground truth) and ``uscal import plus`` (the sweeps it wrote)."""

from __future__ import annotations

import numpy as np
from rich.console import Console

from calib.plus_import import ImportSummary

from .run import calibration_table

__all__ = ["print_import", "print_recorded"]


def print_recorded(m: dict, console: Console) -> None:
    d, loc = m["dataset"], m["localization"]
    console.print(
        f"dataset {d['name']} ({d['source']}): {d['n_sweeps']} sweeps of "
        f"{', '.join(d['targets'])}; {loc['n_sweeps']} localized, {loc['n_rejected']} rejected"
    )

    def cells(c: dict) -> list[str]:
        t = np.array(c["T_ee_us"])[:3, 3] * 1e3
        b = c.get("bound95") or {}
        return [
            *(f"{v:.2f}" for v in t),
            f"{b['rotation_deg']:.3f}" if b else "-",
            f"{b['translation_mm']:.3f}" if b else "-",
            f"{c['precision_mm']:.3f}",
            str(c["n_retained"]),
        ]

    # The 95 % error bounds (calib.uncertainty): what the estimate can be off by.
    columns = ("x mm", "y mm", "z mm", "≤95% rot °", "≤95% mm", "prec mm", "kept")
    console.print(calibration_table(m, "calibration (no ground truth)", columns, cells))
    both = m["calibration"].get("single_vs_three")
    if both:
        console.print(
            f"single vs three-marker: {both['rotation_deg']:.3f} °, "
            f"{both['translation_mm']:.3f} mm apart"
        )
    ev = m.get("evaluation")
    if ev:
        console.print(
            f"touches: {ev['touches']}, DH refined from {ev['dh_from']}, touch residual "
            f"RMS {ev['touch_residual_rms_mm']:.3f} mm"
        )
        for kind, v in ev.get("summary", {}).items():
            a, p = v["accuracy_mm"], v["precision_mm"]
            console.print(
                f"{kind}-marker folds: accuracy {a['mean']:.3f} ± {a['sd']:.3f} mm, "
                f"precision {p['mean']:.3f} ± {p['sd']:.3f} mm (against the touch reference)"
            )


def print_import(summary: ImportSummary, console: Console) -> None:
    """What ``uscal import plus`` wrote: each sweep, the frames skipped and why."""
    for line in summary.sweep_lines:
        console.print(line)
    skipped = sum(summary.skipped.values())
    why = ", ".join(f"{n} with {reason}" for reason, n in sorted(summary.skipped.items()))
    console.print(
        f"wrote {summary.directory}: {summary.sweeps} sweeps, {summary.frames} frames; "
        + (f"skipped {skipped} frames ({why})" if skipped else "no frame skipped")
        + f". Next: uscal calibrate {summary.directory} --markers 1"
    )
