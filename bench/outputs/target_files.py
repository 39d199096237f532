"""What an N-wire calibration writes (``uscal calibrate`` of an N-wire dataset, ``uscal
run`` of an N-wire scenario): ``metrics.json``, ``calibration.yaml`` (``T_ee_us``, its
bounds and verdict, PLUS's ``ImageToProbe`` and the ``CoordinateDefinitions`` entry a
PLUS configuration takes), ``report.md`` / ``report.html`` and a figure of the 3-D
error per frame."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from calib.calibration.nwire import NWireCalibration

from ..jobs.targets import TargetRun
from .calibration_doc import _Dumper, _pose_doc
from .report import report_html

__all__ = ["plus_coordinate_definition", "write_target"]

_MM = 1e3


def plus_coordinate_definition(cal: NWireCalibration, error_mm: float) -> str:
    """The ``<Transform From="Image" To="Probe" …/>`` element of a PLUS device set's
    ``CoordinateDefinitions`` (row-major, millimetres, pixel spacing included)."""
    A = cal.image_to_probe_mm()
    matrix = "\n        ".join(" ".join(f"{v:.9g}" for v in row) for row in A)
    date = datetime.now(UTC).strftime("%m%d%Y_%H%M%S")
    return (
        '<Transform From="Image" To="Probe"\n'
        f'      Matrix="\n        {matrix}"\n'
        f'      Error="{error_mm:.4g}" Date="{date}" />'
    )


_PHANTOM = {"nwire": "N-wire phantom", "wire": "single wire", "cone_tip": "cone tip"}
_ERROR = {
    "nwire": "3-D reprojection error (PLUS's definition)",
    "wire": "error across the wire (PLUS's statistic)",
    "cone_tip": "3-D error of the tip (PLUS's statistic)",
}


def _kind(run: TargetRun) -> str:
    """``nwire`` or ``wire``: which wires the calibration rests on."""
    return str(run.metrics["dataset"]["target"])


def _document(run: TargetRun) -> dict[str, Any]:
    cal, m = run.calibration, run.metrics["calibration"][_kind(run)]
    mean, sd = m["reprojection_3d_mm"]["plus_mean"], m["reprojection_3d_mm"]["plus_sd"]
    std = np.sqrt(np.clip(np.diag(cal.covariance), 0.0, None))
    return {
        "description": (
            "T_ee_us maps points of the ultrasound image frame (us: origin at the centre "
            "of the image's top row, x lateral along increasing columns, y axial = depth, "
            "z = x × y) to the probe's tracked body or the robot flange (ee); T_dst_src "
            "convention. The pixel spacing it holds with is image.pixel_spacing_mm."
        ),
        "dataset": str(run.path),
        "method": "N-wire phantom: threshold-free wire detection, closed form and robust "
        "least squares of the 3-D wire-point distances"
        if _kind(run) == "nwire"
        else "single wire: threshold-free dot detection, robust least squares of each dot's "
        "distance across the wire, the wire's pose estimated with T_ee_us"
        if _kind(run) == "wire"
        else "cone tip: the apex of each sweep (a cone fitted to its frames' surface echoes), "
        "robust least squares of the apexes' distances, the cone's position estimated",
        "verdict": run.verdict.as_dict(),
        "T_ee_us": _pose_doc(cal.T_ee_us),
        "uncertainty_1sigma": {
            "rotation_deg": np.round(np.degrees(std[:3]), 5).tolist(),
            "translation_mm": np.round(std[3:6] * _MM, 5).tolist(),
            "scale": np.round(std[6:8], 6).tolist(),
        },
        "bound95": {
            **{k: round(v, 5) for k, v in cal.bound95.items()},
            "note": (
                "95 % error bounds of T_ee_us and the pixel scale: rotation angle, origin "
                "distance and mean error over the image; from a jackknife over "
                f"{cal.blocks} blocks of consecutive frames against the first-order "
                "covariance, Student-t widened. Not included: the error of the phantom's "
                "registration to its tracked body (Phantom→Reference), which every frame "
                "shares and no residual shows."
                if not cal.phantom_estimated
                else "95 % error bounds of T_ee_us and the pixel scale (the phantom's "
                f"pose estimated with it); jackknife over {cal.blocks} blocks of frames."
            ),
        },
        "reprojection_3d_mm": {
            "mean": round(mean, 4),
            "sd": round(sd, 4),
            "note": "PLUS's definition: distance between each diagonal-wire point and "
            "its image point mapped through the calibration and the pose; mean and SD "
            "of the errors below their 95th percentile"
            if _kind(run) == "nwire"
            else "each dot's distance from the wire across it, mapped through the "
            "calibration and the pose; mean and SD below their 95th percentile",
        },
        "image": {
            "width_px": cal.width_px,
            "height_px": cal.height_px,
            "pixel_spacing_mm": [round(float(s) * _MM, 7) for s in cal.spacing_m],
            "note": "as fitted (scale estimated)"
            if cal.scale_estimated
            else "as the dataset gives it",
        },
        "plus_ImageToProbe": {
            "matrix": np.round(cal.image_to_probe_mm(), 9).tolist(),
            "note": (
                "PLUS / 3D Slicer: image pixel (i, j) → probe mm, pixel spacing included; "
                "the CoordinateDefinitions entry below carries it."
            ),
        },
        "plus_coordinate_definitions": plus_coordinate_definition(cal, mean),
        **({"T_base_phantom": _pose_doc(cal.T_base_phantom)} if cal.phantom_estimated else {}),
    }


def _report(run: TargetRun, figure: str | None) -> str:
    cal, m = run.calibration, run.metrics
    e = m["calibration"][_kind(run)]["reprojection_3d_mm"]
    det = m["detection"]
    lines = [
        f"# uscal calibration of {run.dataset.name} ({_PHANTOM[_kind(run)]})",
        "",
        f"**Verdict: {run.verdict.line()}**",
        "",
        f"- frames: {m['dataset']['n_frames']}, "
        + ("the tip found in sweeps: " if _kind(run) == "cone_tip" else "every wire found in ")
        + f"{det['frames_found']} ({det['points']} points; "
        f"{det['ms_per_frame']:.1f} ms per frame)",
    ]
    for reason, n in det["refused"].items():
        lines.append(f"  - not used ({n}×): {reason}")
    sx, sy = (v * _MM for v in cal.spacing_m)
    lines += [
        f"- phantom pose: {m['dataset']['phantom_pose']}",
        f"- pixel spacing: {sx:.5f} × {sy:.5f} mm"
        + (f" (fitted; × {cal.scale[0]:.4f}, {cal.scale[1]:.4f})" if cal.scale_estimated else ""),
        f"- {_ERROR[_kind(run)]}: {e['plus_mean']:.3f} ± "
        f"{e['plus_sd']:.3f} mm (median {e['median']:.3f}, 95th percentile {e['p95']:.3f})",
        f"- 95 % bounds: {cal.bound95['rotation_deg']:.3f}°, "
        f"{cal.bound95['translation_mm']:.3f} mm, {cal.bound95['image_mm']:.3f} mm over the "
        "image",
        "",
        "## ImageToProbe (PLUS, mm per pixel)",
        "",
        "```",
        *(" ".join(f"{v:12.6f}" for v in row) for row in cal.image_to_probe_mm()),
        "```",
        "",
        "PLUS device set (`CoordinateDefinitions`):",
        "",
        "```xml",
        plus_coordinate_definition(cal, e["plus_mean"]),
        "```",
    ]
    if figure:
        lines += ["", f"![3-D reprojection error per frame]({figure})", ""]
    return "\n".join(lines) + "\n"


def _figure(run: TargetRun, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    obs, cal = run.observations, run.calibration
    fig, ax = plt.subplots(figsize=(7, 3))
    for j in np.unique(obs.pattern):
        rows = obs.pattern == j
        ax.plot(obs.frame[rows], cal.errors_mm[rows], ".", ms=4, label=f"pattern {j + 1}")
    ax.set_xlabel("frame")
    ax.set_ylabel("3-D error (mm)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_target(directory: Path, run: TargetRun) -> list[str]:
    """``metrics.json``, ``calibration.yaml``, ``report.md`` and its figure into
    ``directory``; the names written."""
    import yaml

    (directory / "metrics.json").write_text(json.dumps(run.metrics, indent=2) + "\n")
    header = (
        f"# uscal calibration ({_PHANTOM[_kind(run)]}). "
        "T_ee_us: image (us) → probe / flange (ee).\n"
        "# Lengths in metres unless the key says mm; rotations in radians unless deg.\n"
    )
    doc = yaml.dump(_document(run), Dumper=_Dumper, sort_keys=False, allow_unicode=True)
    (directory / "calibration.yaml").write_text(header + doc, encoding="utf-8")
    (directory / "figures").mkdir(exist_ok=True)
    _figure(run, directory / "figures" / "reprojection.png")
    markdown = _report(run, "figures/reprojection.png")
    (directory / "report.md").write_text(markdown, encoding="utf-8")
    (directory / "report.html").write_text(
        report_html(markdown, f"uscal N-wire calibration of {run.dataset.name}"), encoding="utf-8"
    )
    return [
        "metrics.json",
        "calibration.yaml",
        "report.md",
        "report.html",
        "figures/reprojection.png",
    ]
