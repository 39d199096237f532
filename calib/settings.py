"""Settings of the pipeline stages that follow localization: calibration, evaluation and
reconstruction (defaults: the paper's values)."""

from __future__ import annotations

from dataclasses import dataclass, field

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


@dataclass(frozen=True)
class EvaluationConfig:
    """Cross-validation of the paper (Tables I and II); read by the evaluation stage (to come)."""

    datasets: tuple[str, ...] = field(
        default=("A", "B", "C"), metadata={"doc": "Independent acquisitions (leave-one-out DH)."}
    )
    dh_regularizer: float = field(
        default=0.01, metadata={"doc": "Weight of ‖z‖² in the touch loss.", "ge": 0, "le": 100}
    )
    initialisations: int = field(
        default=12,
        metadata={"doc": "Deterministic initialisations of the DH fit.", "ge": 1, "le": 100},
    )


@dataclass(frozen=True)
class ReconstructionConfig:
    """Cone and prism reconstruction with ICP (Table III); read by a stage to come."""

    central_frames: int = field(
        default=10, metadata={"doc": "Central frames of each sweep used.", "ge": 1, "le": 401}
    )
    icp_max_iterations: int = field(
        default=50, metadata={"doc": "ICP iterations at most.", "ge": 1, "le": 1000}
    )
