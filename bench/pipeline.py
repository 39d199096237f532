"""The one path from a dataset to a calibration (the paper's §II–III), used alike by the
twin's single run, the paper's experiment, ``uscal calibrate`` on recorded data, the
sweeps and the budget:

1. the axial scale of the images (speed of sound, §II-A);
2. localize ↔ calibrate with one and with three markers (:func:`calibrate_markers`;
   §II-B–C, the alternation of :func:`calib.calibrate.alternate`);
3. the touch-based kinematics (:func:`touch_kinematics`; §II-D Steps 1–2): DH
   corrections from other datasets' touches, then this dataset's tool tip and phantom
   pose with that model frozen;
4. the cross-validation folds (:func:`run_folds`; §III) and their summary;
5. the declared systematic terms of each calibration's 95 % bounds
   (:func:`declared_uncertainty`; what ``metrics.json`` keeps of a calibration is
   :func:`bench.results.calibration_entry`).

No ground truth here: comparisons with the twin's truth live in :mod:`bench.truth`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib.calibrate import AlternationResult, alternate
from calib.dataset_files import AcquisitionInfo
from calib.errors import DatasetError
from calib.evaluate import FoldResult, evaluate_fold, folds
from calib.image import pixel_to_us
from calib.kinematics import DHRefinement, TouchReference, fit_reference, refine_dh
from calib.localization import LocalizerConfig
from calib.localize import localize_sphere
from calib.records import Dataset, Sweep, Touch
from calib.settings import EvaluationConfig
from calib.uncertainty import UncertaintyInputs
from sim_us.materials import water_speed_m_s

from .config.scenario import Scenario, layout_sigma_mm
from .progress import report

__all__ = [
    "THERMOMETER_UNCERTAINTY_C",
    "FoldRun",
    "MarkerCalibrations",
    "MethodInputs",
    "axial_scale",
    "axial_scale_of",
    "calibrate_markers",
    "declared_uncertainty",
    "fold_summary",
    "image_points",
    "residual_rms_mm",
    "run_folds",
    "scenario_uncertainty",
    "speed_ratio",
    "touch_kinematics",
]

Array = NDArray[np.float64]


# ------------------------------------------------------------------ the image's scale


def speed_ratio(
    correction: bool, medium: str, temperature_c: float, assumed_speed_m_s: float
) -> float:
    """c_medium / c_assumed when the speed-of-sound correction is on (the pipeline knows
    the water temperature a user reads off a thermometer), else 1; a medium other than
    water is taken at 1540 m/s."""
    if not correction:
        return 1.0
    c = water_speed_m_s(temperature_c) if medium == "water" else 1540.0
    return c / assumed_speed_m_s


def axial_scale(scenario: Scenario) -> float:
    """The axial spacing's correction factor of a scenario (:func:`speed_ratio`)."""
    return speed_ratio(
        scenario.imaging.sound_speed_correction,
        scenario.medium.kind,
        scenario.medium.temperature_c,
        scenario.imaging.assumed_speed_m_s,
    )


def axial_scale_of(info: AcquisitionInfo) -> float:
    """The axial spacing's correction factor of a recorded dataset (its water
    temperature)."""
    return speed_ratio(
        info.sound_speed_correction, info.medium, info.temperature_c, info.assumed_speed_m_s
    )


def image_points(scenario: Scenario, n: int = 21) -> Array:
    """An n × n grid of points (n², 3) covering the image, metres in the ``us`` frame."""
    probe = scenario.imaging
    spacing = (probe.width_mm * 1e-3 / (n - 1), probe.depth_mm * 1e-3 / (n - 1))
    P = pixel_to_us(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), n, spacing)
    return P.reshape(-1, 3)


# ------------------------------------------------------- single- and three-marker


@dataclass(frozen=True, eq=False)
class MethodInputs:
    """What the method takes besides the sweeps: the CAD sphere radius (m; the only
    prior on a sphere), the localizer's settings, the images' axial scale, the CAD
    sphere centres (phantom frame, m; for multi-marker fits and the folds' references),
    the coarse ``T_ee_us`` to check the start against (None: none known, e.g. a tracked
    probe's import), the alternation's limit and the printed
    layout's prior (1 σ per axis, mm; 0 takes the CAD layout as exact)."""

    radius: float
    localizer: LocalizerConfig
    axial_scale: float
    cad_centres: Mapping[str, Array]
    T_coarse: Array | None
    max_alternations: int
    layout_sigma_mm: float = 0.0

    @classmethod
    def of(
        cls,
        settings: Scenario,
        radius_mm: float,
        axial_scale: float,
        cad_centres: Mapping[str, Array],
        T_coarse: Array | None,
    ) -> MethodInputs:
        """The inputs with the localizer, alternation and layout settings of a scenario
        (a twin's own, or the settings ``uscal calibrate`` runs a recorded dataset with)."""
        return cls(
            radius_mm * 1e-3,
            settings.localization,
            axial_scale,
            cad_centres,
            T_coarse,
            settings.calibration.max_alternations,
            layout_sigma_mm(settings),
        )


