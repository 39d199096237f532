"""What the commands on recorded data print: ``uscal calibrate`` (a recorded dataset's
calibration, no ground truth) and ``uscal import plus`` (the sweeps it wrote)."""

from __future__ import annotations

from rich.console import Console

from calib.files.plus_import import ImportSummary

from ..jobs.targets import TargetRun
from ..summaries import RecordedSummary
from .run import print_verdicts
from .tables import print_table

__all__ = ["print_import", "print_recorded", "print_target"]


def print_recorded(rec: RecordedSummary, console: Console) -> None:
    d, loc = rec.dataset, rec.localization
    console.print(
        f"dataset {d.name} ({d.source}): {d.n_sweeps} sweeps of "
        f"{', '.join(d.targets)}; {loc.n_sweeps} localized, {loc.n_rejected} rejected"
    )
    print_table(rec.calibration_table(), console)
    print_verdicts(rec.calibrations, console)
    both = rec.single_vs_three
    if both is not None:
        console.print(
            f"single vs three-marker: {both.rotation_deg:.3f} °, {both.translation_mm:.3f} mm apart"
        )
    ev = rec.touches
    if ev is not None:
        console.print(
            f"touches: {ev.touches}, DH refined from {ev.dh_from}, touch residual "
            f"RMS {ev.touch_residual_rms_mm:.3f} mm"
        )
        for s in ev.summary:
            console.print(
                f"{s.kind}-marker folds: accuracy {s.accuracy_mean:.3f} ± {s.accuracy_sd:.3f} mm, "
                f"precision {s.precision_mean:.3f} ± {s.precision_sd:.3f} mm (against the touch "
                "reference)"
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
        + f". Next: uscal calibrate {summary.directory}"
        + ("" if summary.nwire else " --markers 1")
    )


_NAMES = {"nwire": "N-wire", "wire": "single wire", "cone_tip": "cone tip"}
_ERRORS = {
    "nwire": "3-D reprojection error",
    "wire": "error across the wire",
    "cone_tip": "3-D error of the tips",
}


def print_target(run: TargetRun, console: Console) -> None:
    """``uscal calibrate`` of an N-wire dataset: detection, calibration, verdict."""
    m, cal = run.metrics, run.calibration
    kind = m["dataset"]["target"]
    det, e = m["detection"], m["calibration"][kind]["reprojection_3d_mm"]
    console.print(
        f"dataset {run.dataset.name} ({_NAMES[kind]}, "
        f"phantom pose {m['dataset']['phantom_pose']}): "
        f"{m['dataset']['n_frames']} frames, "
        + (
            f"the tip found in {det['sweeps_found']} of {m['dataset']['n_sequences']} sweeps"
            if kind == "cone_tip"
            else f"every wire found in {det['frames_found']}"
        ),
        highlight=False,
    )
    for reason, n in list(det["refused"].items())[:3]:
        console.print(f"  not used ({n}×): {reason}", highlight=False)
    sx, sy = (v * 1e3 for v in cal.spacing_m)
    b = cal.bound95
    console.print(
        f"pixel spacing {sx:.5f} × {sy:.5f} mm"
        + (" (fitted)" if cal.scale_estimated else "")
        + f"; {_ERRORS[kind]} "
        f"{e['plus_mean']:.3f} ± {e['plus_sd']:.3f} mm (PLUS's statistic); "
        f"95 % bound {b['rotation_deg']:.2f}°, {b['translation_mm']:.2f} mm, "
        f"{b['image_mm']:.2f} mm over the image",
        highlight=False,
    )
    console.print(f"verdict: {run.verdict.line()}", highlight=False)
