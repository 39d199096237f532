"""Geometric B-mode simulator: turns a probe pose and a scene into the uint8 frame a
frame grabber would deliver.

Imports numpy, scipy, scikit-image, trimesh, numba and embreex (the ray caster), and of
calib only its shared maths: ``calib.se3`` (transforms), ``calib.image`` (the pixel ↔
image mapping) and ``calib.sound`` (the speed of sound in water); DESIGN.md §2."""

from .probe import MediumConfig, ProbeConfig

__all__ = ["MediumConfig", "ProbeConfig"]
