"""Pose planning (calib.acquisition.planning): the paper's plan as sweep poses, the information of
T_ee_us with the target's position unknown, its prediction against a Monte Carlo of the
least-squares fit, the shared offset, and the selection."""

from __future__ import annotations

import numpy as np
import pytest

from calib import se3
from calib.acquisition.observability import jacobians
from calib.acquisition.planning import (
    Candidates,
    NoiseModel,
    PlanningConfig,
    SweepPose,
    bias_covariance,
    image_metric,
    paper_poses,
    predict,
    select_sweeps,
    sweep_commands,
)
from calib.acquisition.protocol import ProtocolConfig, plan_sweeps

X = se3.make(se3.matrix_from_euler(np.radians([90.0, 3.0, -2.0])), [0.004, -0.002, 0.15])
TAUGHT = se3.make(se3.matrix_from_euler(np.radians([180.0, 0.0, 30.0])), [0.3, 0.1, 0.35])
DEPTH = 0.02
NOISE = NoiseModel(0.015, 0.04, 0.055)


def _candidates(poses, layout=None, taught=(TAUGHT,), layout_sigma_mm=0.0) -> Candidates:
    T_ref, p_us, idx = [], [], []
    for k, T0 in enumerate(taught):
        for pose in poses:
            T_ref.append(sweep_commands(T0, X, DEPTH, pose, half_length=0.01, n_frames=3)[1])
            p_us.append(pose.target_in_image(DEPTH))
            idx.append(k)
    return Candidates.build(
        np.array(T_ref),
        X,
        np.array(p_us),
        idx,
        NOISE,
        layout=layout,
        layout_sigma_mm=layout_sigma_mm,
    )


def test_the_papers_plan_is_its_sweep_poses_to_the_last_bit():
    cfg = ProtocolConfig(rotation_deg=12.5, translation_mm=3.3)
    plan = plan_sweeps("sphere_1", TAUGHT, X, cfg)
    poses = paper_poses(12.5, 3.3)
    assert len(poses) == 45 == len(set(poses))
    for p, pose in zip(plan, poses, strict=True):
        assert p.pose == pose
        again = sweep_commands(
            TAUGHT, X, 0.02, pose, half_length=0.01, n_frames=cfg.frames_per_sweep
        )
        assert np.array_equal(p.T_base_ee, again)
        # The target stays where the pose puts it in the image (with this T_ee_us).
        centre = se3.apply(TAUGHT @ X, [0.0, 0.02, 0.0])
        seen = se3.apply(se3.invert(p.T_base_ee[10] @ X), centre)
        np.testing.assert_allclose(seen, pose.target_in_image(0.02), atol=1e-12)


def _monte_carlo(cands: Candidates, chosen, trials=400, seed=1):
    """Sample covariance of θ from the linearized fit calib.calibration.markers makes: centres with
    the candidates' anisotropic noise S, fitted (θ and the nuisance together) by least
    squares that weighs every axis alike."""
    assert cands.prior is None  # an exact layout, or free centres
    rng = np.random.default_rng(seed)
    k = np.asarray(chosen)
    G, D, S = cands.G[k], cands.D[k], cands.S[k]
    L = np.linalg.cholesky(S)
    J = np.concatenate([G, D], axis=2).reshape(-1, G.shape[2] + D.shape[2])
    thetas = []
    for _ in range(trials):
        r = np.einsum("nij,nj->ni", L, rng.normal(size=(len(k), 3))).ravel()
        thetas.append(np.linalg.lstsq(J, r, rcond=None)[0][:6])
    return np.cov(np.array(thetas).T)


@pytest.mark.parametrize("multi", [False, True])
def test_predicted_covariance_is_the_least_squares_fits(multi):
    poses = paper_poses(10.0, 3.0)
    taught = [
        TAUGHT,
        TAUGHT @ se3.make(np.eye(3), [0.03, 0.0, 0.0]),
        TAUGHT @ se3.make(np.eye(3), [0.0, 0.03, 0.0]),
    ]
    centres = {k: se3.apply(T @ X, [0.0, DEPTH, 0.0]) for k, T in enumerate(taught)}
    cands = _candidates(poses[:20], centres if multi else None, taught=taught)
    chosen = list(range(len(cands)))
    M = image_metric(X, np.array([[x, y, 0.0] for x in (-0.01, 0.01) for y in (0.0, 0.03)]))
    p = predict(cands, chosen, M)
    mc = _monte_carlo(cands, chosen, trials=1500)
    # The rotation and translation variances agree within the Monte Carlo's spread.
    np.testing.assert_allclose(np.diag(mc), np.diag(p.covariance), rtol=0.12)
    assert p.rotation_deg == pytest.approx(np.degrees(np.sqrt(np.trace(mc[:3, :3]))), rel=0.08)