@dataclass(frozen=True, eq=False)
class MarkerCalibrations:
    """The single-marker calibration (first sphere) and, with three or more spheres and
    ``markers`` 3, the three-marker one (first three)."""

    targets: list[str]
    single: AlternationResult | None
    three: AlternationResult | None


def calibrate_markers(
    dataset: Dataset, inputs: MethodInputs, markers: tuple[int, ...] = (1, 3)
) -> MarkerCalibrations:
    """Localize ↔ calibrate (the paper's alternation) with one and/or three markers;
    the three-marker fit estimates the printed layout at ``inputs.layout_sigma_mm`` (see
    :func:`calib.calibrate.calibrate`)."""
    targets = dataset.targets()
    by_target = {t: dataset.of(t) for t in targets}
    cad_centres = inputs.cad_centres
    if 3 in markers and len(targets) < 3 and 1 not in markers:
        raise DatasetError(
            f"dataset {dataset.name}: three-marker calibration needs sweeps of three "
            f"spheres; it has {', '.join(targets)}"
        )
    missing = [t for t in targets[:3] if t not in cad_centres]
    if 3 in markers and len(targets) >= 3 and missing:
        raise DatasetError(
            f"dataset {dataset.name}: no CAD centre for {', '.join(missing)} (acquisition."
            "landmarks_mm)"
        )
    run_three = 3 in markers and len(targets) >= 3
    n_cal = int(1 in markers) + int(run_three)
    common = (inputs.radius, inputs.localizer, inputs.axial_scale)
    report("calibrations", 0, n_cal)
    single = three = None
    if 1 in markers:
        single = alternate(
            {targets[0]: by_target[targets[0]]},
            *common,
            None,
            inputs.T_coarse,
            inputs.max_alternations,
        )
        report("calibrations", 1, n_cal)
    if run_three:
        three = alternate(
            {t: by_target[t] for t in targets[:3]},
            *common,
            {t: cad_centres[t] for t in targets[:3]},
            inputs.T_coarse,
            inputs.max_alternations,
            layout_sigma_mm=inputs.layout_sigma_mm,
        )
        report("calibrations", n_cal, n_cal)
    return MarkerCalibrations(targets, single, three)


# ------------------------------------------------------------ touch-based kinematics


def touch_kinematics(
    nominal,
    training: Sequence[Sequence[Touch]],
    own: Sequence[Touch],
    vertices: Mapping[str, Array],
    tip_cad: Array,
    ev: EvaluationConfig,
) -> tuple[DHRefinement, TouchReference]:
    """The paper's touch-based steps: DH corrections of the ``nominal`` table from the
    ``training`` touch sets (Step 1; the paper's leave-one-dataset-out), then, with that
    model frozen, the tool tip and phantom pose of a dataset from its ``own`` touches
    (Step 2: its reference)."""
    refinement = refine_dh(
        nominal,
        [list(t) for t in training],
        vertices,
        tip_cad,
        ev.dh_regularizer,
        ev.initialisations,
        ev.dh_bound,
    )
    return refinement, fit_reference(refinement.table, list(own), vertices, tip_cad)


def residual_rms_mm(residuals_mm: Array) -> float:
    """RMS of a fit's touch residuals (mm)."""
    return float(np.sqrt(np.mean(np.asarray(residuals_mm) ** 2)))


# ------------------------------------------------------------------------- the folds


@dataclass(frozen=True, eq=False)
class FoldRun:
    """A dataset's folds and the time they took (the shared initial localizations, then
    the folds' alternations)."""

    results: list[FoldResult]
    seconds_initial: float
    seconds_folds: float


