"""The calibration method of the paper: acquisition protocol, threshold-free sphere
localization, single/three-marker calibration, kinematic reference, evaluation,
reconstruction and observability.

Imports only numpy, scipy, scikit-image and trimesh (DESIGN.md §2).
"""
