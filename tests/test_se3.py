"""Property tests of the SE(3) helpers with seeded loops."""

from __future__ import annotations

import re

import numpy as np
import pytest

from calib import se3

N = 500
TOL = 1e-12


def random_transforms(rng: np.random.Generator, n: int) -> np.ndarray:
    rotvec = rng.normal(size=(n, 3))
    rotvec *= (rng.uniform(0, np.pi * 0.999, n) / np.linalg.norm(rotvec, axis=1))[:, None]
    return se3.make(se3.matrix_from_rotvec(rotvec), rng.uniform(-1, 1, (n, 3)))


def test_inverse_composes_to_identity(rng):
    T = random_transforms(rng, N)
    eye = np.broadcast_to(np.eye(4), T.shape)
    np.testing.assert_allclose(T @ se3.invert(T), eye, atol=TOL)
    np.testing.assert_allclose(se3.invert(T) @ T, eye, atol=TOL)
    np.testing.assert_allclose(se3.invert(T), np.linalg.inv(T), atol=TOL)


def test_composition_applies_in_order(rng):
    T_a_b, T_b_c = random_transforms(rng, N), random_transforms(rng, N)
    P_c = rng.normal(size=(N, 3))
    np.testing.assert_allclose(
        se3.apply(T_a_b @ T_b_c, P_c), se3.apply(T_a_b, se3.apply(T_b_c, P_c)), atol=TOL
    )
    # One transform, many points.
    P = rng.normal(size=(7, 3))
    np.testing.assert_allclose(se3.apply(T_a_b[0], P), (T_a_b[0][:3, :3] @ P.T).T + T_a_b[0][:3, 3])


def test_rotvec_round_trip(rng):
    T = random_transforms(rng, N)
    R = T[:, :3, :3]
    np.testing.assert_allclose(se3.matrix_from_rotvec(se3.rotvec_from_matrix(R)), R, atol=TOL)
    np.testing.assert_allclose(se3.matrix_from_pose6(se3.pose6_from_matrix(T)), T, atol=TOL)


@pytest.mark.parametrize("seq", ["xyz", "XYZ", "zyx"])
def test_euler_round_trip(rng, seq):
    angles = rng.uniform(-np.pi, np.pi, (N, 3))
    angles[:, 1] = rng.uniform(-1.4, 1.4, N)  # away from gimbal lock
    R = se3.matrix_from_euler(angles, seq=seq)
    np.testing.assert_allclose(se3.euler_from_matrix(R, seq=seq), angles, atol=1e-9)


def test_exp_log_round_trip(rng):
    T = random_transforms(rng, N)
    np.testing.assert_allclose(se3.exp(se3.log(T)), T, atol=1e-10)
    xi = rng.normal(size=(N, 6))
    xi[:, 3:] *= 0.5
    np.testing.assert_allclose(se3.log(se3.exp(xi)), xi, atol=1e-10)
    # The small-angle series branch agrees with the closed form.
    tiny = np.array([1e-3, -2e-3, 5e-4, 1e-8, -2e-8, 3e-8])
    np.testing.assert_allclose(se3.log(se3.exp(tiny)), tiny, atol=1e-15)


def test_exp_is_a_one_parameter_group(rng):
    xi = rng.normal(size=6) * 0.3
    np.testing.assert_allclose(se3.exp(0.3 * xi) @ se3.exp(0.7 * xi), se3.exp(xi), atol=1e-12)


def test_distances(rng):
    T = random_transforms(rng, 1)[0]
    angle = 0.3
    R = se3.matrix_from_rotvec([0.0, 0.0, angle])
    T2 = T @ se3.make(R, [0.0, 0.0, 0.0])
    assert se3.rotation_angle(T, T2) == pytest.approx(angle, abs=1e-12)
    T3 = se3.make(T[:3, :3], T[:3, 3] + [0.003, 0.004, 0.0])
    assert se3.translation_distance(T, T3) == pytest.approx(0.005, abs=1e-15)
    assert se3.rotation_angle(T, T3) == pytest.approx(0.0, abs=1e-7)


@pytest.mark.parametrize(
    ("T", "message"),
    [
        (np.eye(3), "shape (3, 3), a rigid transform is (4, 4)"),
        (np.full((4, 4), np.nan), "NaN or infinite"),
        (np.vstack([np.eye(4)[:3], [0.0, 0.0, 0.1, 1.0]]), "last row"),
        (np.diag([1.0, 1.001, 1.0, 1.0]), "not a rotation"),
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "reflection"),
        ("not a matrix", "not a matrix of numbers"),
    ],
)
def test_check_refuses_what_is_not_a_rigid_transform(T, message):
    from calib.errors import TransformError, UscalError

    with pytest.raises(TransformError, match="T_ee_us: .*" + re.escape(message)):
        se3.check(T, "T_ee_us")
    assert issubclass(TransformError, UscalError)  # one line from the CLI


def test_check_passes_rigid_transforms_and_batches():
    from calib.errors import TransformError

    T = se3.exp(np.array([[0.01, 0.02, 0.03, 0.1, -0.2, 0.3], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]))
    assert se3.check(T, "poses", batch=True) is not None
    with pytest.raises(TransformError, match=r"poses: shape \(2, 4, 4\)"):
        se3.check(T, "poses")
    # A file's few decimals are within the tolerance.
    np.testing.assert_array_equal(se3.check(T[0].round(6), "T"), T[0].round(6))


def test_the_method_refuses_a_wrong_matrix_where_it_enters():
    """A scaled mount or a reflected flange pose is refused by name at the localizer's and
    the calibration's entry, not found by the error it causes later."""
    from calib.calibration.markers import Observation, calibrate
    from calib.errors import TransformError
    from calib.localize import LocalizerConfig, localize_sphere
    from calib.records import Sweep

    poses = np.array([se3.make(np.eye(3), [0.0, 0.0, z]) for z in (-1e-3, 0.0, 1e-3)])
    sweep = Sweep(
        "sphere_1", 7, np.zeros((3, 20, 20), np.uint8), (2e-4, 2e-4), np.zeros((3, 6)), poses
    )
    with pytest.raises(TransformError, match="T_ee_us: not a rigid transform"):
        localize_sphere([sweep], np.diag([1e-3, 1e-3, 1e-3, 1.0]), 5e-3, LocalizerConfig())
    obs = [Observation("sphere_1", i, np.zeros(3), np.eye(4)) for i in range(4)]
    obs[2] = Observation("sphere_1", 2, np.zeros(3), np.diag([1.0, -1.0, 1.0, 1.0]))
    with pytest.raises(TransformError, match="flange poses T_base_ee: not a rigid transform"):
        calibrate(obs)