def run_folds(
    name: str,
    sweeps: Mapping[str, Sequence[Sweep]],
    references: Mapping[str, Array],
    inputs: MethodInputs,
    progress: str = "folds",
    before_fold: Callable[[], None] | None = None,
) -> FoldRun:
    """The paper's folds of dataset ``name`` (§III: each sphere trained alone and tested
    on the others, then leave-one-out), each scored against the touch ``references``.
    Every sweep is localized once without a calibration, shared by all folds.
    ``before_fold`` runs before each fold (e.g. to release the frames' pages)."""
    targets = list(sweeps)
    common = (inputs.radius, inputs.localizer, inputs.axial_scale)
    t0 = time.perf_counter()
    initial = {t: localize_sphere(sweeps[t], None, *common) for t in targets}
    t_initial = time.perf_counter() - t0
    t0 = time.perf_counter()
    fold_list = folds(name, targets)
    results = []
    for k, fold in enumerate(fold_list):
        report(progress, k, len(fold_list))
        if before_fold is not None:
            before_fold()
        results.append(
            evaluate_fold(
                fold,
                sweeps,
                initial,
                references,
                *common,
                inputs.cad_centres,
                inputs.T_coarse,
                inputs.max_alternations,
                inputs.layout_sigma_mm,
            )
        )
    report(progress, len(fold_list), len(fold_list))
    return FoldRun(results, t_initial, time.perf_counter() - t0)


def fold_summary(results: Sequence[FoldResult]) -> dict[str, Any]:
    """Mean and SD over the folds' test spheres, per kind of fold (a dataset's Tables I
    and II in small)."""
    summary = {}
    for kind in ("single", "three"):
        acc = [v for r in results if r.fold.kind == kind for v in r.accuracy_mm.values()]
        prec = [v for r in results if r.fold.kind == kind for v in r.precision_mm.values()]
        if acc:
            summary[kind] = {
                "accuracy_mm": {"mean": float(np.mean(acc)), "sd": float(np.std(acc))},
                "precision_mm": {"mean": float(np.mean(prec)), "sd": float(np.std(prec))},
            }
    return summary


# --------------------------------------------------------------- bounds and entries

#: Uncertainty (°C) of the water temperature a user reads off a lab thermometer: with the
#: speed-of-sound correction, the axial scale is uncertain by the speed's change over it
#: (≈ 0.1 % at 20 °C, Marczak's formula).
THERMOMETER_UNCERTAINTY_C = 0.5


def declared_uncertainty(
    print_tolerance_mm: float,
    sound_speed_correction: bool,
    medium: str,
    temperature_c: float,
    assumed_speed_m_s: float,
    kinematic_residual_rms_mm: float = 0.0,
    radius_tolerance_mm: float = 0.0,
    axial_fwhm_mm: float = 0.0,
) -> UncertaintyInputs:
    """The systematic terms the pipeline knows of (:class:`calib.uncertainty.
    UncertaintyInputs`): the phantom's print specification (1 σ per axis of a sphere
    centre, 1 σ of a sphere's radius), the axial scale's uncertainty — with the
    speed-of-sound correction, the thermometer's; without, the whole difference
    between the medium's speed at the recorded temperature and the scanner's assumed
    one — the localizer's bias along the beam (uniform within ± half the probe's axial
    resolution, as 1 σ: FWHM / (2√3)) and the kinematic model's
    residual after a DH refinement (RMS distance of the touches from the model; per axis
    it is that over √3)."""
    ratio = speed_ratio(True, medium, temperature_c, assumed_speed_m_s)
    if sound_speed_correction:
        warmer = speed_ratio(
            True, medium, temperature_c + THERMOMETER_UNCERTAINTY_C, assumed_speed_m_s
        )
        scale_sigma = abs(warmer / ratio - 1.0)
    else:
        scale_sigma = abs(ratio - 1.0)
    return UncertaintyInputs(
        print_tolerance_m=print_tolerance_mm * 1e-3,
        radius_tolerance_m=radius_tolerance_mm * 1e-3,
        axial_bias_m=axial_fwhm_mm * 1e-3 / (2.0 * np.sqrt(3.0)),
        kinematic_sigma_m=kinematic_residual_rms_mm * 1e-3 / np.sqrt(3.0),
        axial_scale_sigma=scale_sigma,
    )


def scenario_uncertainty(
    scenario: Scenario, kinematic_residual_rms_mm: float = 0.0
) -> UncertaintyInputs:
    """:func:`declared_uncertainty` of a twin's scenario: its phantom's print tolerance
    as the print specification, its medium and speed-of-sound setting."""
    return declared_uncertainty(
        scenario.phantom.tolerance_position_mm,
        scenario.imaging.sound_speed_correction,
        scenario.medium.kind,
        scenario.medium.temperature_c,
        scenario.imaging.assumed_speed_m_s,
        kinematic_residual_rms_mm,
        scenario.phantom.tolerance_radius_mm,
        scenario.imaging.axial_fwhm_mm,
    )
