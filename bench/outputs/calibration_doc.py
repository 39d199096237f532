"""``calibration.yaml``: the estimated ``T_ee_us`` (metres and mm, rotation matrix and
angles), its 1 σ and 95 % bounds, the DH table it holds with, PLUS's ``ImageToProbe``
matrix, ROS 2's static transform, and where it came from."""

from __future__ import annotations

from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from calib import se3
from calib.dh import DHTable
from calib.evaluation.cross_validation import METHOD_TITLES
from calib.files.plus_config import image_to_probe_mm

from ..config.scenario import Scenario
from ..results import RunResult
from ..summaries import CalibrationSummary, RecordedSummary, RunSummary, read_metrics
from .ros import URDF_FILE, static_transform_command

Array = NDArray[np.float64]
_MM = 1e3


def _pose_doc(T: Array) -> dict[str, Any]:
    T = np.asarray(T, dtype=float)
    T_mm = T.copy()
    T_mm[:3, 3] *= _MM
    return {
        "matrix_m": np.round(T, 9).tolist(),
        "matrix_mm": np.round(T_mm, 6).tolist(),
        "position_mm": np.round(T[:3, 3] * _MM, 4).tolist(),
        "rotation_vector_rad": np.round(se3.rotvec_from_matrix(T[:3, :3]), 9).tolist(),
        "rotation_xyz_deg": np.round(np.degrees(se3.euler_from_matrix(T[:3, :3])), 5).tolist(),
    }


def _dh_doc(table: DHTable, source: str) -> dict[str, Any]:
    return {
        "source": source,
        "theta_rad": list(table.theta),
        "d_m": list(table.d),
        "a_m": list(table.a),
        "alpha_rad": list(table.alpha),
    }


def _bound_doc(cal: CalibrationSummary) -> dict[str, Any]:
    """``calibration.yaml``'s 95 % error bounds of a calibration (one that has them)."""
    b = cal.bound95
    assert b is not None and b.image_mm is not None
    u = cal.uncertainty
    declared = u.declared
    kin = u.one_sigma_rss.get("kinematics")
    kinematics = (
        f"kinematic residual {declared.kinematic_sigma_mm:.3g} mm"
        if kin is None or declared.kinematic_sigma_mm == 0
        # The refined arm model's own error at the sweeps' poses (its touch fit's
        # covariance), 1 σ rss on T_ee_us; its touch residual, per axis, beside it.
        else f"the refined arm model's own error {kin.translation_mm:.3g} mm / "
        f"{kin.rotation_deg:.3g}° on T_ee_us (1 σ rss; its touch residual "
        f"{declared.kinematic_sigma_mm:.3g} mm)"
    )
    return {
        "rotation_deg": round(b.rotation_deg, 5),
        "translation_mm": round(b.translation_mm, 5),
        "image_mm": round(b.image_mm, 5),
        "note": (
            "95 % error bounds of T_ee_us: its rotation angle, the distance of its origin, "
            "and the mean error over the image; from a jackknife over the "
            f"{u.views if u.views is not None else '?'} views (probe orientations) of the "
            "data plus the declared "
            f"systematic terms (print tolerance {declared.print_tolerance_mm:g} mm, "
            f"radius tolerance {declared.radius_tolerance_mm:g} mm, "
            f"axial bias {declared.axial_bias_mm:.3g} mm, "
            f"{kinematics}, axial scale "
            f"{declared.axial_scale_sigma:.2g}"
            + (
                f", the rig's own mount error {declared.mount_sigma_mm:g} mm / "
                f"{declared.mount_sigma_deg:g}°"
                if declared.mount_sigma_mm > 0 or declared.mount_sigma_deg > 0
                else ""
            )
            + "; 1 σ per axis)."
        ),
    }


