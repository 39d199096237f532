"""The run's report: ``report.md`` and ``report.html`` (relative links to
``figures/*.png``), the figures, and ``calibration.yaml`` — the estimated ``T_ee_us``
and the DH table in a form a user copies into their robot software, plus PLUS's
``ImageToProbe`` matrix for PLUS / 3D Slicer users.

The HTML is the Markdown rendered by markdown-it-py (CommonMark with tables), so the
two always say the same.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
from markdown_it import MarkdownIt
from numpy.typing import NDArray

from calib.evaluate import METHOD_TITLES

from ..config.scenario import Scenario
from ..results import RunResult
from ..snapshot import LocalizationSnapshot
from .calibration_doc import calibration_yaml, chosen_calibration
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


def _figures(out: Path, result: RunResult, snapshot: LocalizationSnapshot | None) -> dict[str, str]:
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
    if ev is not None and ev.reconstruction:
        reconstruction_heatmaps(
            ev.reconstruction,
            result.metrics["evaluation"]["datasets"],
            fig_dir / "reconstruction_heatmaps.png",
        )
        written["heatmaps"] = "figures/reconstruction_heatmaps.png"
    return written


# ----------------------------------------------------------------------------- text


def _matrix_md(T: Array, digits: int = 4) -> str:
    rows = ["| | | | |", "|---:|---:|---:|---:|"]
    rows += ["| " + " | ".join(f"{v:.{digits}f}" for v in r) + " |" for r in np.asarray(T)]
    return "\n".join(rows)


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
    return "| setting | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)


def _dataset_md(m: dict[str, Any]) -> str:
    d, im = m["dataset"], m["image"]
    rows = [
        ("dataset", f"`{d['name']}` ({d['source']}), `{d['path']}`"),
        ("sweeps", f"{d['n_sweeps']} ({d['n_frames']} frames) of {', '.join(d['targets'])}"),
        (
            "image",
            f"{im['width_px']} × {im['height_px']} px, "
            f"{', '.join(f'{v * _MM:.4g}' for v in im['spacing_m'])} mm/px",
        ),
        ("medium", f"{d['temperature_c']:g} °C, axial scale {d['axial_scale']:.5f}"),
        ("touches", str(d["n_touches"])),
    ]
    text = "| setting | value |\n|---|---|\n" + "\n".join(f"| {k} | {v} |" for k, v in rows)
    both = m["calibration"].get("single_vs_three")
    if both:
        text += (
            f"\n\nSingle- vs three-marker `T_ee_us`: {both['rotation_deg']:.3f} °, "
            f"{both['translation_mm']:.3f} mm apart."
        )
    return text


_FOLD_TITLES = {"single": "Single-marker", "three": "Leave-one-sphere-out (three-marker)"}


def _touch_evaluation_md(ev: dict[str, Any]) -> str:
    """The paper's folds of a recorded dataset, scored against its touch reference."""
    rows = ["| fold | test sphere | precision (mm) | accuracy (mm) |", "|---|---|---:|---:|"]
    for f in ev["folds"]:
        for s, acc in f["accuracy_mm"].items():
            rows.append(f"| `{f['fold']}` | {s} | {f['precision_mm'][s]:.3f} | {acc:.3f} |")
    lines = [
        f"DH model refined from the touches of {ev['dh_from']}; {ev['touches']} touches of "
        f"this dataset fix its phantom pose (residual RMS {ev['touch_residual_rms_mm']:.3f} "
        "mm). Each fold calibrates on its training spheres and localizes the others:",
        "",
        "\n".join(rows),
    ]
    for kind, v in ev.get("summary", {}).items():
        a, p = v["accuracy_mm"], v["precision_mm"]
        lines += [
            "",
            f"{_FOLD_TITLES[kind]} folds: accuracy {a['mean']:.3f} ± {a['sd']:.3f} mm, "
            f"precision {p['mean']:.3f} ± {p['sd']:.3f} mm.",
        ]
    return "\n".join(lines)


def _calibration_md(m: dict[str, Any]) -> str:
    parts = []
    for method in ("single", "three"):
        c = m["calibration"].get(method)
        if c is None:
            continue
        T = np.array(c["T_ee_us"])
        T_mm = T.copy()
        T_mm[:3, 3] *= _MM
        cov = np.array(c["covariance_rotvec_rad_translation_m"])
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        fold = f" — fold `{c['fold']}`" if "fold" in c else ""
        e = c.get("true_error")
        if e is None:  # recorded data: no truth to compare with
            against = f"Precision {c['precision_mm']:.3f} mm (spread of the sphere centres)."
        else:
            against = (
                f"Against the twin's ground truth: rotation {e['rotation_deg']:.3f} °, "
                f"translation {e['translation_mm']:.3f} mm, mean error over the image "
                f"{e['image_mm']:.3f} mm; precision {c['precision_mm']:.3f} mm, accuracy "
                f"{c['accuracy_mm']:.3f} mm."
            )
        parts.append(
            f"### {METHOD_TITLES[method]}{fold}\n\n"
            f"`T_ee_us` (translation in mm):\n\n{_matrix_md(T_mm)}\n\n"
            f"1 σ (first order, from the residuals): rotation "
            f"{', '.join(f'{v:.3f}' for v in np.degrees(std[:3]))} °, translation "
            f"{', '.join(f'{v:.3f}' for v in std[3:] * _MM)} mm. "
            f"{c['n_retained']} observations kept, {c['iterations']} alternations.\n\n"
            + _bound_md(c)
            + against
        )
    return "\n\n".join(parts)


