"""Acquisition (paper §III-B, §III-C): what the robot does before any image is read.

``protocol`` the paper's 45-pose sweep protocol and the touch poses; ``planning`` which
sweeps to acquire beyond the paper's fixed grid; ``observability`` the information
matrix a set of observations gives the calibration, per kind of target (§III-B).
"""
