"""Geometric B-mode simulator: turns a probe pose and a scene into the uint8 frame a
frame grabber would deliver. Imports only numpy, scipy, scikit-image and trimesh."""

from .probe import MediumConfig, ProbeConfig

__all__ = ["MediumConfig", "ProbeConfig"]
