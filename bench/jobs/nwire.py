"""``uscal calibrate`` of an N-wire dataset (``uscal import plus --config``, or a robot
rig's N-wire acquisition): uscal's own wire detection on every frame, ``T_ee_us`` (PLUS's
``ImageToProbe``) with the pixel scale and, without a tracked phantom, the phantom's pose
(:mod:`calib.nwire_calibration`), its bounds and verdict; written as ``uscal calibrate``
writes a sphere dataset's (``calibration.yaml``, ``metrics.json``, ``report.md``) plus
the ``CoordinateDefinitions`` entry a PLUS configuration takes."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from calib import se3
from calib.dataset_files import AcquisitionInfo
from calib.image import pixel_to_us
from calib.nwire_calibration import (
    NWireCalibration,
    NWireObservations,
    NWireVerdict,
    calibrate_either_side,
    judge_nwire,
    observe_nwires,
    plus_error_mm,
)
from calib.pipeline import axial_scale
from calib.plus_config import NWire, NWirePattern, NWirePhantom
from calib.records import Dataset
from calib.verdict import Requirements

from ..outputs.calibration_doc import _Dumper, _pose_doc
from ..outputs.report import report_html

__all__ = [
    "NWireRun",
    "calibrate_nwire_dataset",
    "nwire_frames",
    "plus_coordinate_definition",
    "run_nwire",
    "twin_nwire_phantom",
    "write_nwire",
]

_MM = 1e3


@dataclass(frozen=True)
class NWireRun:
    """An N-wire dataset's calibration and what it rests on."""

    dataset: Dataset
    info: AcquisitionInfo
    path: Path
    observations: NWireObservations
    calibration: NWireCalibration
    verdict: NWireVerdict
    metrics: dict[str, Any]


