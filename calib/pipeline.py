"""The method end to end (the paper's §III, evaluated as in §IV-A), from a
:class:`~calib.records.Dataset` and frozen settings; the twin's runs, the paper's
experiment, ``uscal calibrate``, the sweeps and the budget all go through it, and a
script with its own data can too.

:func:`calibrate_dataset` is the front door for a recorded dataset; it orders the
stages, each also callable alone:

1. the axial scale of the images (:func:`axial_scale`; speed of sound, beyond the paper);
2. with touches, the touch-based kinematics (:func:`touch_kinematics`; §III-D Steps
   1–2): DH corrections from the training datasets' touches, then this dataset's tool
   tip and phantom pose with that model frozen; every frame's flange pose recomputed
   through the refined model;
3. localize ↔ calibrate with one and with three markers (:func:`calibrate_markers`;
   §III-E–F, the alternation of :func:`calib.calibration.alternation.alternate`);
4. each calibration's 95 % error bounds (:func:`declared_uncertainty` and
   :func:`calib.calibration.uncertainty.alternation_bound`);
5. with touches, the cross-validation folds (:func:`run_folds`; §III-F-3, "Evaluation
   protocol") and their summary.

No ground truth here, and nothing of the test bench: comparisons with a twin's truth
live in ``bench.truth``.

Examples
--------
>>> from calib.pipeline import MethodSettings, calibrate_dataset  # doctest: +SKIP
>>> from calib.files.dataset import read_dataset  # doctest: +SKIP
>>> dataset, info = read_dataset("my_dataset")  # doctest: +SKIP
>>> result = calibrate_dataset(dataset, info, MethodSettings())  # doctest: +SKIP
>>> result.calibrations.single.result.T_ee_us  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .calibration.alternation import AlternationResult, AlternationSettings, alternate
from .calibration.uncertainty import Bound95, UncertaintyInputs, alternation_bound, image_grid
from .dh import DHTable
from .errors import DatasetError
from .evaluation.cross_validation import EvaluationConfig, FoldResult, evaluate_fold, folds
from .files.dataset import AcquisitionInfo
from .kinematics import (
    DHRefinement,
    TouchReference,
    fit_reference,
    kinematic_modes,
    refine_dh,
    with_kinematics,
)
from .localize import LocalizerConfig, localize_sphere
from .progress import report
from .records import Dataset, Sweep, Touch
from .sound import speed_ratio

__all__ = [
    "THERMOMETER_UNCERTAINTY_C",
    "DatasetCalibration",
    "FoldRun",
    "MarkerCalibrations",
    "MethodInputs",
    "MethodSettings",
    "axial_scale",
    "calibrate_dataset",
    "calibrate_markers",
    "declared_uncertainty",
    "fold_summary",
    "refinement_modes",
    "residual_rms_mm",
    "run_folds",
    "touch_kinematics",
]

Array = NDArray[np.float64]


# ---------------------------------------------------------------------- the settings


@dataclass(frozen=True)
class MethodSettings:
    """The method's settings, as a lab fixes them once for its rig (a scenario's
    ``localization``, ``calibration`` and ``evaluation`` sections map onto them).

    Attributes
    ----------
    localizer : the localizer's settings
    max_alternations : int
        Localize/calibrate alternations at most.
    layout_sigma_mm : float
        Multi-marker: the printed layout's prior (1 σ per axis of a sphere centre, mm);
        0 takes the CAD layout as exact (the paper's loss).
    evaluation : the touch-based DH refinement's settings
    print_tolerance_mm, radius_tolerance_mm : float
        The phantom's print specification (1 σ per axis of a sphere centre; of a radius):
        systematic terms of the bounds.
    axial_fwhm_mm : float
        The probe's axial resolution (FWHM): the localizer's bias along the beam is taken
        as uniform within ± half of it.
    mount_error_mm, mount_error_deg : float
        The rig's own error of the mount's position and orientation that no view shows
        (1 σ per axis, declared: :class:`calib.calibration.markers.CalibrationConfig`).
    nominal_dh : DHTable or None
        The arm's nominal kinematic model, which the touches refine (a dataset with
        touches needs it).
    """

    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    max_alternations: int = 10
    layout_sigma_mm: float = 0.0
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    print_tolerance_mm: float = 0.0
    radius_tolerance_mm: float = 0.0
    axial_fwhm_mm: float = 0.0
    mount_error_mm: float = 0.0
    mount_error_deg: float = 0.0
    nominal_dh: DHTable | None = None

    def alternation(
        self, *, axial_scale: float, localizer: LocalizerConfig | None = None
    ) -> AlternationSettings:
        """How the alternation runs with these settings on images of ``axial_scale``
        (``localizer``: these settings' localizer, or one adapted to the dataset)."""
        return AlternationSettings(
            self.localizer if localizer is None else localizer,
            axial_scale=axial_scale,
            max_iterations=self.max_alternations,
            layout_sigma_mm=self.layout_sigma_mm,
        )


@dataclass(frozen=True, eq=False)
class MethodInputs:
    """What the calibration of one acquisition takes besides its sweeps: the CAD sphere
    radius (m; the only prior on a sphere), the CAD sphere centres (phantom frame, m; for
    multi-marker fits and the folds' references), the coarse ``T_ee_us`` to check the
    start against (None: none known, e.g. a tracked probe's import), and how the
    alternation runs (its localizer, the images' axial scale, its limit and the printed
    layout's prior)."""

    radius: float
    cad_centres: Mapping[str, Array]
    T_coarse: Array | None
    alternation: AlternationSettings


# ------------------------------------------------------------------ the image's scale


def axial_scale(info: AcquisitionInfo) -> float:
    """The axial spacing's correction factor of a recorded dataset (its medium and water
    temperature; :func:`calib.sound.speed_ratio`)."""
    return speed_ratio(
        correction=info.sound_speed_correction,
        medium=info.medium,
        temperature_c=info.temperature_c,
        assumed_speed_m_s=info.assumed_speed_m_s,
    )


# ------------------------------------------------------- single- and three-marker


@dataclass(frozen=True, eq=False)
class MarkerCalibrations:
    """The single-marker calibration (first sphere) and, with three or more spheres and
    ``markers`` 3, the three-marker one (first three)."""

    targets: list[str]
    single: AlternationResult | None
    three: AlternationResult | None


def calibrate_markers(
    dataset: Dataset, inputs: MethodInputs, *, markers: tuple[int, ...] = (1, 3)
) -> MarkerCalibrations:
    """Localize ↔ calibrate (the paper's alternation) with one and/or three markers;
    the three-marker fit estimates the printed layout at
    ``inputs.alternation.layout_sigma_mm`` (see :func:`calib.calibration.markers.calibrate`)."""
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
    report("calibrations", 0, n_cal)
    single = three = None
    if 1 in markers:
        single = alternate(
            {targets[0]: by_target[targets[0]]},
            inputs.radius,
            inputs.alternation,
            T_coarse=inputs.T_coarse,
        )
        report("calibrations", 1, n_cal)
    if run_three:
        three = alternate(
            {t: by_target[t] for t in targets[:3]},
            inputs.radius,
            inputs.alternation,
            cad_centres={t: cad_centres[t] for t in targets[:3]},
            T_coarse=inputs.T_coarse,
        )
        report("calibrations", n_cal, n_cal)
    return MarkerCalibrations(targets, single, three)


# ------------------------------------------------------------ touch-based kinematics


def touch_kinematics(
    nominal: DHTable,
    training: Sequence[Sequence[Touch]],
    own: Sequence[Touch],
    *,
    vertices: Mapping[str, Array],
    tip_cad: Array,
    evaluation: EvaluationConfig,
) -> tuple[DHRefinement, TouchReference]:
    """The paper's touch-based steps: DH corrections of the ``nominal`` table from the
    ``training`` touch sets (Step 1; the paper's leave-one-dataset-out), then, with that
    model frozen, the tool tip and phantom pose of a dataset from its ``own`` touches
    (Step 2: its reference). ``vertices``: the CAD touch targets (phantom frame, m);
    ``tip_cad``: the stylus tip in the flange frame (m), the fit's start."""
    refinement = refine_dh(
        nominal,
        [list(t) for t in training],
        vertices,
        tip_cad,
        regularizer=evaluation.dh_regularizer,
        initialisations=evaluation.initialisations,
        bound=evaluation.dh_bound,
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
    *,
    progress: str = "folds",
    before_fold: Callable[[], None] | None = None,
) -> FoldRun:
    """The paper's folds of dataset ``name`` (§III-F-3: each sphere trained alone and tested
    on the others, then leave-one-out), each scored against the touch ``references``.
    Every sweep is localized once without a calibration, shared by all folds.
    ``before_fold`` runs before each fold (e.g. to release the frames' pages)."""
    targets = list(sweeps)
    alternation = inputs.alternation
    t0 = time.perf_counter()
    initial = {
        t: localize_sphere(
            sweeps[t],
            None,
            inputs.radius,
            alternation.localizer,
            axial_scale=alternation.axial_scale,
        )
        for t in targets
    }
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
                inputs.radius,
                alternation,
                cad_centres=inputs.cad_centres,
                T_coarse=inputs.T_coarse,
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


# --------------------------------------------------------------------- the bounds

#: Uncertainty (°C) of the water temperature a user reads off a lab thermometer: with the
#: speed-of-sound correction, the axial scale is uncertain by the speed's change over it
#: (≈ 0.1 % at 20 °C, Marczak's formula).
THERMOMETER_UNCERTAINTY_C = 0.5


def declared_uncertainty(
    *,
    print_tolerance_mm: float,
    sound_speed_correction: bool,
    medium: str,
    temperature_c: float,
    assumed_speed_m_s: float,
    kinematic_residual_rms_mm: float = 0.0,
    radius_tolerance_mm: float = 0.0,
    axial_fwhm_mm: float = 0.0,
    kinematic_modes: Mapping[tuple[str, int], Array] | None = None,
    mount_error_mm: float = 0.0,
    mount_error_deg: float = 0.0,
) -> UncertaintyInputs:
    """The systematic terms the pipeline knows of (:class:`calib.calibration.uncertainty.
    UncertaintyInputs`): the phantom's print specification (1 σ per axis of a sphere
    centre, 1 σ of a sphere's radius), the axial scale's uncertainty — with the
    speed-of-sound correction, the thermometer's; without, the whole difference
    between the medium's speed at the recorded temperature and the scanner's assumed
    one — the localizer's bias along the beam (uniform within ± half the probe's axial
    resolution, as 1 σ: FWHM / (2√3)) and the kinematic model's
    residual after a DH refinement (RMS distance of the touches from the model; per axis
    it is that over √3; reported, and used only where the refinement's own error at the
    sweeps' poses, ``kinematic_modes``, is not known), and the rig's own error of the
    mount that no view shows (``mount_error_mm``, ``mount_error_deg``: 1 σ per axis, as
    declared)."""

    def ratio_at(t_c: float) -> float:
        return speed_ratio(
            correction=True, medium=medium, temperature_c=t_c, assumed_speed_m_s=assumed_speed_m_s
        )

    ratio = ratio_at(temperature_c)
    if sound_speed_correction:
        scale_sigma = abs(ratio_at(temperature_c + THERMOMETER_UNCERTAINTY_C) / ratio - 1.0)
    else:
        scale_sigma = abs(ratio - 1.0)
    return UncertaintyInputs(
        print_tolerance_m=print_tolerance_mm * 1e-3,
        radius_tolerance_m=radius_tolerance_mm * 1e-3,
        axial_bias_m=axial_fwhm_mm * 1e-3 / (2.0 * np.sqrt(3.0)),
        kinematic_sigma_m=kinematic_residual_rms_mm * 1e-3 / np.sqrt(3.0),
        axial_scale_sigma=scale_sigma,
        kinematic_modes=kinematic_modes,
        mount_sigma_m=mount_error_mm * 1e-3,
        mount_sigma_rad=np.radians(mount_error_deg),
    )


# ------------------------------------------------------------ a recorded dataset


@dataclass(frozen=True, eq=False)
class DatasetCalibration:
    """Everything :func:`calibrate_dataset` found.

    Attributes
    ----------
    dataset : the dataset as calibrated (with touches: every flange pose recomputed
        through the refined DH model)
    axial_scale : the images' axial correction factor
    localizer : the localizer's settings as run (the search depth the dataset recorded)
    calibrations : the single- and three-marker calibrations
    bounds : "single" / "three" → the 95 % bounds and their declared terms
    refinement, reference : the touch-based steps' results (None without touches)
    dh_from : the names of the datasets the DH model was refined from
    folds : the paper's folds against the touch reference (None: no touches, or one
        sphere)
    seconds_dh : time of the touch-based kinematics
    """

    dataset: Dataset
    axial_scale: float
    localizer: LocalizerConfig
    calibrations: MarkerCalibrations
    bounds: dict[str, tuple[Bound95, UncertaintyInputs]]
    refinement: DHRefinement | None = None
    reference: TouchReference | None = None
    dh_from: tuple[str, ...] = ()
    folds: FoldRun | None = None
    seconds_dh: float = 0.0

    @property
    def dh_table(self) -> DHTable | None:
        """The refined DH model (None: the controller's own, no touches)."""
        return None if self.refinement is None else self.refinement.table

    @property
    def kinematic_rms_mm(self) -> float:
        """RMS of the DH refinement's touch residuals (0 without touches: none known)."""
        return _kinematic_rms_mm(self.refinement)


def calibrate_dataset(
    dataset: Dataset,
    info: AcquisitionInfo,
    settings: MethodSettings,
    *,
    markers: tuple[int, ...] = (1, 3),
    dh_from: Sequence[Dataset] = (),
) -> DatasetCalibration:
    """The whole method on a recorded dataset (no ground truth: precision, the
    calibrations' own uncertainty, and consistency between the spheres).

    With touches in the dataset, the paper's evaluation follows: the DH model refined
    from the touches of the ``dh_from`` datasets (this dataset's own when none), every
    frame's flange pose recomputed from its joint angles with it, this dataset's touch
    reference, and the paper's folds (each sphere trained alone and tested on the others,
    then leave-one-out) scored by precision and accuracy against the touch reference.
    ``info``: the acquisition's facts (CAD radius and landmarks, medium, coarse mount;
    :class:`calib.files.dataset.AcquisitionInfo`).

    Raises
    ------
    DatasetError
        Touches but no ``vertex_*`` landmarks, no stylus tip or no nominal DH model;
        ``dh_from`` datasets without touches; too few spheres for ``markers``.
    """
    for d in dh_from:
        if not d.touches:
            raise DatasetError(f"--dh-from: dataset {d.name} has no touches")
    if dh_from and not dataset.touches:
        raise DatasetError(f"--dh-from: dataset {dataset.name} itself has no touches")
    # Where this dataset's plan put the spheres, not where the settings' protocol would
    # (a dataset that did not record it is searched over the whole image).
    localizer = dataclasses.replace(settings.localizer, expected_depth_mm=info.target_depth_mm)
    scale = axial_scale(info)
    cad = {k: v for k, v in info.landmarks.items() if k.startswith("sphere_")}
    refinement = reference = None
    sources: tuple[str, ...] = ()
    seconds_dh = 0.0
    if dataset.touches:
        t1 = time.perf_counter()
        refinement, reference, sources = _touch_steps(dataset, info, settings, dh_from)
        dataset = Dataset(
            dataset.name,
            tuple(
                s
                for t in dataset.targets()
                for s in with_kinematics(dataset.of(t), refinement.table)
            ),
            dataset.meta,
            dataset.touches,
        )
        seconds_dh = time.perf_counter() - t1
    inputs = MethodInputs(
        info.sphere_radius_mm * 1e-3,
        cad,
        info.T_ee_us_coarse,
        settings.alternation(axial_scale=scale, localizer=localizer),
    )
    cals = calibrate_markers(dataset, inputs, markers=markers)
    # The bounds' declared terms: the settings' print specification of the phantom, the
    # recorded medium, the refinement's residual.
    declared = declared_uncertainty(
        print_tolerance_mm=settings.print_tolerance_mm,
        sound_speed_correction=info.sound_speed_correction,
        medium=info.medium,
        temperature_c=info.temperature_c,
        assumed_speed_m_s=info.assumed_speed_m_s,
        kinematic_residual_rms_mm=_kinematic_rms_mm(refinement),
        radius_tolerance_mm=settings.radius_tolerance_mm,
        axial_fwhm_mm=settings.axial_fwhm_mm,
        kinematic_modes=refinement_modes(refinement, dataset.sweeps),
        mount_error_mm=settings.mount_error_mm,
        mount_error_deg=settings.mount_error_deg,
    )
    sweep0 = dataset.sweeps[0]
    H, W = sweep0.images.shape[1:]
    grid = image_grid((W - 1) * sweep0.spacing[0], (H - 1) * sweep0.spacing[1] * scale)
    bounds = {}
    if cals.single is not None:
        bounds["single"] = (
            alternation_bound(cals.single, grid, cad_centres=None, inputs=declared),
            declared,
        )
    if cals.three is not None:
        multi = {t: cad[t] for t in cals.targets[:3]}
        bounds["three"] = (
            alternation_bound(cals.three, grid, cad_centres=multi, inputs=declared),
            declared,
        )
    fold_run = None
    if reference is not None and len(cals.targets) >= 2:
        targets = dataset.targets()
        fold_run = run_folds(
            dataset.name,
            {t: dataset.of(t) for t in targets},
            reference.reference_points({t: cad[t] for t in targets}),
            inputs,
        )
    return DatasetCalibration(
        dataset,
        scale,
        localizer,
        cals,
        bounds,
        refinement=refinement,
        reference=reference,
        dh_from=sources,
        folds=fold_run,
        seconds_dh=seconds_dh,
    )


def refinement_modes(
    refinement: DHRefinement | None, sweeps: Sequence[Sweep]
) -> dict[tuple[str, int], Array] | None:
    """:func:`calib.kinematics.kinematic_modes` of a DH refinement at the sweeps' poses
    (None without one, or without its covariance)."""
    if refinement is None or refinement.covariance is None:
        return None
    return kinematic_modes(refinement.table, refinement.covariance, sweeps)


def _kinematic_rms_mm(refinement: DHRefinement | None) -> float:
    """The DH refinement's touch residual RMS (mm); 0 without one (the controller's own
    model: no residual known)."""
    return 0.0 if refinement is None else residual_rms_mm(refinement.residuals_mm)


def _touch_steps(
    dataset: Dataset, info: AcquisitionInfo, settings: MethodSettings, dh_from: Sequence[Dataset]
) -> tuple[DHRefinement, TouchReference, tuple[str, ...]]:
    """:func:`touch_kinematics` on recorded data: DH corrections from the touches of
    ``dh_from`` (the paper's leave-one-dataset-out; this dataset's own when empty), then
    this dataset's reference with that model frozen."""
    vertices = {k: v for k, v in info.landmarks.items() if k.startswith("vertex_")}
    if not vertices:
        raise DatasetError(f"dataset {dataset.name}: touches but no vertex_* landmarks")
    if info.stylus_tip_cad_mm is None:
        raise DatasetError(f"dataset {dataset.name}: touches but no stylus_tip_cad_mm")
    if settings.nominal_dh is None:
        raise DatasetError(
            f"dataset {dataset.name}: touches, but the settings name no nominal DH model to refine"
        )
    tip = np.asarray(info.stylus_tip_cad_mm, dtype=float) * 1e-3
    sources = list(dh_from) or [dataset]
    refinement, reference = touch_kinematics(
        settings.nominal_dh,
        [d.touches for d in sources],
        dataset.touches,
        vertices=vertices,
        tip_cad=tip,
        evaluation=settings.evaluation,
    )
    return refinement, reference, tuple(d.name for d in sources)
