"""Calibration on synthetic observations: exact recovery, initialisation, outliers."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.acquisition.protocol import ProtocolConfig, plan_sweeps
from calib.calibration.markers import (
    Observation,
    calibrate,
    centres_in_base,
    consensus_initialisation,
    linear_initialisation,
)
from calib.errors import CalibrationError

MM = 1e-3
T_EE_US_TRUE = se3.make(
    se3.matrix_from_euler(np.radians([91.0, -0.8, 1.5])), [0.8e-3, -1.2e-3, 0.158]
)


def observations(centre_base, target="sphere_1", noise_mm=0.0, rng=None, X=T_EE_US_TRUE):
    """Noise-free (or noisy) localized centres from the paper's 45-pose plan."""
    cfg = ProtocolConfig()
    depth = cfg.target_depth_mm * MM
    T_face_us = se3.make(
        np.column_stack([[0, 1, 0], [0, 0, -1], [-1, 0, 0]]), centre_base + np.array([0, 0, depth])
    )
    T_taught = T_face_us @ se3.invert(X)
    obs = []
    for sweep in plan_sweeps(target, T_taught, X, cfg):
        T_ref = sweep.T_base_ee[len(sweep.T_base_ee) // 2]
        p = se3.apply(se3.invert(T_ref @ X), centre_base)
        if noise_mm:
            p = p + rng.normal(0, noise_mm * MM, 3)
        obs.append(Observation(target, sweep.pose_id, p, T_ref))
    return obs


def pose_errors(T_est, T_true=T_EE_US_TRUE):
    return (
        1e3 * se3.translation_distance(T_est, T_true),
        np.degrees(se3.rotation_angle(T_est, T_true)),
    )


def test_linear_initialisation_is_exact_on_noise_free_points():
    obs = observations(np.array([0.3, 0.02, 0.02]))
    d_mm, d_deg = pose_errors(linear_initialisation(obs))
    assert d_mm < 1e-6 and d_deg < 1e-6


def test_single_marker_recovers_exactly():
    obs = observations(np.array([0.3, -0.02, 0.02]))
    res = calibrate(obs)
    d_mm, d_deg = pose_errors(res.T_ee_us)
    assert d_mm < 1e-6 and d_deg < 1e-6
    assert res.retained.all() and res.cost < 1e-9
    np.testing.assert_allclose(
        centres_in_base(obs, res.T_ee_us), [[0.3, -0.02, 0.02]] * 45, atol=1e-9
    )


@pytest.mark.parametrize("dt_mm,dr_deg", [(10.0, 20.0), (-10.0, -20.0)])
def test_converges_from_a_bad_start(dt_mm, dr_deg):
    obs = observations(np.array([0.3, 0.0, 0.02]))
    start = T_EE_US_TRUE @ se3.make(
        se3.matrix_from_euler(np.radians([dr_deg] * 3)), [dt_mm * MM] * 3
    )
    d_mm, d_deg = pose_errors(calibrate(obs, T_init=start).T_ee_us)
    assert d_mm < 1e-5 and d_deg < 1e-5


def test_three_marker_recovers_transform_and_phantom_pose():
    cad = {
        "sphere_1": np.array([-0.025, -0.025, 0.02]),
        "sphere_2": np.array([0.025, -0.025, 0.02]),
        "sphere_3": np.array([0.025, 0.025, 0.02]),
    }
    Y = se3.make(se3.matrix_from_euler(np.radians([0.5, -0.3, 4.0])), [0.3, 0.01, 0.0])
    obs = []
    for name, c in cad.items():
        obs += observations(se3.apply(Y, c), name)
    res = calibrate(obs, cad)
    d_mm, d_deg = pose_errors(res.T_ee_us)
    assert d_mm < 1e-6 and d_deg < 1e-6
    assert se3.translation_distance(res.T_base_phantom, Y) < 1e-9


def test_noise_gives_physical_errors_and_outliers_are_rejected(rng):
    obs = observations(np.array([0.3, 0.0, 0.02]), noise_mm=0.15, rng=rng)
    bad = obs[7]
    obs[7] = Observation(
        bad.target, bad.pose_id, bad.p_us + np.array([0.0, 0.010, 0.0]), bad.T_base_ee
    )
    res = calibrate(obs)
    assert not res.retained[7] and res.retained.sum() == 44
    assert "sphere_1/7" in res.rejection_reasons
    assert "from the centroid" in res.rejection_reasons["sphere_1/7"]
    d_mm, d_deg = pose_errors(res.T_ee_us)
    assert d_mm < 1.0 and d_deg < 1.0
    # The covariance is a real uncertainty: positive definite, of the noise's scale.
    sd = np.sqrt(np.diag(res.covariance))
    assert np.all(np.isfinite(sd)) and 1e-6 < sd[3:].max() < 2e-3


def test_reported_covariance_matches_repeated_calibrations(rng):
    """The covariance a calibration reports is the spread of its estimate: 80 noisy
    calibrations (0.15 mm per axis) scatter, per component of (rotation vector in ee,
    translation), as the reported standard deviations say (within ±35 %)."""
    errors, reported = [], []
    for _ in range(80):
        res = calibrate(observations(np.array([0.3, 0.0, 0.02]), noise_mm=0.15, rng=rng))
        dR = res.T_ee_us[:3, :3] @ T_EE_US_TRUE[:3, :3].T
        dt = res.T_ee_us[:3, 3] - T_EE_US_TRUE[:3, 3]
        errors.append(np.concatenate([se3.rotvec_from_matrix(dR), dt]))
        reported.append(np.sqrt(np.diag(res.covariance)))
    ratio = np.std(errors, axis=0) / np.mean(reported, axis=0)
    assert np.all((ratio > 0.65) & (ratio < 1.35)), ratio


def test_too_few_observations():
    obs = observations(np.array([0.3, 0.0, 0.02]))[:3]
    with pytest.raises(CalibrationError, match="at least 4"):
        calibrate(obs)


CAD_LAYOUT = {
    "sphere_1": np.array([-0.025, -0.025, 0.02]),
    "sphere_2": np.array([0.025, -0.025, 0.02]),
    "sphere_3": np.array([0.025, 0.025, 0.02]),
}
Y_PHANTOM = se3.make(se3.matrix_from_euler(np.radians([0.5, -0.3, 4.0])), [0.3, 0.01, 0.0])


def _layout_misfit_mm(layout, printed):
    names = sorted(printed)
    P = np.array([layout[t] for t in names])
    Q = np.array([printed[t] for t in names])
    aligned = se3.apply(se3.kabsch(P, Q), P)
    return float(np.sqrt(np.mean(np.sum((aligned - Q) ** 2, axis=1))) * 1e3)


def test_estimated_layout_is_never_worse_than_one_marker(rng):
    """A phantom printed 0.3 mm (1 σ per axis) off its CAD: the fit with the CAD as a prior
    at that tolerance estimates the printed layout (closer to it than the CAD) and is no
    worse than one marker (20 trials, localization noise 0.05 mm per axis)."""
    rot = {"single": [], "cad": [], "estimated": []}
    misfit_cad, misfit_est = [], []
    for _ in range(20):
        printed = {k: v + rng.normal(0.0, 0.3e-3, 3) for k, v in CAD_LAYOUT.items()}
        obs = []
        for name, c in printed.items():
            obs += observations(se3.apply(Y_PHANTOM, c), name, noise_mm=0.05, rng=rng)
        single = calibrate([o for o in obs if o.target == "sphere_1"])
        exact = calibrate(obs, CAD_LAYOUT)
        est = calibrate(obs, CAD_LAYOUT, layout_sigma_mm=0.3)
        assert exact.layout is None and est.layout is not None and est.layout_weight > 0
        for key, res in (("single", single), ("cad", exact), ("estimated", est)):
            rot[key].append(pose_errors(res.T_ee_us)[1])
        misfit_cad.append(_layout_misfit_mm(CAD_LAYOUT, printed))
        misfit_est.append(_layout_misfit_mm(est.layout, printed))
    med = {k: float(np.median(v)) for k, v in rot.items()}
    assert med["estimated"] <= 1.1 * med["single"], med
    # The estimated layout is closer to the printed one than the CAD is.
    assert np.median(misfit_est) < 0.5 * np.median(misfit_cad)


def test_a_tight_layout_prior_is_the_exact_cad_fit(rng):
    """σ_tol → 0 gives the paper's exact-layout loss (the prior pins every sphere)."""
    obs = []
    for name, c in CAD_LAYOUT.items():
        obs += observations(se3.apply(Y_PHANTOM, c), name, noise_mm=0.05, rng=rng)
    exact = calibrate(obs, CAD_LAYOUT)
    tight = calibrate(obs, CAD_LAYOUT, layout_sigma_mm=1e-5)
    assert se3.translation_distance(tight.T_ee_us, exact.T_ee_us) < 1e-8
    assert np.degrees(se3.rotation_angle(tight.T_ee_us, exact.T_ee_us)) < 1e-5
    for t, c in CAD_LAYOUT.items():
        assert np.linalg.norm(tight.layout[t] - c) < 1e-8
    with pytest.raises(ValueError, match="layout_sigma_mm"):
        calibrate(obs, CAD_LAYOUT, layout_sigma_mm=-1.0)


def test_a_contaminated_first_localization_starts_from_the_largest_agreeing_set(rng):
    """Uncalibrated, half the sweeps may take a plate 20 mm away for the sphere: the
    closed form on all of them is a compromise far from the truth, and the outlier stage
    then keeps a handful of accidental agreements. The largest agreeing set's closed form
    (RANSAC) finds the sphere's sweeps, and the calibration from it keeps exactly them."""
    centre = np.array([0.3, 0.0, 0.02])
    obs = observations(centre, noise_mm=0.15, rng=rng)
    wrong = rng.choice(len(obs), 21, replace=False)
    for i in wrong:
        o = obs[i]
        direction = rng.normal(size=3)
        spot = centre + 0.022 * direction / np.linalg.norm(direction)
        p = se3.apply(se3.invert(o.T_base_ee @ T_EE_US_TRUE), spot)
        obs[i] = Observation(o.target, o.pose_id, p, o.T_base_ee)
    d_mm, d_deg = pose_errors(linear_initialisation(obs))
    assert d_mm > 5 or d_deg > 5  # the compromise
    T0, agree = consensus_initialisation(obs)
    assert set(np.flatnonzero(agree)) == set(range(len(obs))) - set(wrong)
    res = calibrate(obs, T_init=T0, first_fit=agree)
    assert set(np.flatnonzero(res.retained)) == set(range(len(obs))) - set(wrong)
    d_mm, d_deg = pose_errors(res.T_ee_us)
    assert d_mm < 1.0 and d_deg < 1.0
    # Seeded: the same observations, the same start.
    assert np.array_equal(consensus_initialisation(obs)[0], T0)
    with pytest.raises(CalibrationError, match="first fit"):
        calibrate(obs, first_fit=np.zeros(len(obs), bool))
