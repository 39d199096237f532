"""What every sphere localizer takes and returns: its settings (:class:`LocalizerConfig`,
the scenario's ``localization`` section), one sweep's result (:class:`SweepLocalization`)
and where a sweep's frames lie in its reference frame (:func:`frame_offsets`).

The threshold-free localizer (:mod:`calib.localize.sphere` and its stages) and the
fixed-threshold baseline (:mod:`calib.localize.baseline`) both build on this module, and
neither on the other's internals.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from .. import se3
from ..records import Sweep

__all__ = ["LocalizerConfig", "SweepLocalization", "frame_offsets"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class LocalizerConfig:
    """Threshold-free sphere localization (paper, "Threshold-Free Sphere Localization")."""

    method: Literal["paper", "refined", "fixed_threshold"] = field(
        default="refined",
        metadata={
            "doc": "'paper': grid-point centres exactly as published; 'refined': "
            "brightness also above each depth's noise floor, the grid's best separate "
            "maxima looked at finely, a sphere's echo required to stop at the CAD radius "
            "(a flat reflector's runs on), the specular arc alone where the whole cap is "
            "not seen, and a sub-voxel centre from the cap's echo; 'fixed_threshold': the "
            "baseline the paper argues against (one absolute grey-level threshold, "
            "largest bright set, least-squares sphere; calib/localize/baseline.py)."
        },
    )
    fixed_threshold: int = field(
        default=120,
        metadata={
            "doc": "The fixed_threshold baseline's grey level (0-255), tuned once at the "
            "nominal gain and depth: the best of 60, 90, …, 240 by median error "
            "(scenarios/tune_fixed_threshold.yaml, seed 100); unused by the "
            "threshold-free methods.",
            "ge": 1,
            "le": 255,
        },
    )
    grid_mm: float = field(
        default=1.0,
        metadata={"doc": "Spacing of the exhaustive candidate-centre grid.", "gt": 0.05, "le": 5},
    )
    shell_samples: int = field(
        default=256,
        metadata={"doc": "Fibonacci directions on the proximal shell.", "ge": 8, "le": 511},
    )
    interior_samples: int = field(
        default=256, metadata={"doc": "Samples in the proximal half-ball.", "ge": 8, "le": 511}
    )
    refinement_passes: int = field(
        default=2, metadata={"doc": "Radial-band refinement passes.", "ge": 0, "le": 10}
    )
    profile_directions: int = field(
        default=64,
        metadata={
            "doc": "Fibonacci directions per trial radius of the radial brightness profile "
            "(averaged over all sweeps of the sphere, so a few dozen suffice).",
            "ge": 8,
            "le": 4096,
        },
    )
    refine_window_mm: float = field(
        default=2.0,
        metadata={
            "doc": "Refinement passes search ± this around the current centre.",
            "ge": 0,
            "le": 20,
        },
    )
    min_coverage: float = field(
        default=0.7,
        metadata={
            "doc": "A candidate needs at least this share of its shell and of its "
            "interior samples inside the acquired volume (partial caps are "
            "scored from their visible part; too small a part is noise).",
            "ge": 0,
            "le": 1,
        },
    )
    relocalize_window_mm: float = field(
        default=3.0,
        metadata={
            "doc": "After a calibration update, each sweep is re-stacked and searched ± "
            "this around its previous centre (the whole grid again when the best "
            "candidate lies on the window's edge, or the sweep had no centre).",
            "gt": 0,
            "le": 20,
        },
    )
    expected_depth_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Depth of the sphere centre the acquisition plan puts in the image. "
            "Method 'refined' searches only within ± expected_window_mm of it and of the "
            "image's centre line: a bright reflector elsewhere (the plate under the "
            "sphere, the tank floor) cannot win a sweep whose sphere is too faint to see. "
            "Unset in a scenario: protocol.target_depth_mm; `uscal calibrate` uses the "
            "depth a dataset recorded (the whole image if it recorded none).",
            "gt": 0,
            "le": 200,
        },
    )
    expected_window_mm: float = field(
        default=10.0,
        metadata={
            "doc": "Half-width of that window, laterally and in depth: it must cover the "
            "plan's in-plane offsets (protocol.translation_mm) and how far the taught "
            "pose may miss the target (3 × protocol.teaching_error_mm). Unset in a "
            "scenario: 10, or that need where the plan needs more (shown as derived by "
            "`uscal check`); a value set short of it is refused.",
            "gt": 0,
            "le": 200,
        },
    )
    min_score: float = field(
        default=0.2,
        metadata={
            "doc": "Detection confidence: a sweep whose best score (a difference of "
            "bright fractions, not an intensity) stays below this is rejected.",
            "ge": 0,
            "le": 1,
        },
    )


@dataclass(frozen=True)
class SweepLocalization:
    """Result for one sweep.

    ``centre`` (3,) metres in the sweep's reference frame (NaN when rejected); ``score`` the
    peak score; ``f_shell``/``f_interior`` its two fractions (their difference is the
    contrast; with ``method="refined"`` the score is the confined contrast ``f_shell −
    max(f_interior, f_outer)``); ``accepted`` and, if not, ``reason``.
    """

    target: str
    pose_id: int
    centre: Array
    score: float
    f_shell: float
    f_interior: float
    accepted: bool
    reason: str = ""
    f_outer: float = float("nan")  # bright share outside the sphere, probe side ("refined")


def frame_offsets(sweep: Sweep, T_ee_us: Array | None) -> Array:
    """Each frame's origin in the sweep's reference frame, (n, 3) metres.

    Without ``T_ee_us`` the frames sit on the elevational axis at the robot-measured
    distances along the sweep; with it, at their full offsets (in-plane shift included).
    """
    T = sweep.T_base_ee
    ref = sweep.reference_index
    if T_ee_us is None:
        t = T[:, :3, 3]
        direction = t[-1] - t[0]
        direction /= np.linalg.norm(direction)
        z = (t - t[ref]) @ direction
        return np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    T_base_us = T @ T_ee_us
    return se3.apply(se3.invert(T_base_us[ref]), T_base_us[:, :3, 3])
