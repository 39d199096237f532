"""The calibration method of the paper: acquisition protocol, threshold-free sphere
localization, single/three-marker calibration, kinematic reference, evaluation,
reconstruction and observability.

Imports only numpy, scipy, scikit-image and trimesh (DESIGN.md §2).

The method's public API is importable from the package itself (``calib.LocalizerConfig``,
``calib.localize_sphere``, ``calib.alternate``, ...), one module per section of the paper:

==========================  ==============================================================
module                      paper section
==========================  ==============================================================
``calib.protocol``          acquisition protocol (45 sweeps, touches)
``calib.localize``          threshold-free sphere localization (§II-E), a module per stage:
                            ``settings`` (the localizer's settings, per-sweep result),
                            ``volume`` (adaptive brightness, the sweep volume), ``search``
                            (§II-E-3), ``refine`` (§II-E-4), ``consensus`` (the siblings,
                            the reasons a sweep is rejected), ``sphere`` (the stages in
                            order), ``baseline`` (the fixed-threshold localizer the paper
                            argues against)
``calib.calibrate``         single- and three-marker calibration, alternation
``calib.kinematics``        touch-based DH refinement and the touch reference
``calib.evaluate``          cross-validation folds, Tables I and II
``calib.reconstruct``       cone and prism reconstruction, ICP (Table III)
``calib.observability``     the information matrix of a plan
``calib.uncertainty``       95 % error bounds of a calibration (beyond the paper)
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
