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

================================  ========================================================
package / module                  paper section
================================  ========================================================
``calib.pipeline``                the method end to end: its settings, the stages in order
``calib.acquisition``             §III-B/C what the robot does: ``protocol`` (the 45-sweep
                                  protocol, touches), ``planning`` (which sweeps, beyond
                                  the paper), ``observability`` (§III-B the information a
                                  plan gives, per kind of target)
``calib.targets``                 §III-B the kinds of target (sphere, wire, N-wire pattern,
                                  cone tip) and the residual each observation contributes
``calib.localize``                §III-E finding the targets in the images: the
                                  threshold-free sphere localizer, a module per stage
                                  (``settings`` ``volume`` ``search`` ``refine``
                                  ``consensus`` ``sphere``; ``baseline`` the fixed-threshold
                                  localizer the paper argues against), ``nwire`` (wires)
``calib.calibration``             §III-F ``T_ee_us`` from the targets: ``markers``
                                  (§III-F-1/2 single- and three-marker fit),
                                  ``alternation`` (§III-F), ``nwire`` (N-wire patterns),
                                  ``targets`` (any mix of kinds in one fit),
                                  ``uncertainty`` (95 % bounds) and ``verdict`` (beyond
                                  the paper)
``calib.kinematics`` ``dh``       §III-D touch-based DH refinement, the touch reference;
                                  the DH table
``calib.evaluation``              §III-F-3/§IV ``cross_validation`` (folds, Tables I–II),
                                  ``reconstruct`` (cone and prism, ICP, Table III)
``calib.files``                   ``dataset`` (dataset directories, the manifest),
                                  ``metafile`` (PLUS sequence files), ``plus_import``
                                  (PLUS recordings as datasets), ``plus_config`` (PLUS's
                                  device-set XML)
``calib.se3`` ``image``           shared maths: transforms, the one pixel ↔ image mapping,
``robust`` ``sound``              robust statistics, the speed of sound (beyond the paper)
``calib.records``                 the frozen records (frames, sweeps, touches, datasets)
``calib.errors`` ``progress``     the error hierarchy; stages' progress counts
================================  ========================================================

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
    "AlternationResult": "calibration.alternation",
    "AlternationSettings": "calibration.alternation",
    "alternate": "calibration.alternation",
    "CalibrationResult": "calibration.markers",
    "Observation": "calibration.markers",
    "MethodInputs": "pipeline",
    "MethodSettings": "pipeline",
    "calibrate_dataset": "pipeline",
    "calibrate_markers": "pipeline",
    "run_folds": "pipeline",
    "Bound95": "calibration.uncertainty",
    "UncertaintyInputs": "calibration.uncertainty",
    "bound95": "calibration.uncertainty",
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
