"""The run's report: ``report.md`` and ``report.html`` (relative links to
``figures/*.png``), the figures, and ``calibration.yaml`` — the estimated ``T_ee_us``
and the DH table in a form a user copies into their robot software, plus PLUS's
``ImageToProbe`` matrix for PLUS / 3D Slicer users.

The HTML is the Markdown rendered by markdown-it-py (CommonMark with tables), so the
two always say the same. What they say of the run comes from its typed summary
(:func:`bench.summaries.read_metrics`), its tables from :class:`bench.tables.Table`.
"""

from __future__ import annotations

import html
from dataclasses import replace
from pathlib import Path

import numpy as np
from markdown_it import MarkdownIt
from numpy.typing import NDArray

from calib.calibration.verdict import SHALLOW_CAPS_M, TILTED_SWEEP_DEG
from calib.evaluation.cross_validation import METHOD_TITLES

from ..config.scenario import Scenario
from ..results import RunResult
from ..snapshot import LocalizationSnapshot
from ..summaries import (
    Calibrations,
    CalibrationSummary,
    LocalizationSummary,
    PaperEvaluation,
    Reconstruction,
    RecordedSummary,
    RunSummary,
    TouchEvaluation,
    read_metrics,
)
from ..tables import Column, Table, left
from .calibration_doc import calibration_yaml
from .figures import (
    convergence_figure,
    observability_eigenvalues,
    observability_figure,
    overlay_figure,
    profile_figure,
    reconstruction_heatmaps,
)
from .ros import URDF_FILE, static_transform_command, urdf_xacro

__all__ = ["report_html", "report_markdown", "write_report"]

Array = NDArray[np.float64]
_MM = 1e3


# ----------------------------------------------------------------------------- figures


def _figures(
    out: Path,
    result: RunResult,
    snapshot: LocalizationSnapshot | None,
    summary: RunSummary | RecordedSummary,
) -> dict[str, str]:
    """Draw the figures; returns {key: relative path}."""
    fig_dir = out / "figures"
    fig_dir.mkdir(exist_ok=True)
    written: dict[str, str] = {}
    alternations = result.alternations()
    if alternations:
        convergence_figure(alternations, fig_dir / "convergence.png")
        written["convergence"] = "figures/convergence.png"
        observability_figure(
            {METHOD_TITLES[k]: observability_eigenvalues(a) for k, a in alternations.items()},
            fig_dir / "observability.png",
        )
        written["observability"] = "figures/observability.png"
    if snapshot is not None:
        overlay_figure(snapshot, fig_dir / "localization_overlay.png")
        written["overlay"] = "figures/localization_overlay.png"
        if snapshot.profile.n_sweeps:
            profile_figure(snapshot, fig_dir / "radial_profile.png")
            written["profile"] = "figures/radial_profile.png"
    ev = result.evaluation
    paper = summary.evaluation if isinstance(summary, RunSummary) else None
    if ev is not None and ev.reconstruction and paper is not None:
        reconstruction_heatmaps(
            ev.reconstruction, paper.datasets, fig_dir / "reconstruction_heatmaps.png"
        )
        written["heatmaps"] = "figures/reconstruction_heatmaps.png"
    return written


# ----------------------------------------------------------------------------- text


def _matrix_md(T: Array, digits: int = 4) -> str:
    rows = tuple(tuple(f"{v:.{digits}f}" for v in r) for r in np.asarray(T))
    return Table((Column("", "right"),) * 4, rows).markdown()


def _settings_md(rows: list[tuple[str, str]], notes: tuple[str, ...] = ()) -> str:
    """A two-column table of settings and their values (Markdown in the values)."""
    return Table(left("setting", "value"), tuple(rows), notes=notes).markdown()


def _scenario_md(s: Scenario) -> str:
    r, p, im, pr = s.robot, s.phantom, s.imaging, s.protocol
    rows = [
        ("scenario", f"`{s.source}` (seed {s.seed})"),
        ("robot", f"{r.model}, DH error ×{r.dh_error_scale:g}"),
        ("phantom", f"{p.kind}, sphere radius {p.sphere_radius_mm:g} mm"),
        (
            "imaging",
            f"{im.width_mm:g} × {im.depth_mm:g} mm, {list(im.pixel_spacing_mm)} mm/px, "
            f"{im.f_mhz:g} MHz, gain {im.gain_db:g} dB",
        ),
        ("medium", f"{s.medium.kind} at {s.medium.temperature_c:g} °C"),
        (
            "protocol",
            f"spheres {list(pr.spheres)}, 45 sweeps each of {pr.frames_per_sweep} frames "
            f"over ±{pr.sweep_half_length_mm:g} mm",
        ),
        ("localization", f"{s.localization.method}"),
        ("datasets", ", ".join(s.evaluation.datasets) or "one acquisition"),
    ]
    return _settings_md(rows)