def test_the_fits_spread_is_the_inverse_information_for_isotropic_noise():
    """Sanity: with the same noise on every axis, the fit that weighs the axes alike is
    the efficient one, and the prediction is the inverse of the information; with the
    image's anisotropic noise it is larger."""
    poses = PlanningConfig(max_rotation_deg=20, max_lateral_mm=4, max_axial_mm=4).candidates()
    T_ref = np.array(
        [sweep_commands(TAUGHT, X, DEPTH, q, half_length=0.01, n_frames=3)[1] for q in poses[::9]]
    )
    p_us = np.array([q.target_in_image(DEPTH) for q in poses[::9]])
    idx = np.zeros(len(p_us), dtype=int)
    M = np.eye(6)
    iso = Candidates.build(T_ref, X, p_us, idx, NoiseModel(0.04, 0.04, 0.04))
    chosen = range(len(iso))
    fisher = np.linalg.inv(predict(Candidates(iso.A, iso.B, iso.target), chosen, M).covariance)
    np.testing.assert_allclose(predict(iso, chosen, M).covariance @ fisher, np.eye(6), atol=1e-8)
    aniso = Candidates.build(T_ref, X, p_us, idx, NOISE)
    efficient = predict(Candidates(aniso.A, aniso.B, aniso.target), chosen, M)
    assert predict(aniso, chosen, M).rotation_deg > efficient.rotation_deg


def test_a_shared_offset_moves_the_translation_by_the_mount():
    """A constant offset δ of every centre in the image frame is fitted as t_X − R_X δ:
    the rotation is untouched, whatever the plan."""
    cov = bias_covariance(X, [0.01, 0.05, 0.02])
    np.testing.assert_allclose(cov[:3], 0.0)
    R = X[:3, :3]
    np.testing.assert_allclose(cov[3:, 3:], R @ np.diag([1e-4, 25e-4, 4e-4]) @ R.T)
    # The same through the Jacobians: observations p + δ at any poses are explained
    # exactly by θ = (0, −R_X δ) with the sphere where it was.
    poses = paper_poses(10.0, 3.0)
    T = np.array(
        [sweep_commands(TAUGHT, X, DEPTH, p, half_length=0.01, n_frames=3)[1] for p in poses]
    )
    P = np.array([p.target_in_image(DEPTH) for p in poses])
    delta = np.array([0.02, -0.05, 0.01])  # mm
    G = jacobians(T, X, P)
    shift = np.einsum("nij,j->ni", G, np.r_[np.zeros(3), -R @ delta])
    seen = np.einsum("nij,j->ni", T[:, :3, :3] @ R, delta)
    np.testing.assert_allclose(shift + seen, 0.0, atol=1e-12)


def test_selection_beats_the_papers_plan_and_never_repeats_a_pose():
    cfg = PlanningConfig(max_rotation_deg=20.0, max_lateral_mm=6.0, max_axial_mm=6.0)
    dense = cfg.candidates()
    cands = _candidates(dense)
    paper = _candidates(paper_poses(10.0, 3.0))
    M = image_metric(X, np.array([[x, y, 0.0] for x in (-0.01, 0.01) for y in (0.0, 0.03)]))
    chosen = select_sweeps(cands, 15, criterion="D", M=M)
    assert len(set(chosen)) == 15
    opt, ref = predict(cands, chosen, M), predict(paper, range(45), M)
    # A third of the sweeps, and still better determined (rotation) than the paper's 45.
    assert opt.rotation_deg < ref.rotation_deg
    # The exchange only ever improves on the greedy start; every criterion runs.
    greedy = select_sweeps(cands, 15, criterion="D", M=M, max_passes=0)
    H = {k: np.linalg.slogdet(np.linalg.inv(predict(cands, c, M).covariance))[1]
         for k, c in (("greedy", greedy), ("exchanged", chosen))}  # fmt: skip
    assert H["exchanged"] >= H["greedy"] - 1e-9
    for criterion in ("A", "E"):
        assert len(set(select_sweeps(cands, 6, criterion=criterion, M=M))) == 6
    with pytest.raises(ValueError, match="criterion"):
        select_sweeps(cands, 3, criterion="Z", M=M)  # type: ignore[arg-type]


