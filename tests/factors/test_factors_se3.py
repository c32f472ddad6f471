"""factors.se3 against gtsam.Pose3 (Expmap / Logmap / AdjointMap / retract)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors.se3 import (
    exp_se3_batch,
    adjoint_se3,
    check_pose,
    check_poses,
    check_rotation,
    exp_se3,
    exp_so3,
    hat,
    inverse_se3,
    log_se3,
    log_so3,
    rotation_angle,
    vee,
)

# Tolerance of agreement with gtsam away from theta = pi (both are closed forms in float64).
TOL = 1e-12
# Near theta = pi gtsam's Logmap switches to an approximation with errors up to ~4e-7
# (measured at pi - 1e-3); ours reads the axis from the symmetric part of R and stays at
# ~1e-12, so near pi we compare with the known xi tightly and with gtsam loosely.
TOL_NEAR_PI_GTSAM = 1e-6
TOL_NEAR_PI_TRUTH = 1e-10


def _xi(rng: np.random.Generator, angle: float) -> np.ndarray:
    w = rng.normal(size=3)
    w *= angle / np.linalg.norm(w)
    return np.concatenate([w, rng.normal(scale=5.0, size=3)])


def test_hat_is_cross_product_and_vee_inverts_it():
    rng = np.random.default_rng(0)
    w, x = rng.normal(size=(2, 3))
    np.testing.assert_allclose(hat(w) @ x, np.cross(w, x), atol=1e-15)
    np.testing.assert_allclose(vee(hat(w)), w, atol=0)
    np.testing.assert_allclose(hat(w), gtsam.Rot3.Hat(w), atol=0)
    batch = rng.normal(size=(4, 5, 3))
    assert hat(batch).shape == (4, 5, 3, 3)
    np.testing.assert_allclose(hat(batch)[2, 3], hat(batch[2, 3]), atol=0)
    with pytest.raises(ValueError, match="3"):
        hat(np.zeros(4))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-6, 1e-4, 0.3, 1.0, 2.5, 3.0])
def test_exp_log_match_gtsam(angle):
    rng = np.random.default_rng(int(angle * 1000) + 1)
    for _ in range(10):
        xi = _xi(rng, angle)
        T = exp_se3(xi)
        G = gtsam.Pose3.Expmap(xi)
        np.testing.assert_allclose(T, G.matrix(), atol=TOL, rtol=0)
        np.testing.assert_allclose(log_se3(G.matrix()), gtsam.Pose3.Logmap(G), atol=TOL * 10, rtol=0)
        np.testing.assert_allclose(log_se3(T), xi, atol=1e-10, rtol=0)
        np.testing.assert_allclose(exp_so3(xi[:3]), gtsam.Rot3.Expmap(xi[:3]).matrix(), atol=TOL)


@pytest.mark.parametrize("gap", [1e-2, 1e-3, 1e-5, 1e-8])
def test_log_near_pi_matches_gtsam(gap):
    rng = np.random.default_rng(7)
    for _ in range(10):
        xi = _xi(rng, np.pi - gap)
        G = gtsam.Pose3.Expmap(xi)
        ours = log_se3(G.matrix())
        np.testing.assert_allclose(ours, xi, atol=TOL_NEAR_PI_TRUTH, rtol=0)
        np.testing.assert_allclose(ours, gtsam.Pose3.Logmap(G), atol=TOL_NEAR_PI_GTSAM, rtol=0)
        # and it is a valid logarithm of the same pose
        np.testing.assert_allclose(exp_se3(ours), G.matrix(), atol=1e-9)
        assert np.linalg.norm(log_so3(G.rotation().matrix())) <= np.pi + 1e-12


def test_right_perturbation_is_gtsam_retract_and_adjoint():
    rng = np.random.default_rng(3)
    for _ in range(10):
        T = exp_se3(_xi(rng, 1.0))
        xi = rng.normal(size=6)
        P = gtsam.Pose3(T)
        np.testing.assert_allclose(T @ exp_se3(xi), P.retract(xi).matrix(), atol=1e-12)
        np.testing.assert_allclose(adjoint_se3(T), P.AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(
            T @ exp_se3(xi) @ inverse_se3(T), exp_se3(adjoint_se3(T) @ xi), atol=1e-10
        )
        np.testing.assert_allclose(inverse_se3(T), P.inverse().matrix(), atol=1e-12)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="xi"):
        exp_se3(np.zeros(5))
    with pytest.raises(ValueError, match="non-finite"):
        exp_se3(np.array([np.nan, 0, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="4, 4"):
        log_se3(np.eye(3))


ANGLES = [0.0, 1e-12, 1e-8, 1e-4, 0.3, np.pi / 2, 2.5, np.pi - 1e-6, np.pi]


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("theta", ANGLES)
def test_rotation_angle_closed_form(theta):
    """Q Rz(theta) Q^T turns by exactly theta about Q e_z, for any rotation Q (here from gtsam)."""
    rng = np.random.default_rng(int(theta * 1e6) % 1000)
    Q = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
    R = Q @ _rot_z(theta) @ Q.T
    assert rotation_angle(_rot_z(theta)) == pytest.approx(theta, abs=1e-15)
    assert rotation_angle(R) == pytest.approx(theta, abs=1e-14)  # rounding of the product only
    assert isinstance(rotation_angle(R), float)


def test_rotation_angle_batch_equals_single_and_acos_away_from_the_ends():
    rng = np.random.default_rng(5)
    Rs = np.stack([gtsam.Rot3.Expmap(w).matrix() for w in rng.normal(size=(20, 3))]).reshape(4, 5, 3, 3)
    batch = rotation_angle(Rs)
    assert batch.shape == (4, 5)
    single = np.array([[rotation_angle(R) for R in row] for row in Rs])
    np.testing.assert_array_equal(batch, single)
    acos = np.arccos(np.clip((np.trace(Rs, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    np.testing.assert_allclose(batch, acos, atol=1e-12)
    with pytest.raises(ValueError, match="3, 3"):
        rotation_angle(np.eye(4))


def test_pose_validator_one_and_many():
    rng = np.random.default_rng(3)
    T = exp_se3(_xi(rng, 1.0))
    np.testing.assert_array_equal(check_pose(T), T)
    np.testing.assert_array_equal(check_poses(np.stack([T, T])), np.stack([T, T]))
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])  # orthogonal, det -1: not a rotation
    sheared = T.copy()
    sheared[0, 1] += 1e-3
    bottom = T.copy()
    bottom[3, 0] = 0.1
    nan = T.copy()
    nan[1, 3] = np.nan
    for bad, msg in ((reflection, "not orthonormal"), (sheared, r"defect [0-9.e-]+ > tolerance 0.0001"), (bottom, "bottom row"),
                     (nan, "non-finite"), (np.eye(3), "(4, 4)")):
        with pytest.raises(ValueError, match=msg):
            check_pose(bad, "X")
    with pytest.raises(ValueError, match="X: pose 1 rotation is not orthonormal"):
        check_poses(np.stack([T, sheared]), "X")
    check_pose(sheared, rot_tol=1e-2)  # within a looser tolerance
    with pytest.raises(ValueError, match="not orthonormal"):
        check_rotation(reflection[:3, :3])
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        check_rotation(np.eye(4))


def test_exp_se3_batch_equals_exp_se3_and_the_matrix_exponential():
    """Batched Exp (tiny, series-range and large angles) against exp_se3 row by row and scipy's expm."""
    import scipy.linalg

    rng = np.random.default_rng(1)
    xi = rng.normal(size=(12, 6)) * [0.5, 0.5, 0.5, 2, 2, 2]
    xi[0, :3] = 0.0
    xi[1, :3] = [1e-9, -2e-9, 0.0]
    xi[2, :3] = [0.01, 0.02, -0.015]  # below the series threshold
    batch = exp_se3_batch(xi)
    for k in range(len(xi)):
        np.testing.assert_allclose(batch[k], exp_se3(xi[k]), atol=1e-14)
        M = np.zeros((4, 4))
        M[:3, :3] = hat(xi[k, :3])
        M[:3, 3] = xi[k, 3:]
        np.testing.assert_allclose(batch[k], scipy.linalg.expm(M), atol=1e-10)
        np.testing.assert_allclose(log_se3(batch[k]), xi[k], atol=1e-9)
    assert exp_se3_batch(xi.reshape(3, 4, 6)).shape == (3, 4, 4, 4)
    with pytest.raises(ValueError, match="shape"):
        exp_se3_batch(np.zeros((2, 5)))
