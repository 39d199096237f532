"""Observability of pose plans (calib/acquisition/observability.py)."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.acquisition.observability import (
    information,
    jacobians,
    observability,
    planned_observations,
)
from calib.acquisition.protocol import ProtocolConfig, facing_pose, plan_sweeps
from calib.calibration.markers import Observation, calibrate

MM = 1e-3
X_TRUE = se3.make(se3.matrix_from_euler(np.radians([91.0, -0.8, 1.5])), [0.8e-3, -1.2e-3, 0.158])
CENTRE = np.array([0.275, -0.025, 0.02])


def paper_plan(cfg=None):
    cfg = cfg or ProtocolConfig()
    T_face = facing_pose(CENTRE, cfg.target_depth_mm * MM)
    plan = plan_sweeps("sphere_1", T_face @ se3.invert(X_TRUE), X_TRUE, cfg)
    T = np.array([p.T_base_ee[len(p.T_base_ee) // 2] for p in plan])
    return T, planned_observations(T, X_TRUE, CENTRE), T_face


def test_planned_observations_put_the_sphere_where_the_plan_aims():
    _, P, _ = paper_plan()
    assert P.shape == (45, 3)
    # Nominal pose: on the image centre line at the target depth.
    np.testing.assert_allclose(P[0], [0.0, 20 * MM, 0.0], atol=1e-12)
    # Rotations turn about the sphere: the five positions of each orientation share their
    # depth up to the ±3 mm in-plane offsets.
    assert np.abs(P[:, 0]).max() == pytest.approx(3 * MM, abs=1e-9)


def test_jacobian_matches_finite_differences():
    T, P, _ = paper_plan()
    G = jacobians(T, X_TRUE, P)
    h = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        R = se3.matrix_from_rotvec(d[:3]) @ X_TRUE[:3, :3]
        Xp = se3.make(R, X_TRUE[:3, 3] + d[3:] * MM)
        d[i] = -h
        R = se3.matrix_from_rotvec(d[:3]) @ X_TRUE[:3, :3]
        Xm = se3.make(R, X_TRUE[:3, 3] + d[3:] * MM)
        xp = se3.apply(T @ Xp, P)
        xm = se3.apply(T @ Xm, P)
        np.testing.assert_allclose(G[:, :, i], (xp - xm) / (2 * h) * 1e3, atol=1e-4)


@pytest.mark.parametrize("seed", range(5))
def test_a_wire_never_carries_more_information_than_a_sphere(seed):
    rng = np.random.default_rng(seed)
    if seed == 0:
        T, P, T_face = paper_plan()
        u = T_face[:3, 2]
    else:
        T = se3.exp(rng.normal(0, [0.3, 0.3, 0.3, 0.2, 0.2, 0.2], (30, 6)))
        P = rng.normal(0, 0.02, (30, 3))
        u = rng.normal(size=3)
    G = jacobians(T, X_TRUE, P)
    H_point = information(G)
    H_line = information(G, line_direction=u)
    diff = np.linalg.eigvalsh(H_point - H_line)
    assert diff.min() >= -1e-9 * np.abs(H_point).max()
    assert np.linalg.eigvalsh(H_line).min() <= np.linalg.eigvalsh(H_point).min() + 1e-9


def test_wider_translations_lever_the_rotation_better():
    T, P, _ = paper_plan()
    narrow = observability(information(jacobians(T, X_TRUE, P)))
    T, P, _ = paper_plan(ProtocolConfig(translation_mm=10.0))
    wide = observability(information(jacobians(T, X_TRUE, P)))
    assert wide.std_rotation_deg.max() < narrow.std_rotation_deg.max()
    assert wide.min_singular_value > narrow.min_singular_value


def test_predicted_covariance_matches_repeated_calibrations():
    """Monte Carlo: 150 single-marker calibrations of the paper plan with 0.1 mm isotropic
    localization noise; the spread of the estimates matches σ² H̃⁻¹ within 25 %."""
    T, P, _ = paper_plan()
    sigma = 0.1
    pred = observability(information(jacobians(T, X_TRUE, P)), noise_mm=sigma)
    rng = np.random.default_rng(7)
    errors = []
    for _ in range(150):
        noisy = P + rng.normal(0, sigma * MM, P.shape)
        obs = [Observation("sphere_1", k, noisy[k], T[k]) for k in range(len(T))]
        X = calibrate(obs).T_ee_us
        w = se3.rotvec_from_matrix(X[:3, :3] @ X_TRUE[:3, :3].T)
        errors.append(np.concatenate([w, (X[:3, 3] - X_TRUE[:3, 3]) * 1e3]))
    emp = np.std(np.array(errors), axis=0, ddof=1)
    predicted = np.sqrt(np.diag(pred.covariance))
    ratio = emp / predicted
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