def _dataset_md(rec: RecordedSummary) -> str:
    d, im = rec.dataset, rec.image
    rows = [
        ("dataset", f"`{d.name}` ({d.source}), `{d.path}`"),
        ("sweeps", f"{d.n_sweeps} ({d.n_frames} frames) of {', '.join(d.targets)}"),
        (
            "image",
            f"{im.width_px} × {im.height_px} px, "
            f"{', '.join(f'{v * _MM:.4g}' for v in im.spacing_m)} mm/px",
        ),
        ("medium", f"{d.temperature_c:g} °C, axial scale {d.axial_scale:.5f}"),
        ("touches", str(d.n_touches)),
    ]
    both = rec.single_vs_three
    notes = (
        ()
        if both is None
        else (
            f"Single- vs three-marker `T_ee_us`: {both.rotation_deg:.3f} °, "
            f"{both.translation_mm:.3f} mm apart.",
        )
    )
    return _settings_md(rows, notes)


_FOLD_TITLES = {"single": "Single-marker", "three": "Leave-one-sphere-out (three-marker)"}


def _touch_evaluation_md(ev: TouchEvaluation) -> str:
    """The paper's folds of a recorded dataset, scored against its touch reference."""
    spreads = tuple(
        f"{_FOLD_TITLES[s.kind]} folds: accuracy {s.accuracy_mean:.3f} ± {s.accuracy_sd:.3f} mm, "
        f"precision {s.precision_mean:.3f} ± {s.precision_sd:.3f} mm."
        for s in ev.summary
    )
    return (
        f"DH model refined from the touches of {ev.dh_from}; {ev.touches} touches of "
        f"this dataset fix its phantom pose (residual RMS {ev.touch_residual_rms_mm:.3f} "
        "mm). Each fold calibrates on its training spheres and localizes the others:\n\n"
        + replace(ev.folds_table(), notes=spreads).markdown()
    )


def _calibration_md(calibrations: Calibrations) -> str:
    parts = []
    for c in calibrations:
        T_mm = c.T_ee_us.copy()
        T_mm[:3, 3] *= _MM
        std = c.std
        fold = f" — fold `{c.fold}`" if c.fold is not None else ""
        e = c.true_error
        if e is None:  # recorded data: no truth to compare with
            against = f"Precision {c.precision_mm:.3f} mm (spread of the sphere centres)."
        else:
            against = (
                f"Against the twin's ground truth: rotation {e.rotation_deg:.3f} °, "
                f"translation {e.translation_mm:.3f} mm, mean error over the image "
                f"{e.image_mm:.3f} mm; precision {c.precision_mm:.3f} mm, accuracy "
                f"{c.accuracy_mm:.3f} mm."
            )
        verdict = (
            f"**Verdict: {c.verdict.status}**"
            + (" — " + "; ".join(c.verdict.reasons) if c.verdict.reasons else "")
            + ".\n\n"
            if c.verdict is not None
            else ""
        )
        parts.append(
            f"### {METHOD_TITLES[c.method]}{fold}\n\n"
            + verdict
            + f"`T_ee_us` (translation in mm):\n\n{_matrix_md(T_mm)}\n\n"
            f"1 σ (first order, from the residuals): rotation "
            f"{', '.join(f'{v:.3f}' for v in np.degrees(std[:3]))} °, translation "
            f"{', '.join(f'{v:.3f}' for v in std[3:] * _MM)} mm. "
            f"{c.n_retained} observations kept, {c.iterations} alternations.\n\n"
            + _bound_md(c)
            + against
        )
    return "\n\n".join(parts)