def nwire_frames(dataset: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Every frame of the dataset's sequences, in order, and its pose ``T_base_ee``."""
    images = np.concatenate([s.images for s in dataset.sweeps])
    poses = np.concatenate([s.T_base_ee for s in dataset.sweeps])
    return images, poses


def nwire_spacing_m(dataset: Dataset, info: AcquisitionInfo) -> tuple[float, float]:
    """The images' pixel spacing (columns, rows; m), the axial one corrected for the
    medium's speed of sound when the dataset asks for it."""
    sx, sy = dataset.sweeps[0].spacing
    return float(sx), float(sy) * axial_scale(info)


def calibrate_nwire_dataset(
    dataset: Dataset,
    info: AcquisitionInfo,
    path: str | Path,
    requirements: Requirements,
    *,
    estimate_scale: bool = True,
    wire_tolerance_m: float = 0.0,
    axial_bias_m: float = 0.0,
) -> NWireRun:
    """Detect, calibrate and judge (see the module doc). ``wire_tolerance_m`` and
    ``axial_bias_m``: the declared errors of the bounds (the phantom's build tolerance,
    the echoes' depth bias; :func:`calib.nwire_calibration.calibrate_nwire`)."""
    assert info.nwire is not None
    t0 = time.perf_counter()
    images, poses = nwire_frames(dataset)
    spacing = nwire_spacing_m(dataset, info)
    spacing_mm = (spacing[0] * _MM, spacing[1] * _MM)
    obs = observe_nwires(images, info.nwire.patterns, spacing_mm)
    t_detect = time.perf_counter() - t0
    H, W = images.shape[1:]
    cal, obs, mirrored = calibrate_either_side(
        obs,
        info.nwire.patterns,
        spacing_mm,
        poses,
        width_px=W,
        height_px=H,
        spacing_m=spacing,
        T_base_phantom=info.nwire.T_base_phantom,
        estimate_scale=estimate_scale,
        wire_tolerance_m=wire_tolerance_m,
        axial_bias_m=axial_bias_m,
    )
    verdict = judge_nwire(cal, requirements)
    mean, sd = plus_error_mm(cal.errors_mm)
    metrics: dict[str, Any] = {
        "dataset": {
            "path": str(path),
            "name": dataset.name,
            "source": info.source,
            "target": "nwire",
            "n_sequences": len(dataset.sweeps),
            "n_frames": len(images),
            "patterns": len(info.nwire.patterns),
            "phantom_pose": "estimated" if cal.phantom_estimated else "tracked",
        },
        "image": {
            "width_px": int(W),
            "height_px": int(H),
            "spacing_m": [float(v) for v in spacing],
        },
        "detection": {
            "frames_found": obs.frames_used,
            "points": len(obs.frame),
            "refused": dict(obs.refusals().most_common()),
            "marked_side": "last wire first" if mirrored else "first wire first",
            "ms_per_frame": t_detect / max(len(images), 1) * 1e3,
        },
        "calibration": {
            "nwire": {
                "T_ee_us": cal.T_ee_us.tolist(),
                "plus_ImageToProbe_mm": cal.image_to_probe_mm().tolist(),
                "spacing_fitted_mm": [v * _MM for v in cal.spacing_m],
                "scale_estimated": cal.scale_estimated,
                "scale": list(cal.scale),
                "T_base_phantom": cal.T_base_phantom.tolist(),
                "reprojection_3d_mm": {
                    "plus_mean": mean,
                    "plus_sd": sd,
                    "mean": float(cal.errors_mm.mean()),
                    "median": float(np.median(cal.errors_mm)),
                    "p95": float(np.percentile(cal.errors_mm, 95)),
                    "note": "PLUS's statistic: mean and SD below the 95th percentile",
                },
                "bound95": cal.bound95,
                "covariance_rotvec_rad_translation_m_scale": cal.covariance.tolist(),
                "jackknife_blocks": cal.blocks,
                "outliers": cal.outliers,
                "converged": cal.converged,
                "solver": cal.message,
                "verdict": verdict.as_dict(),
                "seconds": cal.seconds,
            }
        },
        "timing_s": {"detection": t_detect, "total": time.perf_counter() - t0},
    }
    return NWireRun(dataset, info, Path(path), obs, cal, verdict, metrics)


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


def _document(run: NWireRun) -> dict[str, Any]:
    cal, m = run.calibration, run.metrics["calibration"]["nwire"]
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
        "least squares of the 3-D wire-point distances",
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
            "of the errors below their 95th percentile",
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


def _report(run: NWireRun, figure: str | None) -> str:
    cal, m = run.calibration, run.metrics
    e = m["calibration"]["nwire"]["reprojection_3d_mm"]
    det = m["detection"]
    lines = [
        f"# uscal calibration of {run.dataset.name} (N-wire phantom)",
        "",
        f"**Verdict: {run.verdict.line()}**",
        "",
        f"- frames: {m['dataset']['n_frames']}, every pattern found in "
        f"{det['frames_found']} ({det['points']} wire points; "
        f"{det['ms_per_frame']:.1f} ms per frame)",
    ]
    for reason, n in det["refused"].items():
        lines.append(f"  - not used ({n}×): {reason}")
    sx, sy = (v * _MM for v in cal.spacing_m)
    lines += [
        f"- phantom pose: {m['dataset']['phantom_pose']}",
        f"- pixel spacing: {sx:.5f} × {sy:.5f} mm"
        + (f" (fitted; × {cal.scale[0]:.4f}, {cal.scale[1]:.4f})" if cal.scale_estimated else ""),
        f"- 3-D reprojection error (PLUS's definition): {e['plus_mean']:.3f} ± "
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


def _figure(run: NWireRun, path: Path) -> None:
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


def write_nwire(directory: Path, run: NWireRun) -> list[str]:
    """``metrics.json``, ``calibration.yaml``, ``report.md`` and its figure into
    ``directory``; the names written."""
    import yaml

    (directory / "metrics.json").write_text(json.dumps(run.metrics, indent=2) + "\n")
    header = (
        "# uscal calibration (N-wire phantom). T_ee_us: image (us) → probe / flange (ee).\n"
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


# ---------------------------------------------------------------- the twin's N-wire run


def twin_nwire_phantom(twin) -> NWirePhantom:
    """What the pipeline knows of the twin's N-wire phantom: its CAD patterns (three
    wires each, in the phantom's order), its pose unknown (a robot rig)."""
    wires = twin.phantom_cad.wires
    patterns = tuple(
        NWirePattern(tuple(NWire(w.name, w.front, w.back) for w in wires[k : k + 3]))  # type: ignore[arg-type]
        for k in range(0, len(wires), 3)
    )
    return NWirePhantom(patterns, None)


def run_nwire(scenario, twin, acq, t_start: float) -> NWireRun:
    """``uscal run`` of an N-wire scenario: the acquisition's frames calibrated as
    ``uscal calibrate`` would (phantom pose estimated), then scored against the twin's
    truth — rotation, translation and mean image error of ``T_ee_us`` with the fitted
    pixel scale, and whether the 95 % bounds cover them."""
    from sim_us.materials import medium_material

    from ..acquire_sim import acquisition_info
    from ..config.method import requirements, scenario_uncertainty
    from ..truth import transform_difference
    from .single import equivalent_mount

    info = acquisition_info(scenario, twin, acq.T_ee_us_coarse)
    inputs = scenario_uncertainty(scenario)
    t_sim = time.perf_counter() - t_start
    result = calibrate_nwire_dataset(
        acq.dataset,
        info,
        "(twin acquisition)",
        requirements(scenario),
        wire_tolerance_m=scenario.phantom.tolerance_position_mm / _MM,
        axial_bias_m=inputs.axial_bias_m,
    )
    truth = twin.truth
    X_equiv = equivalent_mount(scenario, acq, truth)
    T_true = truth.T_ee_us if X_equiv is None else X_equiv
    cal = result.calibration
    # The image's pixels as each maps them: the fit with its spacing, the truth with the
    # scanner's true one (its scale error; depth drawn at the assumed speed of sound).
    im = scenario.imaging
    H, W = im.image_shape
    rows, cols = np.meshgrid(np.linspace(0, H - 1, 21), np.linspace(0, W - 1, 21))
    ex, ey = im.pixel_scale_error_pct
    c = medium_material(scenario.medium.kind, scenario.medium.temperature_c).speed_m_s
    sx, sy = im.spacing_m
    true_spacing = (sx / (1 + ex / 100), sy / (1 + ey / 100) * c / im.assumed_speed_m_s)
    est = se3.apply(cal.T_ee_us, pixel_to_us(rows, cols, W, cal.spacing_m).reshape(-1, 3))
    true = se3.apply(T_true, pixel_to_us(rows, cols, W, true_spacing).reshape(-1, 3))
    error = transform_difference(cal.T_ee_us, T_true) | {
        "image_mm": float(np.linalg.norm(est - true, axis=1).mean() * _MM)
    }
    b = cal.bound95
    covered = {k: bool(error[k] <= b[k]) for k in ("rotation_deg", "translation_mm", "image_mm")}
    m = result.metrics
    m["scenario"] = {"name": scenario.source, "seed": scenario.seed}
    m["acquisition"] = {
        "sweeps": len(acq.dataset.sweeps),
        "frames": int(sum(s.n_frames for s in acq.dataset.sweeps)),
        "robot_time_s": acq.robot_time_s,
        "replaced": [r.line() for r in acq.replaced],
    }
    m["calibration"]["nwire"]["true_error"] = error
    m["calibration"]["nwire"]["bound_covers"] = covered
    m["calibration"]["nwire"]["coarse_error"] = transform_difference(
        acq.T_ee_us_coarse, truth.T_ee_us
    )
    m["timing_s"]["simulate"] = t_sim
    m["timing_s"]["total"] = time.perf_counter() - t_start
    return replace(result, path=Path(scenario.output.dir), metrics=m)
