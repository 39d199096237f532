"""The calibration method of the paper: acquisition protocol, threshold-free sphere
localization, single/three-marker calibration, kinematic reference, evaluation,
reconstruction and observability — the whole method from a dataset to a calibration
(:mod:`calib.pipeline`), with nothing of the test bench, the twin or the simulator.

Imports numpy, scipy, scikit-image, trimesh (with rtree) and numba (the compiled
kernels, each saying why it is hand-written); YAML only for the dataset manifest
(DESIGN.md §2).

The method's public API is importable from the package itself (``calib.LocalizerConfig``,
``calib.localize_sphere``, ``calib.alternate``, ``calib.calibrate_dataset``, ...), one
module per section of the paper (§III Methods, §IV Experiments):

==========================  ==============================================================
module                      paper section
==========================  ==============================================================
``calib.pipeline``          the method end to end: its settings, the stages in order
``calib.protocol``          §III-C multi-pose sphere acquisition (45 sweeps), touches
``calib.localize``          §III-E threshold-free sphere localization, a module per stage:
                            ``settings`` (the localizer's settings, per-sweep result),
                            ``volume`` (§III-E-1/2 adaptive brightness, the sweep
                            volume), ``search`` (§III-E-3), ``refine`` (§III-E-4),
                            ``consensus`` (the siblings, the reasons a sweep is
                            rejected), ``sphere`` (the stages in order), ``baseline``
                            (the fixed-threshold localizer the paper argues against)
``calib.calibrate``         §III-F-1/2 single- and three-marker calibration (the fit)
``calib.alternation``       §III-F the alternation of localization and calibration
``calib.kinematics``        §III-D touch-based DH refinement and the touch reference
``calib.evaluate``          §III-F-3 cross-validation folds, Tables I–III (§IV)
``calib.reconstruct``       §IV-B cone and prism reconstruction, ICP (Table III)
``calib.observability``     §III-B the information matrix of a plan (sphere vs wire)
``calib.planning``          which sweeps to acquire (beyond the paper)
``calib.uncertainty``       95 % error bounds of a calibration (beyond the paper)
``calib.sound``             the speed of sound, the images' axial scale (beyond the paper)
``calib.se3`` ``image``     shared maths: transforms, the one pixel ↔ image mapping,
``dh`` ``robust``           the DH table, robust statistics
``calib.records``           the frozen records (frames, sweeps, touches, datasets)
``calib.dataset_files``     dataset directories (manifest); ``metafile`` PLUS sequence
                            files; ``plus_import`` PLUS recordings as datasets
``calib.errors``            the error hierarchy; ``progress`` stages' progress counts
==========================  ==============================================================

The names load lazily (PEP 562): ``from calib import se3`` stays as light as that module,
so the twin and the hardware adapter, which use only the shared maths, do not load the
localizer's compiled kernels.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name → the module that defines it.
_EXPORTS = {
    "LocalizerConfig": "localize.settings",
    "SweepLocalization": "localize.settings",
    "frame_offsets": "localize.settings",
    "SweepVolume": "localize.volume",
    "stack_sweep": "localize.volume",
    "localize_sphere": "localize.sphere",
    "sphere_profile": "localize.sphere",
    "localize_sphere_fixed_threshold": "localize.baseline",
    "AlternationResult": "alternation",
    "AlternationSettings": "alternation",
    "alternate": "alternation",
    "CalibrationResult": "calibrate",
    "Observation": "calibrate",
    "MethodInputs": "pipeline",
    "MethodSettings": "pipeline",
    "calibrate_dataset": "pipeline",
    "calibrate_markers": "pipeline",
    "run_folds": "pipeline",
    "Bound95": "uncertainty",
    "UncertaintyInputs": "uncertainty",
    "bound95": "uncertainty",
    "Dataset": "records",
    "Sweep": "records",
    "Touch": "records",
    "CalibrationError": "errors",
    "LocalizationError": "errors",
    "UscalError": "errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'calib' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