def calibration_document(scenario: Scenario, result: RunResult) -> dict[str, Any]:
    """``calibration.yaml``'s content: the calibration to use
    (:attr:`bench.summaries.Calibrations.chosen`: three-marker when it ran)."""
    summary = read_metrics(result.metrics)
    cal = summary.calibrations.chosen
    T, cov, std = cal.T_ee_us, cal.covariance, cal.std
    recorded = summary if isinstance(summary, RecordedSummary) else None
    if recorded is not None:  # a recorded dataset: its frames decide
        W, H = recorded.image.width_px, recorded.image.height_px
        spacing = recorded.image.spacing_m
    else:
        H, W = scenario.imaging.image_shape
        spacing = scenario.imaging.spacing_m
    paper = summary.evaluation if isinstance(summary, RunSummary) else None
    if recorded is not None:
        d, touches, refined = recorded.dataset, recorded.touches, recorded.dh_table_refined
        if refined is not None and touches is not None:
            dh = _dh_doc(
                DHTable.from_array(refined),
                f"refined from the touches of {touches.dh_from}; the flange poses "
                "were recomputed from the joint angles with it",
            )
        else:
            dh = _dh_doc(
                scenario.robot.nominal_table,
                f"nominal {scenario.robot.model} table (the poses are as the controller "
                "reported them, with its own calibrated model)",
            )
        origin = f"dataset {d.name} ({d.path})"
    elif result.evaluation is not None and paper is not None and cal.fold is not None:
        dataset = cal.fold.split("/")[0]
        others = ", ".join(n for n in paper.datasets if n != dataset)
        dh = _dh_doc(
            result.evaluation.refinements[dataset].table,
            f"refined from the touches of datasets {others} (used for dataset {dataset})",
        )
        origin = f"fold {cal.fold} of the paper's cross-validation"
    else:
        dh = _dh_doc(scenario.robot.nominal_table, f"nominal {scenario.robot.model} table")
        origin = "the run's acquisition"
    return {
        "description": (
            "T_ee_us maps points of the ultrasound image frame (us: origin at the centre of "
            "the transducer face, x lateral along increasing columns, y axial = depth, "
            "z = x × y) to the robot flange frame (ee); T_dst_src convention."
        ),
        **(
            {"scenario": summary.scenario}
            if isinstance(summary, RunSummary)
            else {"dataset": summary.dataset.path}
        ),
        "method": METHOD_TITLES[cal.method],
        "from": origin,
        **(
            {"verdict": {"status": cal.verdict.status, "reasons": list(cal.verdict.reasons)}}
            if cal.verdict is not None
            else {}
        ),
        "T_ee_us": _pose_doc(T),
        "uncertainty_1sigma": {
            "rotation_deg": np.round(np.degrees(std[:3]), 5).tolist(),
            "translation_mm": np.round(std[3:] * _MM, 5).tolist(),
            "covariance_rotvec_rad_translation_m": cov.tolist(),
        },
        **({"bound95": _bound_doc(cal)} if cal.bound95 is not None else {}),
        "image": {
            "width_px": int(W),
            "height_px": int(H),
            "pixel_spacing_mm": [round(s * _MM, 6) for s in spacing],
            "note": "spacing as the scanner displays it (at its assumed speed of sound)",
        },
        "plus_ImageToProbe": {
            # Nine decimals: the entries are mm per pixel, multiplied by hundreds of pixels.
            "matrix": np.round(image_to_probe_mm(T, W, spacing), 9).tolist(),
            "note": (
                "PLUS / 3D Slicer: image pixel (i, j) → probe (= flange) mm, pixel spacing "
                "included; put it in the PLUS device set as the ImageToProbe transform."
            ),
        },
        "ros": {
            "urdf": URDF_FILE,
            "parent_link": scenario.output.ros_parent_link,
            "child_link": scenario.output.ros_image_link,
            "static_transform_publisher": static_transform_command(
                T, scenario.output.ros_parent_link, scenario.output.ros_image_link
            ),
            "note": (
                f"ROS 2: {URDF_FILE} adds the image frame to the robot description as a "
                "fixed joint (xyz m, rpy rad); or publish it with the command."
            ),
        },
        "dh_table": dh,
    }


class _Dumper(yaml.SafeDumper):
    """Lists of numbers in flow style (a 4 × 4 matrix reads as four rows)."""


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    flat = all(not isinstance(v, (list, dict)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flat)


def _represent_str(dumper: yaml.SafeDumper, data: str) -> yaml.Node:
    """Text of several lines (an XML snippet to paste) as a literal block."""
    style = "|" if "\n" in data else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style=style)


_Dumper.add_representer(list, _represent_list)
_Dumper.add_representer(str, _represent_str)


def calibration_yaml(scenario: Scenario, result: RunResult) -> str:
    """``calibration.yaml``: :func:`calibration_document` with its header."""
    header = (
        "# uscal calibration. T_ee_us: image (us) → flange (ee). Lengths in metres unless\n"
        "# the key says mm; rotations in radians unless it says deg.\n"
    )
    doc = calibration_document(scenario, result)
    return header + yaml.dump(doc, Dumper=_Dumper, sort_keys=False, width=100, allow_unicode=True)