def test_the_candidate_grid_is_symmetric_and_complete():
    cfg = PlanningConfig(max_rotation_deg=20, rotation_step_deg=10, max_lateral_mm=4,
                         max_axial_mm=2, shift_step_mm=2)  # fmt: skip
    poses = cfg.candidates()
    assert len(poses) == 5**3 * 5 * 3
    assert SweepPose((-20.0, 0.0, 20.0), -4.0, 2.0) in poses
    # The localizer's noise and the arm's pose noise, added in quadrature.
    assert cfg.noise() == NoiseModel(*np.hypot(cfg.localization_noise_mm, cfg.pose_noise_mm))


def test_a_three_marker_plan_sees_every_sphere_and_a_loose_layout_informs_less():
    """Jointly planned spheres share the phantom's pose: each keeps the minimum of
    sweeps, and a layout printed loosely (its centres free within the tolerance) informs
    T_ee_us less than the exact CAD, and more than free centres."""
    taught = [TAUGHT @ se3.make(np.eye(3), d) for d in ([0, 0, 0], [0.03, 0, 0], [0, 0.03, 0])]
    centres = {k: se3.apply(T @ X, [0.0, DEPTH, 0.0]) for k, T in enumerate(taught)}
    poses = PlanningConfig(max_rotation_deg=20, max_lateral_mm=4, max_axial_mm=4).candidates()
    M = image_metric(X, np.array([[x, y, 0.0] for x in (-0.01, 0.01) for y in (0.0, 0.03)]))
    cands = _candidates(poses[::7], centres, taught=taught)
    chosen = select_sweeps(cands, 18, criterion="D", M=M, min_per_target=5)
    per = np.bincount(cands.target[chosen], minlength=3)
    assert per.min() >= 5 and per.sum() == 18
    exact = predict(cands, chosen, M).rotation_deg
    loose = _candidates(poses[::7], centres, taught=taught, layout_sigma_mm=0.1)
    free = _candidates(poses[::7], None, taught=taught)
    assert exact <= predict(loose, chosen, M).rotation_deg <= predict(free, chosen, M).rotation_deg
    with pytest.raises(ValueError, match="cannot give"):
        select_sweeps(cands, 12, criterion="D", M=M, min_per_target=5)


def test_candidates_of_many_rows_keep_each_sweeps_information_with_its_shared_error():
    """A sweep of many observations (a wire's frames) enters the plan as the square root
    of its information: the sums equal JᵀΣ⁻¹J with Σ = I + KKᵀ (the error its
    observations share), computed densely, sweep by sweep; without a shared error, JᵀJ."""
    rng = np.random.default_rng(3)
    n, R, m = 4, 12, 5
    Jt, Jn, K = rng.normal(size=(n, R, 6)), rng.normal(size=(n, R, m)), rng.normal(size=(n, R, 2))
    cands = Candidates.from_rows(Jt, Jn, np.zeros(n), shared=K)
    assert cands.A.shape == (n, 6 + m, 6) and cands.B.shape == (n, 6 + m, m)
    S_AA, S_AB, S_BB = cands.sums([0, 2, 3])
    dense = np.zeros((6 + m, 6 + m))
    for k in (0, 2, 3):
        J = np.concatenate([Jt[k], Jn[k]], axis=1)
        dense += J.T @ np.linalg.solve(np.eye(R) + K[k] @ K[k].T, J)
    np.testing.assert_allclose(S_AA, dense[:6, :6], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(S_AB, dense[:6, 6:], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(S_BB, dense[6:, 6:], rtol=1e-9, atol=1e-9)
    # The shared error costs information: less than the same rows independent.
    plain = Candidates.from_rows(Jt, Jn, np.zeros(n)).sums([0, 2, 3])[0]
    np.testing.assert_allclose(plain, np.einsum("nri,nrj->ij", Jt[[0, 2, 3]], Jt[[0, 2, 3]]))
    assert np.linalg.eigvalsh(plain - S_AA).min() > -1e-9
    assert np.trace(plain - S_AA) > 0.1 * np.trace(plain)
