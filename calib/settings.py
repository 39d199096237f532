"""Settings of the pipeline stages that follow localization: calibration, evaluation and
reconstruction (defaults: the paper's values)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

__all__ = ["CalibrationConfig", "EvaluationConfig", "ReconstructionConfig"]


@dataclass(frozen=True)
class CalibrationConfig:
    """Single- and three-marker calibration (paper, "Single- and Three-Marker Calibration")."""

    initial_error_mm: float = field(
        default=3.0,
        metadata={
            "doc": "Simulation: the coarse T_ee_us handed to the pipeline is off by up to "
            "± this per axis.",
            "ge": 0,
            "le": 50,
        },
    )
    initial_error_deg: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: coarse T_ee_us rotation error, up to ± this per axis.",
            "ge": 0,
            "le": 45,
        },
    )
    max_alternations: int = field(
        default=5, metadata={"doc": "Localize/calibrate alternations at most.", "ge": 1, "le": 50}
    )
    layout: Literal["estimated", "cad"] = field(
        default="estimated",
        metadata={
            "doc": "Multi-marker: 'estimated' fits the printed sphere layout with the CAD "
            "as its prior at the phantom's print tolerance (phantom."
            "tolerance_position_mm) and reports it; 'cad' takes the CAD layout as exact "
            "(the paper's loss)."
        },
    )


@dataclass(frozen=True)
class EvaluationConfig:
    """Touch reference, DH refinement and the paper's cross-validation (Tables I, II)."""

    datasets: tuple[str, ...] = field(
        default=("A", "B", "C"),
        metadata={
            "doc": "Independent acquisitions (touches + sweeps, new phantom placement "
            "each); each uses the DH model refined from the others' touches. Fewer than "
            "two: no touches and no evaluation, the controller's kinematics are used."
        },
    )
    dh_regularizer: float = field(
        default=0.01, metadata={"doc": "Weight of ‖z‖² in the touch loss.", "ge": 0, "le": 100}
    )
    initialisations: int = field(
        default=12,
        metadata={"doc": "Deterministic initialisations of the DH fit.", "ge": 1, "le": 100},
    )
    dh_bound: float = field(
        default=10.0,
        metadata={
            "doc": "Bound of each scaled DH correction (° for Δθ, Δα; mm for Δd, Δa).",
            "gt": 0,
            "le": 90,
        },
    )
    stylus_tip_cad_mm: tuple[float, float, float] = field(
        default=(0.0, 0.0, 165.0),
        metadata={
            "doc": "Stylus tip offset in ee from the stylus drawing: the fit's start value "
            "(the fit estimates the true one)."
        },
    )
    placement_shift_mm: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: the phantom of each dataset after the first is put back "
            "up to ± this off (x, y) from the scenario's placement.",
            "ge": 0,
            "le": 50,
        },
    )
    placement_rotation_deg: float = field(
        default=10.0,
        metadata={
            "doc": "Simulation: and turned up to ± this about the vertical.",
            "ge": 0,
            "le": 45,
        },
    )
    session_shift_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Simulation: 1 σ per horizontal axis of the phantom's displacement "
            "between a dataset's touches and its sweeps (truth only; 0 = off): the tool "
            "exchange, stylus out and probe in, over a phantom standing in the tank, and "
            "the touches' own push. The touch reference then maps the CAD centres to "
            "where the phantom was, not where it is scanned. Est. 0–1 mm for a phantom "
            "held by weights or tape rather than clamped (no published figure; the paper "
            "lists stylus contact and remounting among its remaining errors, and its "
            "per-set accuracy varies 1.16–2.26 mm while its precision varies "
            "0.71–0.96 mm).",
            "ge": 0,
            "le": 10,
        },
    )
    workers: int = field(
        default=0,
        metadata={
            "doc": "Processes running the datasets and the reconstruction's tasks in "
            "parallel (0: one per core).",
            "ge": 0,
            "le": 64,
        },
    )


@dataclass(frozen=True)
class ReconstructionConfig:
    """Cone and prism reconstruction with ICP (Table III), run with the evaluation.

    Paper, "Volumetric Reconstruction of Different Phantoms"; it uses the evaluation's
    three DH models.
    """

    phantoms: tuple[Literal["cone", "prism"], ...] = field(
        default=("cone", "prism"),
        metadata={"doc": "Phantoms scanned and reconstructed (empty: no reconstruction)."},
    )
    central_frames: int = field(
        default=10, metadata={"doc": "Central frames of each sweep used.", "ge": 1, "le": 401}
    )
    icp_max_iterations: int = field(
        default=100, metadata={"doc": "ICP iterations at most.", "ge": 1, "le": 1000}
    )
    icp_points: int = field(
        default=2000,
        metadata={
            "doc": "Points (a random subset) driving the ICP iterations; the distances "
            "reported are those of all points.",
            "ge": 100,
            "le": 1_000_000,
        },
    )
    remount_position_mm: float = field(
        default=1.0,
        metadata={
            "doc": "Simulation: the probe taken off and put back before these scans; its "
            "true mount moves by this (1 σ per axis).",
            "ge": 0,
            "le": 20,
        },
    )
    remount_rotation_deg: float = field(
        default=1.0,
        metadata={"doc": "Simulation: and turns by this (1 σ about each axis).", "ge": 0, "le": 20},
    )
    placement_error_mm: float = field(
        default=5.0,
        metadata={
            "doc": "Simulation: the cone or prism stands up to ± this (x, y) off the "
            "scenario's phantom position, the nominal placement ICP starts from.",
            "ge": 0,
            "le": 50,
        },
    )
    placement_error_deg: float = field(
        default=5.0,
        metadata={
            "doc": "Simulation: and turned up to ± this about the vertical.",
            "ge": 0,
            "le": 45,
        },
    )