def _bound_md(c: CalibrationSummary) -> str:
    """The 95 % error bounds of one calibration and what they are made of."""
    b = c.bound95
    if b is None:
        return ""
    terms = c.uncertainty.one_sigma_rss
    names = {
        "jackknife": "jackknife over views",
        "first_order": "first order",
        "print_tolerance": "print tolerance",
        "kinematics": "kinematic residual",
        "axial_scale": "axial scale",
    }
    parts = ", ".join(
        f"{label} {terms[k].rotation_deg:.3f} ° / {terms[k].translation_mm:.3f} mm"
        for k, label in names.items()
        if k in terms
    )
    return (
        f"95 % error bound: rotation {b.rotation_deg:.3f} °, translation "
        f"{b.translation_mm:.3f} mm, mean error over the image {b.image_mm:.3f} mm "
        f"(1 σ, rss over the axes: {parts}).\n\n"
    )


def _sweep_axis_md(metrics: dict) -> str:
    """How far the sweeps ran off the calibrated image normal and, with a second pass,
    what the first pass's calibrations were off by (simulated runs)."""
    axis = metrics.get("calibration", {}).get("sweep_axis")
    if axis is None or not np.isfinite(axis["angle_deg"]):
        return ""
    first = metrics.get("first_pass")
    which = "second pass's " if first is not None else ""
    text = (
        f"The {which}sweeps ran {axis['angle_deg']:.1f}° off the calibrated image normal "
        f"({axis['in_depth_deg']:+.1f}° towards depth, {axis['across_deg']:+.1f}° across the "
        "image): the mount they were planned through was off the calibrated one by that "
        "much."
    )
    if first is None:
        text += (
            " A sweep tilted towards depth moves a target's depth from frame to frame; with "
            f"the caps' tops within {SHALLOW_CAPS_M * 1e3:g} mm of the face and the sweeps "
            f"{TILTED_SWEEP_DEG:g}° or more off in depth, a calibration is suspect (on the "
            "twin, 20 of 82 such single scans fell "
            'outside their 95 % bounds; README, "The sweep\'s tilt in depth"), and a second '
            "scan along the calibrated normal (protocol.second_pass; on a rig, a second "
            "acquisition with this calibration as the coarse mount) removes most of it."
        )
    else:
        a = first["sweep_axis"]
        errs = "; ".join(
            f"{METHOD_TITLES[k].lower()}: rotation {e['rotation_deg']:.3f} °, mean error over "
            f"the image {e['image_mm']:.3f} mm"
            for k, e in first["true_error"].items()
        )
        text += (
            f" The first pass's sweeps ran {a['angle_deg']:.1f}° off it "
            f"({a['in_depth_deg']:+.1f}° towards depth); calibrated on them, against the "
            f"twin's ground truth: {errs}. The calibrations above are the second pass's "
            "(protocol.second_pass)."
        )
        if any(first.get("tilted_over_shallow_caps", {}).values()):
            text += (
                " Scanned once, the first pass would have been suspect: its sweeps' tilt "
                f"towards depth over caps within {SHALLOW_CAPS_M * 1e3:g} mm of the face."
            )
    return text + "\n"


def _localization_md(loc: LocalizationSummary) -> str:
    e = loc.error_mm
    if e is None:
        return f"{loc.n_sweeps} sweeps localized ({loc.method}), {loc.n_rejected} rejected."
    return (
        f"{loc.n_sweeps} sweeps localized ({loc.method}), {loc.n_rejected} rejected; "
        f"centre error against the truth: median {e.median:.3f} mm, p95 {e.p95:.3f} mm, "
        f"max {e.max:.3f} mm."
    )


def _truth_md(ev: PaperEvaluation, rec: Reconstruction | None) -> str:
    """The evaluation against the twin's ground truth (beyond the paper), per dataset."""
    notes = [
        "mm. kin. err: RMS error of the kinematic model at the image over the scanned "
        "configurations; ref. err: touch reference centres vs true centres; image / acc: "
        "per-fold mean true image error of `T_ee_us` and accuracy against the true centres "
        '(1: single-, 3: three-marker); accepted: folds whose verdict (README, "The '
        'verdict") is accepted.'
    ]
    worst = rec.worst_recalibration_image_mm if rec is not None else None
    if worst is not None:
        notes.append(
            "Re-calibration after the remount (Table III's `T_ee_us`), true image error: "
            f"up to {worst:.2f} mm over the DH models and methods."
        )
    return replace(ev.truth_table(), notes=tuple(notes)).markdown()


def _figure_md(figures: dict[str, str], key: str, caption: str) -> str:
    if key not in figures:
        return ""
    return f"![{caption}]({figures[key]})\n\n*{caption}*\n"