def _bound_md(c: dict[str, Any]) -> str:
    """The 95 % error bounds of one calibration and what they are made of."""
    b = c.get("bound95")
    if b is None:
        return ""
    u = c.get("uncertainty", {})
    terms = u.get("one_sigma_rss", {})
    names = {
        "jackknife": "jackknife over views",
        "first_order": "first order",
        "print_tolerance": "print tolerance",
        "kinematics": "kinematic residual",
        "axial_scale": "axial scale",
    }
    parts = ", ".join(
        f"{label} {terms[k]['rotation_deg']:.3f} ° / {terms[k]['translation_mm']:.3f} mm"
        for k, label in names.items()
        if k in terms
    )
    return (
        f"95 % error bound: rotation {b['rotation_deg']:.3f} °, translation "
        f"{b['translation_mm']:.3f} mm, mean error over the image {b['image_mm']:.3f} mm "
        f"(1 σ, rss over the axes: {parts}).\n\n"
    )


def _localization_md(m: dict[str, Any]) -> str:
    loc = m["localization"]
    e = loc.get("error_mm")
    if e is None:
        return (
            f"{loc['n_sweeps']} sweeps localized ({loc['method']}), {loc['n_rejected']} rejected."
        )
    return (
        f"{loc['n_sweeps']} sweeps localized ({loc['method']}), {loc['n_rejected']} rejected; "
        f"centre error against the truth: median {e['median']:.3f} mm, p95 {e['p95']:.3f} mm, "
        f"max {e['max']:.3f} mm."
    )


def _truth_md(m: dict[str, Any]) -> str:
    """The evaluation against the twin's ground truth (beyond the paper), per dataset."""
    names = m["evaluation"]["datasets"]
    kin = m["kinematics"]["datasets"]
    rows = [
        "| set | kin. err nominal | kin. err refined | ref. err | 1: image | 1: acc | "
        "3: image | 3: acc |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def mean(folds, kind: str, key: str) -> str:
        v = [f["true"][key] for f in folds if f["kind"] == kind]
        return f"{np.mean(v):.2f}" if v else "–"

    for n in names:
        k = kin[n]
        folds = [f for f in m["evaluation"]["folds"] if f["dataset"] == n]
        rows.append(
            f"| {n} | {k['true_error']['nominal_rms']:.2f} | {k['true_error']['refined_rms']:.3f}"
            f" | {np.mean(list(k['reference_error_mm'].values())):.2f}"
            f" | {mean(folds, 'single', 'image_mm')} | {mean(folds, 'single', 'accuracy_true_mm')}"
            f" | {mean(folds, 'three', 'image_mm')} | {mean(folds, 'three', 'accuracy_true_mm')} |"
        )
    text = "\n".join(rows) + (
        "\n\nmm. kin. err: RMS error of the kinematic model at the image over the scanned "
        "configurations; ref. err: touch reference centres vs true centres; image / acc: "
        "per-fold mean true image error of `T_ee_us` and accuracy against the true centres "
        "(1: single-, 3: three-marker)."
    )
    recal = m.get("reconstruction", {}).get("recalibration", {}).get("true_error")
    if recal:
        worst = max(recal.values(), key=lambda e: e["image_mm"])
        text += (
            "\n\nRe-calibration after the remount (Table III's `T_ee_us`), true image error: "
            f"up to {worst['image_mm']:.2f} mm over the DH models and methods."
        )
    return text


def _figure_md(figures: dict[str, str], key: str, caption: str) -> str:
    if key not in figures:
        return ""
    return f"![{caption}]({figures[key]})\n\n*{caption}*\n"


def report_markdown(scenario: Scenario, result: RunResult, figures: dict[str, str]) -> str:
    """``report.md``."""
    m = result.metrics
    out = [
        "# uscal report",
        "",
        *(
            ["## Dataset", "", _dataset_md(m), ""]
            if "dataset" in m
            else ["## Scenario", "", _scenario_md(scenario), ""]
        ),
        "## Localization",
        "",
        _localization_md(m),
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
        _calibration_md(m),
        "",
        "The transform to copy into robot software, with the DH table and PLUS's "
        "`ImageToProbe`, is in [`calibration.yaml`](calibration.yaml); for ROS 2, "
        f"[`{URDF_FILE}`]({URDF_FILE}) adds it to the robot description, or publish it:",
        "",
        f"```\n{_ros_command(scenario, m)}\n```",
        "",
        _figure_md(figures, "convergence", "Loss and change of T_ee_us per alternation."),
        _figure_md(
            figures,
            "observability",
            "Eigenvalues of the calibrations' information matrices (the smallest is the "
            "weakest direction of the poses).",
        ),
    ]
    if "dataset" in m and m.get("evaluation", {}).get("folds"):
        out += ["## Against the touch reference", "", _touch_evaluation_md(m["evaluation"]), ""]
    if result.evaluation is not None:
        out += [
            "## Against the twin's ground truth",
            "",
            _truth_md(m),
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
    figures = _figures(out, result, result.snapshot)
    md = report_markdown(scenario, result, figures)
    (out / "report.md").write_text(md, encoding="utf-8")
    (out / "report.html").write_text(report_html(md), encoding="utf-8")
    (out / "calibration.yaml").write_text(calibration_yaml(scenario, result), encoding="utf-8")
    T = np.array(result.metrics["calibration"][chosen_calibration(result.metrics)]["T_ee_us"])
    o = scenario.output
    (out / URDF_FILE).write_text(
        urdf_xacro(T, o.ros_parent_link, o.ros_image_link), encoding="utf-8"
    )
    return ["report.md", "report.html", "calibration.yaml", URDF_FILE, *figures.values()]


def _ros_command(scenario: Scenario, m: dict[str, Any]) -> str:
    T = np.array(m["calibration"][chosen_calibration(m)]["T_ee_us"])
    o = scenario.output
    return static_transform_command(T, o.ros_parent_link, o.ros_image_link)