def report_markdown(scenario: Scenario, result: RunResult, figures: dict[str, str]) -> str:
    """``report.md``."""
    summary = read_metrics(result.metrics)
    recorded = summary if isinstance(summary, RecordedSummary) else None
    out = [
        "# uscal report",
        "",
        *(
            ["## Dataset", "", _dataset_md(recorded), ""]
            if recorded is not None
            else ["## Scenario", "", _scenario_md(scenario), ""]
        ),
        "## Localization",
        "",
        _localization_md(summary.localization),
        "",
        _figure_md(
            figures, "overlay", "Sphere sections across one sweep: found (red), true (green)."
        ),
        _figure_md(
            figures,
            "profile",
            "Radial brightness profile about the found centres; its 0.25 and 0.75 crossings "
            "set the interior and shell bands.",
        ),
        "## Calibration",
        "",
        _calibration_md(summary.calibrations),
        "",
        _sweep_axis_md(result.metrics),
        "The transform to copy into robot software, with the DH table and PLUS's "
        "`ImageToProbe`, is in [`calibration.yaml`](calibration.yaml); for ROS 2, "
        f"[`{URDF_FILE}`]({URDF_FILE}) adds it to the robot description, or publish it:",
        "",
        f"```\n{_ros_command(scenario, summary.calibrations.chosen)}\n```",
        "",
        _figure_md(figures, "convergence", "Loss and change of T_ee_us per alternation."),
        _figure_md(
            figures,
            "observability",
            "Eigenvalues of the calibrations' information matrices (the smallest is the "
            "weakest direction of the poses).",
        ),
    ]
    touches = recorded.touches if recorded is not None else None
    if touches is not None and touches.folds:
        out += ["## Against the touch reference", "", _touch_evaluation_md(touches), ""]
    run = summary if isinstance(summary, RunSummary) else None
    if result.evaluation is not None and run is not None and run.evaluation is not None:
        out += [
            "## Against the twin's ground truth",
            "",
            _truth_md(run.evaluation, run.reconstruction),
            "",
            "## The paper's tables",
            "",
            result.evaluation.tables_markdown.strip(),
            "",
            _figure_md(
                figures,
                "heatmaps",
                "Registered reconstruction points coloured by point-to-surface error.",
            ),
        ]
    out += [
        "## Files",
        "",
        "`metrics.json` (every figure, ground truth kept apart), `tables.md` / `tables.csv` "
        f"(evaluation runs), `calibration.yaml`, `{URDF_FILE}`, `figures/`, and "
        "`recording.rrd` (open with "
        "`rerun recording.rrd`) when recorded.",
        "",
    ]
    return "\n".join(line for line in out if line is not None)


_CSS = """
body { font-family: system-ui, sans-serif; max-width: 72rem; margin: 2rem auto;
       padding: 0 1rem; color: #222; line-height: 1.45; }
table { border-collapse: collapse; margin: 0.6rem 0; font-size: 0.9rem; }
th, td { border: 1px solid #ccc; padding: 0.2rem 0.5rem; }
th { background: #f2f2f2; }
img { max-width: 100%; }
code { background: #f4f4f4; padding: 0 0.2rem; }
"""


def report_html(markdown: str, title: str = "uscal report") -> str:
    """The Markdown as one HTML page (figures linked relatively)."""
    body = MarkdownIt("commonmark").enable("table").render(markdown)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n"
        f"</head>\n<body>\n{body}</body>\n</html>\n"
    )


def write_report(
    out: str | Path,
    scenario: Scenario,
    result: RunResult,
) -> list[str]:
    """Write the report, its figures and ``calibration.yaml`` into ``out``; returns the
    files written (relative)."""
    out = Path(out)
    summary = read_metrics(result.metrics)
    figures = _figures(out, result, result.snapshot, summary)
    md = report_markdown(scenario, result, figures)
    (out / "report.md").write_text(md, encoding="utf-8")
    (out / "report.html").write_text(report_html(md), encoding="utf-8")
    (out / "calibration.yaml").write_text(calibration_yaml(scenario, result), encoding="utf-8")
    T = summary.calibrations.chosen.T_ee_us
    o = scenario.output
    (out / URDF_FILE).write_text(
        urdf_xacro(T, o.ros_parent_link, o.ros_image_link), encoding="utf-8"
    )
    return ["report.md", "report.html", "calibration.yaml", URDF_FILE, *figures.values()]


def _ros_command(scenario: Scenario, chosen: CalibrationSummary) -> str:
    o = scenario.output
    return static_transform_command(chosen.T_ee_us, o.ros_parent_link, o.ros_image_link)
